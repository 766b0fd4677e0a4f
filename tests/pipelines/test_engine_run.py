"""The kernel engine of this process (CI runs this file and tests/kernels once more with TI_CMAX_ENGINE=quadrants):
the one chosen is the one imported, and a short `slam` on it is accurate and says in report.json which it was."""
import json
import os

from ti_cmax.cli import main
from ti_cmax.io import read_tum
from ti_cmax.kernels import runtime
from ti_cmax.kernels.engine import engine_info, engine_name
from ti_cmax.metrics import evaluate_rotations


def test_the_chosen_engine_is_the_one_imported(ti_runtime):
    assert runtime.ENGINE == engine_name() == ti_runtime.__name__
    if os.environ.get("TI_CMAX_ENGINE"):
        assert runtime.ENGINE == os.environ["TI_CMAX_ENGINE"]
    assert engine_info()["version"] == ".".join(map(str, ti_runtime.__version__))


def test_slam_end_to_end_names_its_engine(engine_dataset, tmp_path):
    out = tmp_path / "slam"
    assert main(["slam", str(engine_dataset), "--out", str(out), "--quiet", "--set", "pano_height=256"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "ok" and report["engine"] == engine_info()
    assert report["engine"]["name"] == runtime.ENGINE
    err = evaluate_rotations(read_tum(engine_dataset / "groundtruth.txt"), read_tum(out / "trajectory.txt"))
    assert err.abs_rmse_deg < 0.3  # measured at one thread: 0.14-0.15 deg with either engine

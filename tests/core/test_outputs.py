"""Output files get the mode the umask gives (issue 18, point 3): the atomic temp-file-and-rename writer must not
leave mkstemp's 0600 on them."""
import os
import stat

import pytest

from ti_cmax.cli import main
from ti_cmax.outputs import atomic_path


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600)])
def test_atomic_path_respects_umask(tmp_path, umask, mask, mode):
    umask(mask)
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        tmp.write_text("x")
    assert stat.S_IMODE(target.stat().st_mode) == mode


def test_command_outputs_respect_umask(tmp_path, umask, capsys):
    from ti_cmax.camera import Camera
    from ti_cmax.io import write_calib_txt

    umask(0o022)
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text("".join(f"{0.001 * i:.6f} {i % 240} {i % 180} {i % 2}\n" for i in range(1, 50)))
    write_calib_txt(d / "calib.txt", Camera(240, 180, 199.0, 199.0, 120.0, 90.0))
    gt = tmp_path / "gt.txt"
    gt.write_text("".join(f"{0.1 * i:.1f} 0 0 0 0 0 0 1\n" for i in range(30)))
    assert main(["convert", str(d), str(tmp_path / "ev.h5"), "--quiet"]) == 0
    assert main(["evaluate", "--groundtruth", str(gt), "--estimate", str(gt), "--out", str(tmp_path / "e.json")]) == 0
    for name in ("ev.h5", "e.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name


def test_json_ready_makes_strict_json():
    """Every report.json is strict JSON: NaN (an error over a sequence shorter than its window) was written as NaN."""
    import json

    import numpy as np

    from ti_cmax.outputs import json_ready

    doc = json_ready({"a": float("nan"), "b": [np.float32(1.5), np.inf], "c": np.int64(3), "d": np.array([1.0, np.nan]),
                      "e": np.bool_(True)})
    assert json.loads(json.dumps(doc, allow_nan=False)) == {"a": None, "b": [1.5, None], "c": 3, "d": [1.0, None],
                                                            "e": True}

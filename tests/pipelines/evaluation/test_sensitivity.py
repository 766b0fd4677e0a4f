import json

import pytest

from ti_cmax.cli import main


@pytest.mark.slow
def test_sweep_cli_quick(tmp_path, capsys, ti_runtime):
    out = tmp_path / "sweep"
    assert main(["sweep", "--out", str(out), "--quick", "--duration", "0.6", "--scene", "bay",
                 "--parameters", "map_height", "--quiet"]) == 0
    rows = json.loads((out / "sweep.json").read_text())
    assert [r["value"] for r in rows] == [256, 512]
    assert all(r["abs_rmse_deg"] < 2.0 and r["us_per_event_backend"] > 0 for r in rows)
    assert (out / "sweep.png").stat().st_size > 1000 and "map resolution" in (out / "sweep.md").read_text()
    assert main(["sweep", "--out", str(tmp_path / "x"), "--parameters", "nonsense", "--quiet"]) == 2
    assert not (tmp_path / "x").exists()

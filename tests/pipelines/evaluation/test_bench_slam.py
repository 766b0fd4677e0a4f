"""Smoke test of the CMax-SLAM benchmark: one tiny sequence, every method row present and well formed."""
import math

import pytest

from ti_cmax.pipelines.evaluation.bench_slam import METHODS, ROW_KEYS, bench_sequence, format_table


@pytest.mark.slow
def test_bench_sequence_rows_on_tiny_dvs128():
    res = bench_sequence("DVS128", "city", 0.6, overrides={"pano_height": 128}, quick=True)
    assert res["map_size"] == [256, 128]
    assert res["events"] > 0
    rows = res["rows"]
    assert [r["method"] for r in rows] == list(METHODS)
    for r in rows:
        assert set(ROW_KEYS) <= set(r)
        assert math.isfinite(r["abs_rmse_deg"]) and r["abs_rmse_deg"] >= 0
        assert math.isnan(r["rel_rmse_deg_per_s"])  # 0.6 s: no 1 s relative pair fits
        assert 0 < r["ea_percent"] < 100 and r["gm"] > 0
        assert 0 < r["map_events"] <= res["events"]
        assert r["peak_rss_mb"] > 0
    by = {r["method"]: r for r in rows}
    for name in ("SLAM linear", "SLAM cubic"):
        assert by[name]["frontend_us_per_event"] > 0 and by[name]["backend_us_per_event"] > 0
        assert by[name]["map_events"] == res["events"]  # the back-end settles every event into I_G
    assert by["IMU + offline BA"]["backend_us_per_event"] > 0
    assert by["IMU + offline BA"]["frontend_us_per_event"] is None
    assert by["IMU dead reckoning"]["backend_us_per_event"] is None
    table = format_table(res)
    assert table.count("\n| ") == len(METHODS) + 1  # header + one line per method
    assert "targets:" in table

"""The demo end to end on a short sequence: HDF5 events only (text on request), the run figure and the error over
time beside the comparison figures."""

def test_demo_writes_hdf5_only_and_its_figures(tmp_path):
    from ti_cmax.cli import main

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--duration", "0.4", "--quiet"]) == 0
    seq = {p.name for p in (out / "sequence").iterdir()}
    assert "events.h5" in seq and "events.txt" not in seq
    for name in ("trajectories.png", "errors_over_time.png", "errors.png", "maps.png", "slam/run.png",
                 "slam/map.png"):
        assert (out / name).stat().st_size > 1000, name


def test_quick_benchmark_tables_say_they_are_a_smoke_test():
    from ti_cmax.commands.benchmark import smoke_test_meta
    from ti_cmax.pipelines.evaluation import benchmark as B

    text = B.format_tables([], {"map_height": 64, **smoke_test_meta()})
    assert text.startswith("# CMax-SLAM benchmark: smoke test (--quick)") and "**Smoke test.**" in text
    assert "Smoke test" not in B.format_tables([], {"map_height": 64})

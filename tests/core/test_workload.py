"""Parameters that imply absurd work (a packet every nanosecond, millions of control poses) are refused before any
work, in one line with the estimate."""
from __future__ import annotations

import time

import pytest

from ti_cmax.camera import Camera
from ti_cmax.cli import main
from ti_cmax.config import MAX_WORK_ITEMS, SlamConfig, check_workload, load_config
from ti_cmax.errors import InputError
from ti_cmax.io import write_calib_txt

GOOD = "".join(f"{0.001 * i:.9f} {i * 37 % 240} {i * 53 % 180} {i % 2}\n" for i in range(1, 3001))


def test_check_workload_estimates_and_refuses():
    cfg = load_config(SlamConfig, overrides=["dt_ang_vel=1e-9"])
    with pytest.raises(InputError, match=r"dt_ang_vel=1e-09 s over this recording's 3 s \(t = 0 to 3 s\) means 3e\+09 "
                                         r"front-end packets, more than 1e\+07: refused before any work; set dt_ang_vel "
                                         r"to its scale \(default 0.01 s\)"):
        check_workload(cfg, 0.0, 3.0)
    cfg = load_config(SlamConfig, overrides=["dt_knots=0.001", "backend_sliding_window_stride=0.001"])
    check_workload(cfg, 0.0, 60.0)  # a minute at the finest knots: 60 000 control poses
    with pytest.raises(InputError, match=r"dt_knots=0.001 s over this recording's 20000 s .* means 2e\+07 control "
                                         r"poses"):
        check_workload(cfg, 100.0, 20100.0)
    rt = load_config(SlamConfig, overrides=["realtime_chunk=1e-9"])
    check_workload(rt, 0.0, 1.0)  # the real-time hand-overs only count for a real-time run
    with pytest.raises(InputError, match=r"realtime_chunk=1e-09 s .* 1e\+09 real-time hand-overs"):
        check_workload(rt, 0.0, 1.0, realtime=True)
    check_workload(SlamConfig(), 0.0, 86400.0)  # a day at the defaults: 8.6 M packets
    assert MAX_WORK_ITEMS == 10_000_000


@pytest.mark.parametrize("command", ["slam", "frontend", "star-tracking"])
def test_commands_refuse_absurd_work_before_starting(tmp_path, capsys, command):
    """`--set dt_ang_vel=1e-9` ran for hours (3e8 packets over 0.3 s of data... and 3e8 over 3 s)."""
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text(GOOD)
    write_calib_txt(d / "calib.txt", Camera(240, 180, 199.0, 199.0, 120.0, 90.0))
    out = tmp_path / "out"
    tic = time.perf_counter()
    assert main([command, str(d), "--out", str(out), "--set", "dt_ang_vel=1e-9"]) == 2
    assert time.perf_counter() - tic < 10
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dt_ang_vel=1e-09 s over this recording's 2.999 s" in err[0]
    assert "3e+09 front-end packets" in err[0] and not out.exists()


def test_the_smallest_input_for_a_trustworthy_omega():
    """20 or 100 events gave omega 10 rad/s off with status ok: the rule the status reports from (2000 events per
    packet on a DAVIS240C-sized sensor, scaled with the pixels of larger ones)."""
    from ti_cmax.config import MIN_OMEGA_EVENTS, min_events_for_omega, too_few_events_for_omega

    assert MIN_OMEGA_EVENTS == 2000
    assert min_events_for_omega(240, 180) == min_events_for_omega(128, 128) == 2000
    assert min_events_for_omega(1280, 720) == 42667
    assert too_few_events_for_omega(2000, 240, 180) is None
    assert too_few_events_for_omega(100, 240, 180) == ("100 events are too few for a trustworthy angular velocity on "
                                                       "a 240x180 sensor (at least 2000: with fewer, omega was off by "
                                                       "100 % of the rotation or more)")
    assert "at least 42667" in too_few_events_for_omega(20_000, 1280, 720)

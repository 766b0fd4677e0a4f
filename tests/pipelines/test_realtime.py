"""Real-time replay (slam --realtime): lag fields, the degradation controller, bitwise sameness without degradation,
Ctrl-C, the --parallel CLI, slow consumers of OnlineSlam."""
import json
import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from ti_cmax.config import SlamConfig, load_config
from ti_cmax.events import Events
from ti_cmax.pipelines import realtime as R
from ti_cmax.pipelines.slam import OnlineSlam, run_slam

SMALL = ["--set", "pano_height=256"]


def _realtime(report_dir):
    return json.loads((report_dir / "report.json").read_text())["realtime"]


@pytest.mark.slow
def test_realtime_cli_writes_sane_lag_fields(short_dataset, tmp_path, capsys):
    from ti_cmax.cli import main

    out = tmp_path / "rt"
    assert main(["slam", str(short_dataset), "--out", str(out), "--realtime", "--quiet", *SMALL]) == 0
    assert main(["slam", str(short_dataset), "--out", str(tmp_path / "offline"), "--quiet", *SMALL]) == 0
    assert "real time: lag max" in capsys.readouterr().out
    rt = _realtime(out)
    assert rt["windows"] >= 8
    assert 0.0 <= rt["mean_lag_s"] <= rt["max_lag_s"] < 30.0
    assert rt["latency_mean_s"] >= rt["mean_lag_s"] and rt["latency_max_s"] >= rt["max_lag_s"]
    assert 0.0 < rt["events_used_fraction"] <= 1.0
    assert rt["events_read"] >= rt["events_handed_over"] > 0
    assert rt["wall_seconds"] >= 1.0  # 1.2 s of data replayed at sensor speed cannot end sooner
    cpu = rt["cpu_seconds"]
    assert cpu["frontend"] > 0 and cpu["backend"] > 0 and cpu["io"] >= 0
    # the main process's rest, by part: ingest (checks, hot pixels, slicing), the back-end's input, the replay
    assert cpu["ingest"] > 0 and cpu["handover"] > 0 and cpu["close"] > 0 and cpu["replay"] >= 0
    assert cpu["ingest"] + cpu["handover"] + cpu["close"] + cpu["replay"] == pytest.approx(cpu["other"], abs=0.02)
    assert sum(rt["level_sensor_seconds"].values()) == pytest.approx(1.2, abs=0.15)
    assert rt["degradation_applied"] == (rt["degraded_fraction"] > 0 or rt["input_events_dropped"] > 0
                                         or rt["ba_windows_cut_short"] > 0)
    # the controller's per-window trace: one row per window, the lags of the report, levels in range
    import csv

    with open(out / "realtime_windows.csv", newline="") as fh:
        trace = list(csv.DictReader(fh))
    assert tuple(trace[0]) == R.TRACE_COLUMNS and len(trace) == rt["windows"]
    lags = [float(r["lag_s"]) for r in trace]
    assert max(lags) == pytest.approx(rt["max_lag_s"], abs=1e-5) and float(trace[-1]["t_end"]) > 1.0
    assert all(0 <= int(r["level"]) <= R.MAX_LEVEL and int(r["events"]) >= int(r["ba_events"]) for r in trace)
    assert not (tmp_path / "offline" / "realtime_windows.csv").exists()


@pytest.mark.slow
def test_slow_consumer_degrades_and_bounds_the_lag(short_sequence):
    """Replayed 4x faster than the sensor, the pipeline cannot keep up: the controller degrades, says so, and keeps
    the lag well below that of the same replay with degradation off."""
    ev = short_sequence.events
    base = ["pano_height=256", "realtime_speed=4"]
    off = R.run_realtime(iter([ev]), short_sequence.camera, load_config(
        SlamConfig, None, base + ["realtime_target_lag=1000", "realtime_max_lag=1000"])).report["realtime"]
    on = R.run_realtime(iter([ev]), short_sequence.camera, load_config(
        SlamConfig, None, base + ["realtime_target_lag=0.05", "realtime_max_lag=0.2"])).report["realtime"]
    assert not off["degradation_applied"] and off["events_used_fraction"] == 1.0
    assert on["degradation_applied"] and on["degraded_fraction"] > 0.3
    assert on["frontend_packets_skipped"] > 0 and on["ba_windows_skipped"] + on["ba_windows_sampled_below_cap"] > 0
    assert on["events_used_fraction"] < 1.0
    assert on["max_lag_s"] < 0.6 * off["max_lag_s"]


def _report(t_end, lag, ctl, n=100_000, busy=0.05, ba=0.0):
    """A completed window: ``busy`` wall seconds of worker work for its 0.1 s stride, ``ba`` of them in the BA."""
    if ctl.online is not None:  # the front-end advanced one stride
        ctl.online.frontend_until = t_end
    return SimpleNamespace(t_start=t_end - 0.2, t_end=t_end, num_events=n, events_used=n if ba else 0,
                           optimized=ba > 0, rejected=False, skipped=ba == 0, done_at=ctl.due(t_end) + lag,
                           ba_seconds=ba, busy_seconds=busy, seconds=busy, cut_short=False, evaluations=4 if ba else 0)


def test_controller_rule():
    """Escalate while the lag is above target and not draining, hard bound only at the last level; relax on the
    measured headroom: thinning first (below half the target), then a level only when the level below is predicted
    to cost under RELAX_HEADROOM of the wall time, at least 3 windows after the last change."""
    cfg = load_config(SlamConfig, None, ["realtime_min_window_events=10000", "backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0)
    calls, idle_only = [], []

    def degrade(keep, cap, every, budget, thinning=1, loop_idle_only=False):
        calls.append((keep, cap, every, budget))
        idle_only.append(loop_idle_only)

    ctl.online = SimpleNamespace(degrade=degrade,
                                 frontend_until=0.1,
                                 runner=SimpleNamespace(seconds=0.0))
    ctl.wall0, ctl.t0 = 100.0, 0.0
    ctl.apply()  # what a replay starts with: level 0, whose BA budget is half the lag target (the cold first window)
    assert calls == [(1, None, 1, 0.15)]
    calls.clear()
    t = 0.2
    for lag in (0.5, 0.6, 0.7, 0.8):  # late and getting later: one level per window; BA 0.05 s per 100 000 events
        ctl.on_window(_report(t, lag, ctl, busy=0.08, ba=0.05))
        t += 0.1
    assert ctl.level == 4 and ctl.thinning == 1
    # the trace (realtime_windows.csv): per window the level in force and the one chosen after it
    assert [(row[3], row[-1]) for row in ctl.trace] == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert [row[2] for row in ctl.trace] == pytest.approx([0.5, 0.6, 0.7, 0.8]) and len(ctl.trace[0]) == len(R.TRACE_COLUMNS)
    # from level 1 on, a window's BA has one stride of wall time (0.1 s at speed 1)
    # (level 1: the budget alone; 2: half the events; 3: half the BA windows and packets; 4: no BA)
    assert calls == [(1, None, 1, 0.1), (1, 100_000, 1, 0.1), (2, 100_000, 2, 0.1), (4, 0, 1, 0.1)]
    # from level 1 on, the loop closer's work in flight waits for the worker's idle time
    assert idle_only == [False, True, True, True, True]
    ctl.on_window(_report(t, 1.5, ctl))  # beyond the hard bound and rising: hand over 1 of 2 events
    t += 0.1
    assert ctl.thinning == 2
    ctl.on_window(_report(t, 1.2, ctl))  # falling fast enough to be back under the bound within 5 windows: wait
    t += 0.1
    assert ctl.thinning == 2
    for _ in range(2):  # under half the target: thinning goes first, then (after 3 windows at a level) levels
        ctl.on_window(_report(t, 0.1, ctl))
        t += 0.1
    assert ctl.thinning == 1 and ctl.level == 4
    for _ in range(2):  # level 4 costs 0.5 of the wall time; level 3 adds a BA of 100 000 events on 1 of 2 windows:
        assert ctl.level == 4  # the last BA (0.05 s for 100 000 events) / 2 per 0.1 s stride = 0.25
        ctl.on_window(_report(t, 0.2, ctl))  # under the target (not under half of it: relaxing needs headroom)
        t += 0.1
    assert ctl.level == 3 and calls[-1] == (2, 100_000, 2, 0.1)  # 3 windows after the last change
    assert ctl.predicted[-1] == pytest.approx(0.5 + 0.05 / 2 / 0.1, rel=0.02)
    for _ in range(6):  # level 3 costs 0.9, 0.1 of it in the BA: level 2 (a BA on every window) would cost 1.0
        ctl.on_window(_report(t, 0.1, ctl, n=50_000, busy=0.09, ba=0.01))
        t += 0.1
    assert ctl.level == 3
    for _ in range(3):  # less busy (0.6): level 2 is predicted at 0.7 and is taken
        ctl.on_window(_report(t, 0.1, ctl, n=50_000, busy=0.06, ba=0.01))
        t += 0.1
    assert ctl.level == 2 and calls[-1] == (1, 100_000, 1, 0.1)
    s = ctl.summary()
    assert s["max_lag_s"] == pytest.approx(1.5) and s["level_sensor_seconds"]["4"] > 0 and s["input_max_thinning"] == 2
    assert s["latency_max_s"] == pytest.approx(1.6)  # the lag plus the stride whose events got their first pose


def _cli(args, **kw):
    cmd = [sys.executable, "-m", "ti_cmax.cli", *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)


@pytest.mark.slow
def test_one_thread_bitwise_offline_and_parallel_undegraded_realtime(tmp_path):
    """With one thread: `slam --sequential` and `slam --parallel --realtime` with degradation off (replayed 4x fast)
    write the same trajectory, angular velocity and map, byte for byte (the CLI's --parallel path and the replay's
    chunking change nothing; without --realtime the report has no "realtime" block)."""
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = write_sequence(simulate_sequence(SimulatorConfig(scene="town", sensor="DVS128", duration=0.4, seed=2)),
                         tmp_path / "seq", events_format="h5")
    common = ["--quiet", "--threads", "1", "--set", "pano_height=128"]
    runs = {"offline": ["--sequential"],
            "realtime": ["--parallel", "--realtime", "--set", "realtime_target_lag=1000", "--set",
                         "realtime_max_lag=1000", "--set", "realtime_speed=4"]}
    files = {}
    for name, extra in runs.items():
        # --quiet alone (not the tests' TI_CMAX_NO_PROGRESS) keeps either process's start-up line off stderr
        env = {k: v for k, v in os.environ.items() if k != "TI_CMAX_NO_PROGRESS"}
        proc = _cli(["slam", seq, "--out", tmp_path / name, *common, *extra], env=env)
        assert proc.returncode == 0, proc.stderr
        assert "[Taichi]" not in proc.stderr, proc.stderr
        files[name] = {f: (tmp_path / name / f).read_bytes()
                       for f in ("trajectory.txt", "angular_velocity.txt", "map.npy")}
    assert files["realtime"] == files["offline"]
    assert "realtime" not in json.loads((tmp_path / "offline" / "report.json").read_text())
    assert not _realtime(tmp_path / "realtime")["degradation_applied"]
    # the peak memory counts the back-end worker too (it holds the map and the window's events)
    report = json.loads((tmp_path / "realtime" / "report.json").read_text())
    worker_peak = report["backend_process"]["peak_rss_mb"]
    assert worker_peak > 50 and report["peak_rss_mb"] > worker_peak + 50


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_ctrl_c_leaves_no_output_and_no_traceback(short_dataset, tmp_path, sig):
    """Ctrl-C (SIGINT to the process group) and `kill PID` (SIGTERM to the main process; it left partial outputs)."""
    out = tmp_path / "interrupted"
    env = {**os.environ, "TI_CMAX_NO_PROGRESS": "1"}
    # replayed at a twentieth of the sensor's speed (24 s for the 1.2 s sequence; the interrupt ends it): the
    # interrupt 0.3 s after the replay's start lands mid-run even when a loaded machine stalls this process for
    # seconds (at a quarter of the speed, 4.8 s, the run twice ended first under load: exit 0, nothing on stderr)
    cmd = [sys.executable, "-m", "ti_cmax.cli", "slam", str(short_dataset), "--out", str(out), "--realtime",
           "--parallel", "--threads", "1", *SMALL, "--set", "realtime_speed=0.05"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    try:
        lines = []
        while not lines or ("replaying" not in lines[-1] and lines[-1] and len(lines) < 50):
            lines.append(proc.stderr.readline())  # until the replay has started (both processes are working)
        assert "replaying" in lines[-1], lines
        time.sleep(0.3)
        assert proc.poll() is None, "the replay ended before the interrupt"
        if sig == "SIGINT":
            os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
        else:
            os.kill(proc.pid, signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == (130 if sig == "SIGINT" else 143), stderr
    assert ("interrupted" if sig == "SIGINT" else "terminated") in stderr and "Traceback" not in stderr, stderr
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.slow
def test_slow_consumers_lose_no_events(short_sequence):
    """A slow on_window callback (sequential) and a worker bounded to a short backlog (push waits for it): every
    event reaches the map, the result is the unthrottled one; map() mid-stream comes from the worker."""
    ev = short_sequence.events.slice_time(short_sequence.events.t[0], short_sequence.events.t[0] + 0.45)
    cfg = load_config(SlamConfig, None, ["pano_height=256"])
    reference = run_slam(ev, short_sequence.camera, cfg)
    slow = OnlineSlam(short_sequence.camera, cfg, on_window=lambda w: time.sleep(0.05))
    bounded = OnlineSlam(short_sequence.camera, cfg, backend_process=True, max_backlog=0.3)
    mid = None
    for i in range(0, len(ev), 15_000):
        slow.push(ev[i:i + 15_000])
        bounded.push(ev[i:i + 15_000])
        if bounded.refined_until is None:  # the hot-pixel filter's held start: no event handed on yet
            assert bounded.t_last - ev.t[0] <= cfg.frontend.hot_pixel_hold_time + 0.01
            continue
        assert bounded.t_last - bounded.refined_until <= 0.3 + 0.01
        if mid is None and bounded.refined_until > ev.t[0] + 0.05:  # a window is done
            mid = bounded.map()
    for online in (slow, bounded):
        result = online.close()
        assert result.report["events_processed"] == len(ev)
        assert result.report["backend"]["events_settled"] == len(ev)
        np.testing.assert_allclose(result.map, reference.map, rtol=1e-4, atol=1e-4)
    assert mid is not None and 0 < mid.sum() < bounded.map().sum()


def test_controller_jumps_past_the_bound_and_hears_a_slow_front_end():
    cfg = load_config(SlamConfig, None, ["backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0)
    ctl.wall0, ctl.t0 = 100.0, 0.0
    ctl.on_window(_report(0.2, 1.5, ctl))  # beyond the hard bound: the last level at once
    assert ctl.level == R.MAX_LEVEL
    slow = R.RealtimeController(cfg, 1.0)
    slow.wall0, slow.t0 = 100.0, 0.0
    # the front-end alone is late: escalate before any window, straight to level 3 (levels 1-2 only degrade the BA)
    slow.on_frontend(slow.due(0.05) + 0.5, 0.05)
    assert slow.level == 3
    slow.on_frontend(slow.due(0.1) + 0.45, 0.1)  # less than a stride of progress and of wall time: no new decision
    assert slow.level == 3
    slow.on_frontend(slow.due(0.05) + 0.7, 0.05)  # no progress, but a stride of wall time later: heard, and later
    assert slow.level == 4
    slow.on_frontend(slow.due(0.3) + 0.05, 0.3)  # the front-end alone never relaxes
    assert slow.level == 4


def test_with_a_worker_the_front_end_skips_packets_only_while_it_falls_behind():
    """With a back-end worker the front-end has its own core: the levels degrade the BA alone, and the front-end's
    packets are skipped (1 of 2, then 4) only on its own lag; it takes every packet again once its lag is under half
    the target and the main process would cost under RELAX_HEADROOM with them."""
    cfg = load_config(SlamConfig, None, ["realtime_min_window_events=10000", "backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0, worker=True)
    calls = []
    ctl.online = SimpleNamespace(degrade=lambda keep, cap, every, budget, thinning=1, **_: calls.append((keep, cap, every)),
                                 frontend_until=0.1, runner=SimpleNamespace(seconds=0.0))
    ctl.idle_seconds = lambda: 0.0
    ctl.wall0, ctl.t0 = 100.0, 0.0
    t = 0.2
    for lag in (0.5, 0.6, 0.7):  # the worker is late: the BA degrades, the front-end keeps every packet
        ctl.on_window(_report(t, lag, ctl, busy=0.08, ba=0.05))
        t += 0.1
    assert ctl.level == 3 and [c[0] for c in calls] == [1, 1, 1]
    ctl.on_frontend(ctl.due(t) + 0.4, t)  # now the front-end is 0.4 s behind: its packets are skipped, the BA as was
    assert ctl.level == 3 and calls[-1][0] == 2
    ctl._fe_lag = 0.0  # caught up; the main process is nearly idle (its costs: run the windows with no main work)
    for _ in range(4):
        ctl.on_window(_report(t, 0.1, ctl))
        t += 0.1
    assert not ctl.fe_skipping and calls[-1][0] == 1


def test_with_a_worker_a_late_front_end_degrades_its_own_work_not_the_ba():
    """A front-end that falls behind on its core makes the windows late too; they wait for it, so a cheaper BA would
    not help: the front-end skips packets (1 of 2, then 4), then the input is thinned, while the BA keeps level 0 and
    every event (the report's events used stays that of the input). A worker late alone goes through levels 1-4
    before anything is thinned."""
    cfg = load_config(SlamConfig, None, ["realtime_min_window_events=10000", "backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0, worker=True)
    ctl.online = SimpleNamespace(degrade=lambda *a, **k: None, frontend_until=0.1, runner=SimpleNamespace(seconds=0.0))
    ctl.idle_seconds = lambda: 0.0
    ctl.wall0, ctl.t0 = 100.0, 0.0
    t, keeps = 0.2, []
    for k in range(5):
        lag = 0.4 + 0.1 * k
        ctl.on_frontend(ctl.due(t) + lag, t)
        ctl.on_window(_report(t, lag + 0.05, ctl, busy=0.05, ba=0.03))
        keeps.append((ctl.fe_keep(), ctl.thinning, ctl.level))
        t += 0.1
    assert [k[:2] for k in keeps] == [(2, 1), (4, 1), (4, 2), (4, 4), (4, 8)]
    assert all(level == 0 for _, _, level in keeps)
    ba_only = R.RealtimeController(cfg, 1.0, worker=True)
    ba_only.online = ctl.online
    ba_only.idle_seconds = lambda: 0.0
    ba_only.wall0, ba_only.t0 = 100.0, 0.0
    t, seen = 0.2, []
    for k in range(6):
        ba_only.on_frontend(ba_only.due(t) + 0.05, t)  # the front-end keeps up
        ba_only.on_window(_report(t, 0.4 + 0.1 * k, ba_only, busy=0.15, ba=0.1))
        seen.append((ba_only.level, ba_only.thinning, ba_only.fe_keep()))
        t += 0.1
    assert [s[0] for s in seen] == [1, 2, 3, 4, 4, 4] and [s[1] for s in seen] == [1, 1, 1, 1, 2, 4]
    assert all(s[2] == 1 for s in seen)
    # a front-end late because it waited for the worker (the backlog bound): the BA's doing, the levels rise
    held = R.RealtimeController(cfg, 1.0, worker=True)
    held.online, held.idle_seconds, held.wall0, held.t0 = ctl.online, lambda: 0.0, 100.0, 0.0
    waited = {"s": 0.0}
    held.blocked_seconds = lambda: waited["s"]
    t = 0.2
    for k in range(4):
        waited["s"] += 0.08
        held.on_frontend(held.due(t) + 0.4 + 0.1 * k, t)
        held.on_window(_report(t, 0.45 + 0.1 * k, held, busy=0.1, ba=0.09))
        t += 0.1
    assert held.level == 4 and held.fe_keep() == 1 and held.thinning == 1


def test_replay_behind_schedule_hands_over_without_waiting():
    """Behind schedule the replay hands over read chunk after read chunk; keeping up it waits a slice between
    hand-overs. (Taking the clock as the time handed over made it wait a slice after every chunk: at 12.6 M ev/s a
    50 000-event chunk is 4 ms of data, so the replay ran at ~2/3 of the sensor's rate and the lag grew.)"""
    chunk = Events(np.arange(50) * 1e-4, np.zeros(50, np.uint16), np.zeros(50, np.uint16), np.ones(50, np.int8))
    s_now = 0.5  # 0.5 s behind: the whole chunk (5 ms of data) is due
    batch, rest, handed = R._take_due(chunk, s_now)
    assert len(batch) == 50 and len(rest) == 0 and handed == pytest.approx(49e-4)
    assert R._wake_time(0.0050, s_now, handed, 0.002, 0.0) is None  # the next chunk goes at once
    # keeping up: the last hand-over was at the clock; wait for the next slice boundary
    assert R._wake_time(0.5001, 0.5001, 0.5, 0.002, 0.0) == pytest.approx(0.502)
    assert R._wake_time(0.7, 0.5, 0.49, 0.002, 0.0) == pytest.approx(0.7)  # nothing due until 0.7


def test_a_pause_of_the_stream_is_not_lag():
    """Time without events after a window's end, before the event that let it complete was handed over, is not lag
    (module docstring, Lag): a window ending in or just before a pause completes only once the pause has ended. The
    pause recorded here: events until 1.02 s, none until 4.0 s; the front-end had reached 0.95 s before that."""
    cfg = load_config(SlamConfig, None, ["backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0)
    ctl.wall0, ctl.t0 = 100.0, 0.0
    assert ctl.dead(1.0) == 0.0  # no pause: the lag is done - due(end), as before
    ctl.pauses.append((1.02, 4.0, 0.95))
    ctl.on_frontend(ctl.due(4.0) + 0.05, 3.9)  # a packet of the pause, emitted once the event at 4.0 s came
    assert ctl._fe_lag == pytest.approx(0.05)
    for t_end in (1.0, 2.0, 3.9):  # all complete 0.1 s after the event at 4.0 s was handed over
        ctl.on_window(_report(t_end, 4.1 - t_end, ctl))
    ctl.on_window(_report(4.1, 0.1, ctl))  # after the pause: due(4.1) as always
    assert ctl.lags == pytest.approx([0.12, 0.1, 0.1, 0.1])  # (1.0 s: the 20 ms of events after it are counted)
    assert ctl.level == 0 and ctl.pauses == []  # no window later than 4.1 s can have waited through it
    # a system still busy with the events before the pause keeps its lag: the window ending at 0.9 s could complete
    # without the event at 4.0 s (the front-end was past 0.9 s), so its completion after it is 3.2 s late
    slow = R.RealtimeController(cfg, 1.0)
    slow.wall0, slow.t0 = 100.0, 0.0
    slow.pauses.append((1.02, 4.0, 0.95))
    slow.on_window(_report(0.9, 3.2, slow))
    assert slow.lags == pytest.approx([3.2]) and slow.level == R.MAX_LEVEL


def test_a_replay_with_a_pause_keeps_every_event(short_sequence):
    """A stream with a pause (0.8 s of sensor time without events, 3.2 s of wall time at speed 0.25: longer than the
    lag bound): the replay records it and the windows that waited through it are not late; every event is used.
    (Counting the pause as lag gave lag max 1.64-1.66 s at speed 0.5, level 4, events used 0.4-0.6.) A quarter of
    real time leaves room for a machine shared with other jobs (at half speed it degraded there)."""
    ev = short_sequence.events
    t0 = float(ev.t[0])
    ev = ev.slice_time(t0, t0 + 0.5).downsample(4)
    t = ev.t.copy()
    t[t > t0 + 0.3] += 0.8
    paused = Events(t, ev.x, ev.y, ev.p)
    cfg = load_config(SlamConfig, None, ["pano_height=256", "realtime_speed=0.25", "realtime_target_lag=0.8",
                                         "realtime_max_lag=1.2"])
    result = R.run_realtime(iter([paused[i:i + 50_000] for i in range(0, len(paused), 50_000)]),
                            short_sequence.camera, cfg)
    rt = result.report["realtime"]
    assert rt["events_used_fraction"] == 1.0 and rt["input_events_dropped"] == 0
    assert not rt["degradation_applied"] or rt["ba_windows_cut_short"] > 0  # at most the cold window's budget
    # under the target, far below the pause's 3.2 s of wall time
    assert rt["max_lag_s"] < 0.8
    in_pause = [row[2] for row in result.realtime_trace if t0 + 0.3 < row[1] < t0 + 1.1]
    assert len(in_pause) >= 6 and max(in_pause) < 0.8


def test_input_thinning_keeps_the_packets_time_span(short_sequence):
    """Handing over 1 of q events, the front-end's packets take N / q of them (their span stays, their cost falls with
    the input); degrade() restores N."""
    online = OnlineSlam(short_sequence.camera, load_config(SlamConfig, None, ["pano_height=256"]))
    n = online.runner.slicer.n
    online.degrade(4, 0, 1, 0.1, input_thinning=8)
    assert online.runner.slicer.n == n // 8
    online.degrade()
    assert online.runner.slicer.n == n


@pytest.mark.parametrize("kwargs", [{"ba_cap": -5}, {"ba_cap": 2.5}, {"ba_budget": -1.0}, {"ba_every": 0},
                                    {"frontend_keep": 1.5}, {"input_thinning": 0}])
def test_degrade_refuses_values_the_worker_would_read_otherwise(short_sequence, kwargs):
    """In one process a ba_cap of -5 meant no cap and 2.5 a fractional one, a ba_budget of -1 no iteration at all;
    the worker shares them as integers (-1: None), so they meant something else there: refused in both."""
    online = OnlineSlam(short_sequence.camera, load_config(SlamConfig, None, ["pano_height=256"]))
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        online.degrade(**kwargs)
    online.degrade(ba_cap=np.int64(2000), ba_every=2.0, ba_budget=0.0)  # integral values of any type are fine
    assert online.budget.ba_cap == 2000 and online.budget.ba_every == 2


def test_the_real_time_worker_takes_every_core_unless_threads_were_chosen(monkeypatch):
    from ti_cmax.kernels import runtime

    monkeypatch.delenv("TI_CMAX_THREADS", raising=False)
    monkeypatch.setitem(runtime._state, "chosen", False)
    assert R._worker_threads() == R.runtime.available_cores()
    monkeypatch.setenv("TI_CMAX_THREADS", "1")
    assert R._worker_threads() is None  # the chosen count, as for the main process


def test_summaries_name_a_cut_short_cold_window():
    """A run whose only degradation is level 0's budget cutting a BA short (the cold first window) says so, in the
    command's line and the benchmark's table."""
    from ti_cmax.pipelines.evaluation.bench_realtime import _degradation

    rt = {"max_lag_s": 0.2, "mean_lag_s": 0.1, "latency_mean_s": 0.15, "events_used_fraction": 1.0,
          "level_sensor_seconds": {"0": 4.0, "1": 0.0, "2": 0.0, "3": 0.0, "4": 0.0}, "degradation_applied": True,
          "frontend_packets": 400, "frontend_packets_skipped": 0, "ba_windows_skipped": 0, "ba_windows_cut_short": 1,
          "ba_events_fraction": 1.0, "input_events_dropped": 0}
    assert R.describe(rt).endswith("degradation: 1 BA cut short")
    assert _degradation(rt) == "FE 100% of packets; BA events 100%, 0 BA skipped, 1 cut short"
    assert R.describe({**rt, "degradation_applied": False, "ba_windows_cut_short": 0}).endswith("degradation: none")


def test_benchmark_rounds_say_where_the_target_held():
    """bench_realtime --rounds: each row is judged against the real-time target (real time with every event and the
    offline accuracy up to 2.5 Mev/s, a bounded lag above) and the summary counts the rounds per case."""
    from ti_cmax.pipelines.evaluation.bench_realtime import summarize, target_met

    def row(case, rate, used, lag, abs_ratio, rel_ratio=1.0, rnd=1):
        return {"case": case, "mode": "parallel", "event_rate_mev_s": rate, "abs_ratio": abs_ratio,
                "rel_ratio": rel_ratio, "round": rnd, "realtime": {"events_used_fraction": used, "max_lag_s": lag}}

    ok, degraded, inaccurate = row("2m", 2.0, 1.0, 0.3, 1.02), row("2m", 2.0, 0.33, 0.3, 1.0, rnd=2), \
        row("2m", 2.0, 1.0, 0.3, 1.2, rnd=3)
    assert target_met(ok) and not target_met(degraded) and not target_met(inaccurate)
    assert not target_met(row("2m", 2.0, 1.0, 0.6, 1.0))
    assert target_met(row("vga", 12.6, 0.0, 0.9, 4.5)) and not target_met(row("vga", 12.6, 0.0, 1.1, 4.5))
    text = summarize([ok, degraded, inaccurate, row("vga", 12.6, 0.02, 0.9, None)])
    assert text.splitlines()[0] == ("2m (parallel): target met in 1 of 3 rounds; events used 0.330-1.000, lag max "
                                    "0.30-0.30 s, abs ratio 1.00-1.20")
    vga = text.splitlines()[1]
    assert vga.startswith("vga (parallel): target met in 1 of 1 rounds") and "abs ratio" not in vga
    assert summarize([{**ok, "probe_ms": 0.8}, {**degraded, "probe_ms": 1.3}]).endswith(", probe 0.80-1.30 ms")


def test_speed_probe_times_a_fixed_front_end_evaluation(ti_runtime):
    """The benchmarks' machine-speed probe: milliseconds per evaluation of one fixed packet, positive and of the
    order of the front-end's measured cost (0.7-1.4 ms on this 2-core VM), and in the benchmark table."""
    from ti_cmax.pipelines.evaluation.bench_realtime import format_table
    from ti_cmax.pipelines.evaluation.bench_sensors import speed_probe

    ms = speed_probe(evaluations=5)
    assert 0.01 < ms < 100
    rt = {"max_lag_s": 0.2, "mean_lag_s": 0.1, "latency_mean_s": 0.15, "latency_max_s": 0.3,
          "events_used_fraction": 1.0, "degradation_applied": False, "cpu_seconds": {"frontend": 1.0, "backend": 2.0,
                                                                                      "io": 0.1}}
    row = {"case": "2m", "mode": "parallel", "event_rate_mev_s": 2.0, "realtime": rt, "offline_abs_deg": 0.06,
           "realtime_abs_deg": 0.06, "abs_ratio": 1.0, "offline_rel_deg_s": 0.1, "realtime_rel_deg_s": 0.1,
           "rel_ratio": 1.0, "offline_us_per_event": {"frontend": 0.21, "backend": 0.43}, "load_realtime": [1.0, 1.2],
           "probe_ms": ms}
    last = format_table([row]).splitlines()[2]
    assert last.endswith(f"| 0.21 / 0.43 | 1.0-1.2 | {ms:.2f} |")


def test_benchmark_realtime_rounds_are_checked(tmp_path, capsys):
    """`ti-cmax benchmark --realtime --rounds 0`: one clear error, nothing written."""
    from ti_cmax.cli import main

    assert main(["benchmark", "--realtime", "--rounds", "0", "--out", str(tmp_path / "rt")]) == 2
    assert "--rounds must be at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "rt").exists()


def test_the_worker_ends_when_its_parent_died(monkeypatch):
    """A back-end worker whose main process was killed (SIGKILL, out of memory) used to sleep in inbox.get() forever,
    holding the terminal's pipes open (`slam | tee log` never ended): it polls and exits."""
    import multiprocessing
    import queue

    from ti_cmax.pipelines import worker as worker_module

    class Dead:
        def is_alive(self):
            return False

    class Silent:
        def get(self, timeout=None):
            raise queue.Empty

    def exit_(code):
        raise SystemExit(code)

    monkeypatch.setattr(multiprocessing, "parent_process", lambda: Dead())
    monkeypatch.setattr(worker_module.os, "_exit", exit_)
    with pytest.raises(SystemExit):
        worker_module._next_message(Silent(), poll=0.01)


def test_a_hand_over_holds_at_most_hand_over_events():
    """Behind schedule a large read chunk (a reader's block) goes in hand-overs of at most
    HAND_OVER_EVENTS events, the time handed over being the last one's."""
    n = R.HAND_OVER_EVENTS + 123
    chunk = Events(np.arange(n) * 1e-7, np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8))
    batch, rest, handed = R._take_due(chunk, 1.0)
    assert len(batch) == R.HAND_OVER_EVENTS and len(rest) == 123 and handed == batch.t[-1]
    batch, rest, handed = R._take_due(rest, 1.0)
    assert len(batch) == 123 and len(rest) == 0


def test_hot_pixel_events_screened_as_read_are_no_lost_input(short_sequence):
    """The replay screens each chunk as it reads it: the events of a hot pixel are dropped before the hand-over, and
    that is no degradation (every event that passed the filter was handed over and used)."""
    seq = short_sequence
    ev = seq.events.slice_time(seq.events.t[0], seq.events.t[0] + 0.3)
    hot = np.arange(float(ev.t[0]), float(ev.t[-1]), 1 / 3000.0)  # a pixel firing at 3 kHz
    t = np.concatenate([ev.t, hot])
    order = np.argsort(t, kind="stable")
    with_hot = Events(t[order], np.concatenate([ev.x, np.full(len(hot), 7, ev.x.dtype)])[order],
                      np.concatenate([ev.y, np.full(len(hot), 9, ev.y.dtype)])[order],
                      np.concatenate([ev.p, np.ones(len(hot), np.int8)])[order])
    cfg = load_config(SlamConfig, None, ["realtime_target_lag=1000", "realtime_max_lag=1000", "pano_height=256"])
    chunks = [with_hot[i:i + 40_000] for i in range(0, len(with_hot), 40_000)]
    rt = R.run_realtime(chunks, seq.camera, cfg).report["realtime"]
    assert rt["events_read"] == len(with_hot)
    assert rt["events_handed_over"] < len(with_hot) - 0.9 * len(hot)  # the hot pixel's events: dropped as read
    assert rt["events_used_fraction"] == 1.0 and not rt["degradation_applied"]


def test_a_new_level_is_given_time_while_the_lag_stops_rising():
    """The windows queued in the worker were sent with the old budget: after a rise the level is raised again within
    DRAIN_WINDOWS windows only while the lag is above where it stood at the rise (a burst being absorbed at level 1
    went on to halve the BA's events one window later); past them the usual rule applies again."""
    cfg = load_config(SlamConfig, None, ["realtime_min_window_events=10000", "backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0)
    ctl.online = SimpleNamespace(degrade=lambda *a, **k: None, frontend_until=0.1, runner=SimpleNamespace(seconds=0.0))
    ctl.wall0, ctl.t0 = 100.0, 0.0
    t = 0.2
    levels = []
    for lag in (0.3, 0.5, 0.49, 0.48, 0.47, 0.55, 0.54, 0.53, 0.52, 0.51, 0.50, 0.49):
        ctl.on_window(_report(t, lag, ctl, busy=0.08, ba=0.05))
        levels.append(ctl.level)
        t += 0.1
    # rise at 0.5; held while under 0.5; 0.55 rises again; held under 0.55 for 5 windows, then (still not draining
    # within 5 windows) the next rise
    assert levels == [0, 1, 1, 1, 1, 2, 2, 2, 2, 2, 3, 3], levels


def _worker_controller(monkeypatch, clock):
    """A controller with a back-end worker, its wall clock ``clock[0]`` (advanced by the caller)."""
    monkeypatch.setattr(R, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    cfg = load_config(SlamConfig, None, ["realtime_min_window_events=10000", "backend_max_window_events=200000"])
    ctl = R.RealtimeController(cfg, 1.0, worker=True)
    ctl.online = SimpleNamespace(degrade=lambda *a, **k: None, frontend_until=0.1, runner=SimpleNamespace(seconds=0.0))
    ctl.wall0, ctl.t0 = 100.0, 0.0
    return ctl


def test_windows_sent_before_a_rise_do_not_escalate_again(monkeypatch):
    """With a lag of 0.3 s the front-end is 0.3 s ahead of the windows completing: the three windows after a rise
    were sent to the worker under the old budget, so a lag still rising through them escalates no further; the
    first window sent after the rise does, and a lag beyond the hard bound does at once."""
    clock = [100.0]
    ctl = _worker_controller(monkeypatch, clock)
    t, levels = 0.2, []
    for lag in (0.31, 0.33, 0.35, 0.37, 0.39, 0.41, 0.43):
        report = _report(t, lag, ctl, busy=0.12, ba=0.05)
        ctl.online.frontend_until = t + 0.3  # the front-end's progress when this window completes
        clock[0] += 0.1
        ctl.on_window(report)
        levels.append(ctl.level)
        t += 0.1
    # risen after the window ending at 0.2 (front-end at 0.5): windows ending at 0.3, 0.4, 0.5 hold; 0.6 escalates
    assert levels == [1, 1, 1, 1, 2, 2, 2], levels
    report = _report(t, 1.2, ctl, busy=0.12, ba=0.05)
    ctl.online.frontend_until = t + 0.3
    ctl.on_window(report)
    assert ctl.level == R.MAX_LEVEL  # beyond the hard bound: whatever was in flight


def test_with_a_worker_a_busy_main_process_does_not_hold_the_ba_level(monkeypatch):
    """With a worker the levels change the BA alone: a main process kept busy by a high event rate (here all of its
    wall time) does not keep the BA at a level the worker has room below."""
    clock = [100.0]
    ctl = _worker_controller(monkeypatch, clock)
    t = 0.2
    ctl.on_window(_report(t, 1.1, ctl, busy=0.2, ba=0.05))  # beyond the hard bound: level 4 (the BA skipped)
    assert ctl.level == R.MAX_LEVEL
    measured, levels = [], []
    mean_costs = ctl.mean_costs
    ctl.mean_costs = lambda: measured.append(mean_costs()) or measured[-1]  # what the relax rule read
    for _ in range(5):  # the worker busy half the time, the main process all of it, the lag under target
        t += 0.1
        clock[0] += 0.1
        ctl.on_window(_report(t, 0.2, ctl, busy=0.05))
        levels.append(ctl.level)
    assert [m["main"] for m in measured if m] == [pytest.approx(1.0)], measured
    # level 3 (a BA of 100 000 events on 1 of 2 windows: 0.05 / 2 per 0.1 s stride) predicted at 0.5 + 0.25
    assert R.MAX_LEVEL - 1 in levels and ctl.predicted[-1] == pytest.approx(0.75, rel=0.02), (levels, ctl.predicted)


def test_a_lag_under_half_the_target_relaxes_with_less_headroom(monkeypatch):
    """The level below predicted at 0.9 of the worker's time: not taken while the lag is at two thirds of the target
    (RELAX_HEADROOM 0.8), taken once it is under half the target (RELAX_HEADROOM_LOW_LAG)."""
    clock = [100.0]
    ctl = _worker_controller(monkeypatch, clock)
    t = 0.2
    ctl.on_window(_report(t, 1.1, ctl, busy=0.2, ba=0.05))
    for lag in (0.2, 0.2, 0.2, 0.2, 0.2):
        t += 0.1
        clock[0] += 0.1
        ctl.on_window(_report(t, lag, ctl, busy=0.065))
    assert ctl.level == R.MAX_LEVEL and ctl.relax_headroom(0.2) == R.RELAX_HEADROOM
    t += 0.1
    clock[0] += 0.1
    ctl.on_window(_report(t, 0.1, ctl, busy=0.065))
    assert ctl.level == R.MAX_LEVEL - 1 and ctl.predicted[-1] == pytest.approx(0.9, rel=0.02)


def test_the_replay_prepares_the_back_end_for_the_rate_of_its_first_chunk_before_its_clock(short_sequence,
                                                                                             monkeypatch):
    """The first chunk is read before the clock starts; its event rate prepares the back-end's memory
    (``OnlineSlam.prepare``) before any event is handed over."""
    from ti_cmax.pipelines import slam

    calls = []
    prepare, push = slam.OnlineSlam.prepare, slam.OnlineSlam.push_screened
    monkeypatch.setattr(slam.OnlineSlam, "prepare", lambda self, rate: calls.append(("prepare", rate))
                        or prepare(self, rate))
    monkeypatch.setattr(slam.OnlineSlam, "push_screened", lambda self, *a, **k: calls.append(("push", None))
                        or push(self, *a, **k))
    ev = short_sequence.events
    chunks = [ev[i:i + 100_000] for i in range(0, len(ev), 100_000)]
    cfg = load_config(SlamConfig, None, ["pano_height=256", "realtime_speed=4"])
    R.run_realtime(iter(chunks), short_sequence.camera, cfg)
    first = chunks[0]
    assert calls[0] == ("prepare", pytest.approx(len(first) / (first.t[-1] - first.t[0])))
    assert [c[0] for c in calls].count("prepare") == 1 and calls[1][0] == "push"

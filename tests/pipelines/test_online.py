"""Streaming API (OnlineSlam): same result as run_slam for any chunking, a pose for every time pushed, a source
that stops mid-window."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.errors import InputError
from ti_cmax.config import SlamConfig
from ti_cmax.pipelines.slam import OnlineSlam, run_slam


@pytest.fixture(scope="module")
def half_second(short_sequence):
    seq = short_sequence
    return seq, seq.events.slice_time(seq.events.t[0], seq.events.t[0] + 0.5)


def _random_chunks(ev, rng, max_size):
    i = 0
    while i < len(ev):
        n = int(rng.integers(1, max_size))
        yield ev[i:i + n]
        i += n


@pytest.mark.slow
def test_online_equals_run_slam_for_any_chunking(half_second):
    seq, ev = half_second
    offline = run_slam(ev, seq.camera, SlamConfig())
    windows = []
    online = OnlineSlam(seq.camera, SlamConfig(), on_window=windows.append)
    for chunk in _random_chunks(ev, np.random.default_rng(0), 40_000):
        online.push(chunk)
    result = online.close()
    assert online.close() is result  # idempotent
    assert len(windows) == len(offline.windows) == len(result.windows) >= 3
    assert [w.t_start for w in windows] == [w.t_start for w in offline.windows]
    np.testing.assert_allclose(result.frontend.omega, offline.frontend.omega, atol=1e-6)
    np.testing.assert_allclose(result.trajectory.t, offline.trajectory.t)
    assert np.max(so3.geodesic_angle(result.trajectory.R, offline.trajectory.R)) < 1e-5
    np.testing.assert_allclose(result.map, offline.map, rtol=1e-4, atol=1e-4)
    assert result.report["events_processed"] == offline.report["events_processed"] == len(ev)
    with pytest.raises(RuntimeError):
        online.push(ev[:10])


def test_pose_is_available_for_every_time_pushed(half_second):
    seq, ev = half_second
    online = OnlineSlam(seq.camera, SlamConfig())
    t0 = float(ev.t[0])
    assert np.allclose(online.pose([t0, t0 + 1.0]), np.eye(3))  # nothing pushed yet: the world frame
    gt0 = seq.groundtruth.at(t0)[0]
    early = []  # (t, pose then) for times already refined, to compare with the final spline
    worst = 0.0
    for chunk in _random_chunks(ev, np.random.default_rng(1), 30_000):
        online.push(chunk)
        t_last, r_last = online.latest()
        assert t_last == chunk.t[-1]
        times = np.linspace(t0, t_last, 7)
        poses = online.pose(times)
        assert poses.shape == (7, 3, 3) and np.allclose(poses @ poses.transpose(0, 2, 1), np.eye(3), atol=1e-6)
        truth = gt0.T @ seq.groundtruth.at(times)
        worst = max(worst, float(np.max(np.degrees(so3.geodesic_angle(poses, truth)))))
        if online.refined_until is not None and online.refined_until > t0 + 0.15:
            t_fixed = online.refined_until - 0.11  # older than the free control poses of a cubic spline
            early.append((t_fixed, online.pose(t_fixed)[0]))
    assert worst < 2.0  # the best estimate so far stays on the true motion, refined or front-end
    result = online.close()
    assert early
    for t, r in early:
        assert so3.geodesic_angle(r, result.rotation_at(t)[0]) < 1e-6


def test_source_that_stops_mid_window_finishes_cleanly(half_second):
    seq, ev = half_second
    t0 = float(ev.t[0])
    part = ev.slice_time(t0, t0 + 0.35)  # windows of 0.2 s every 0.1 s: stops inside [0.2, 0.4] and [0.3, 0.5]
    online = OnlineSlam(seq.camera, SlamConfig())
    for i in range(0, len(part), 25_000):
        online.push(part[i:i + 25_000])
    result = online.close()
    assert result.report["status"] == "ok"
    assert result.report["backend"]["events_settled"] == len(part)  # every event reached the map
    assert result.windows[-1].t_end == pytest.approx(float(part.t[-1]), abs=0.02)
    assert result.trajectory.t[-1] == pytest.approx(float(part.t[-1]), abs=0.02)
    assert np.isfinite(result.map).all() and result.map.sum() > 0
    with pytest.raises(InputError, match="no events"):
        OnlineSlam(seq.camera, SlamConfig()).close()
    with pytest.raises(InputError, match="time order"):
        online2 = OnlineSlam(seq.camera, SlamConfig())
        online2.push(part[1000:2000])
        online2.push(part[:10])


@pytest.mark.slow
def test_backend_process_equals_the_sequential_run(half_second):
    """The back-end in a worker process (concurrent with the front-end) gives the sequential result; pose() follows
    the worker's refined spline; a small input queue only makes push() wait (no event lost)."""
    seq, ev = half_second
    ev = ev.slice_time(ev.t[0], ev.t[0] + 0.35)
    sequential = run_slam(ev, seq.camera, SlamConfig())
    windows = []
    online = OnlineSlam(seq.camera, SlamConfig(), on_window=windows.append, backend_process=True, queue_size=2)
    for i in range(0, len(ev), 20_000):
        online.push(ev[i:i + 20_000])
    result = online.close()
    assert len(windows) == len(sequential.windows)
    assert result.report["events_processed"] == len(ev)
    assert result.report["backend"]["events_settled"] == sequential.report["backend"]["events_settled"]
    assert np.max(so3.geodesic_angle(result.trajectory.R, sequential.trajectory.R)) < 1e-5
    np.testing.assert_allclose(result.map, sequential.map, rtol=1e-4, atol=1e-4)
    t_mid = float(ev.t[0]) + 0.1
    assert so3.geodesic_angle(online.pose(t_mid)[0], sequential.rotation_at(t_mid)[0]) < 1e-5
    assert result.report["backend_process"]["cpu_seconds"] > 0


def test_pushed_events_are_checked_before_anything_runs(half_second):
    """The Python API checks what the file readers check (one InputError, nothing processed): timestamps out of order
    inside a chunk (one moved the trajectory 1.7 deg), pixels off the sensor (x = width became pixel (0, y + 1)), and
    a pause longer than max_event_gap (a stray event at t = 0 before Unix-time stamps made `slam` run for hours), in
    OnlineSlam and in the front-end alone."""
    from ti_cmax import Events
    from ti_cmax.config import FrontendConfig, load_config
    from ti_cmax.pipelines.frontend import estimate_angular_velocity

    seq, ev = half_second
    cam = seq.camera
    head = ev[:2000]
    t = head.t.copy()
    t[1000] = t[0]
    unsorted = Events(t, head.x, head.y, head.p)
    x = head.x.copy()
    x[5] = cam.width
    off_sensor = Events(head.t, x, head.y, head.p)
    paused = Events.concatenate([head, Events(head.t[-1:] + 61.0, head.x[:1], head.y[:1], head.p[:1])])
    for bad, message in ((unsorted, "not sorted"), (off_sensor, "outside the sensor"), (paused, "no events for 61")):
        online = OnlineSlam(cam, SlamConfig())
        with pytest.raises(InputError, match=message):
            online.push(bad)
        assert online.events_read == 0
        with pytest.raises(InputError, match=message):
            estimate_angular_velocity(bad, cam)
    online = OnlineSlam(cam, SlamConfig())
    online.push(head)
    with pytest.raises(InputError, match="no events for 61"):  # across chunks too
        online.push(paused[-1:])
    cfg = load_config(FrontendConfig, None, ["max_event_gap=100"])
    assert len(estimate_angular_velocity(paused, cam, cfg).t) > 0


@pytest.mark.slow
def test_pose_after_a_pause_of_the_stream_follows_the_worker(half_second):
    """A pause of the stream (0.8 s without events): the back-end fits its empty windows with the next one that has
    events, adding control poses before that window's; pose() in the main process follows the worker's spline
    there too (a shadow spline missing those poses put the later ones at the wrong knots)."""
    from ti_cmax.events import Events

    seq, ev = half_second
    t0 = float(ev.t[0])
    ev = ev.slice_time(t0, t0 + 0.4)
    t = ev.t.copy()
    t[t > t0 + 0.2] += 0.8
    paused = Events(t, ev.x, ev.y, ev.p)
    online = OnlineSlam(seq.camera, SlamConfig(), backend_process=True)
    for i in range(0, len(paused), 20_000):
        online.push(paused[i:i + 20_000])
    online.map()  # waits until the worker has handled every event pushed (its window messages applied)
    # the spline is fitted up to here; final a window and a knot interval before (the next window's BA moves the
    # control poses whose support reaches into it: after a rejected window, from its start on)
    anchor = online.backend.mirror.fitted_until
    assert anchor - 0.25 > t0 + 0.85  # through the pause (its poses fitted with the first window after it)
    t_check = np.linspace(t0 + 0.05, anchor - 0.25, 25)
    before_close = online.pose(t_check)
    result = online.close()
    assert any(w.num_events == 0 for w in result.windows)
    assert np.max(so3.geodesic_angle(before_close, result.rotation_at(t_check))) < 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_unguarded_script_asking_for_a_worker(tmp_path, start):
    """A script that starts a back-end worker at its top level (no ``if __name__ == "__main__":``): a forked worker
    (Linux, a process with one thread) runs it as any other; a spawned one (here: the script runs a second thread)
    runs the script again, and it must end with one message saying so, not hang (it hung in multiprocessing's launch
    while the camera's 1.2 MB of bearing tables filled the pipe) nor print multiprocessing's page of traceback."""
    import subprocess
    import sys

    if start == "fork" and not sys.platform.startswith("linux"):
        pytest.skip("the worker is forked on Linux only")
    script = tmp_path / "unguarded.py"
    script.write_text(
        ("import threading, time\nthreading.Thread(target=time.sleep, args=(600,), daemon=True).start()\n"
         if start == "spawn" else "") +
        "import numpy as np\n"
        "from ti_cmax.camera import Camera\n"
        "from ti_cmax.config import SlamConfig\n"
        "from ti_cmax.events import Events\n"
        "from ti_cmax.pipelines.slam import run_slam\n"
        "rng = np.random.default_rng(0)\n"
        "n = 60_000\n"
        "camera = Camera(240, 180, 200.0, 200.0, 120.0, 90.0)\n"
        "camera.bearing_lut4  # built before the worker is sent the camera\n"
        "ev = Events(np.sort(rng.uniform(0, 0.6, n)), rng.integers(0, 240, n), rng.integers(0, 180, n),\n"
        "            rng.integers(0, 2, n))\n"
        "result = run_slam(ev, camera, SlamConfig(), backend_process=True)\n"
        "print(result.report['backend_process']['start_method'])\n")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=180, cwd=tmp_path)
    if start == "fork":
        assert proc.returncode == 0 and proc.stdout.split() == ["fork"], proc.stderr
        return
    assert proc.returncode != 0
    assert "WorkerLost" in proc.stderr and 'if __name__ == "__main__":' in proc.stderr
    assert "bootstrapping phase" not in proc.stderr  # multiprocessing's own message is not shown


def test_camera_pickles_without_its_bearing_tables():
    import pickle

    from ti_cmax.camera import Camera

    camera = Camera(240, 180, 200.0, 200.0, 121.0, 89.0, (0.1, -0.02, 0.001, 0.0, 0.0))
    table = camera.bearing_lut4.copy()
    data = pickle.dumps(camera)
    assert len(data) < 4096  # the tables are 1.2 MB
    copy = pickle.loads(data)
    assert copy == camera and "bearing_lut4" not in vars(copy)
    np.testing.assert_array_equal(copy.bearing_lut4, table)


@pytest.mark.parametrize("backend_process", [False, True])
def test_the_window_budget_reaches_the_backend_wherever_it_runs(half_second, backend_process):
    """The real-time budget is an argument of every window step: set by degrade() between pushes it applies to the
    windows that start after it, in this process and in a worker (sent with every pose message)."""
    seq, ev = half_second
    windows = []
    online = OnlineSlam(seq.camera, SlamConfig(), on_window=windows.append, backend_process=backend_process)
    half = int(np.searchsorted(ev.t, ev.t[0] + 0.25))
    online.degrade(ba_cap=0)
    online.push(ev[:half])
    online.map()  # with a worker: every window of the first half is done before the budget changes
    online.degrade()
    online.push(ev[half:])
    result = online.close()
    first = [w for w in result.windows if w.t_end <= ev.t[0] + 0.2]
    assert first and all(w.skipped and not w.optimized for w in first)
    assert any(w.optimized for w in result.windows)
    assert [w.t_start for w in windows] == [w.t_start for w in result.windows]


@pytest.mark.parametrize("slice_seconds", [0.02, None])
def test_a_sliced_loop_closers_optimizer_is_imported_before_the_clock_starts(slice_seconds):
    """Real time (loop verifications in slices): the back-end's start-up imports the joint refinement's optimizer, so
    its import does not hold the first window; offline it stays unimported until a revisit needs it."""
    import subprocess
    import sys

    code = ("import sys\nfrom ti_cmax.camera import Camera\nfrom ti_cmax.config import SlamConfig\n"
            "from ti_cmax.pipelines.online_backend import BackendRunner\n"
            "cam = Camera.ideal(64, 48)\n"
            f"BackendRunner(cam, SlamConfig(), loop_slice_seconds={slice_seconds!r}).compile()\n"
            "print('scipy.optimize' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[-1] == str(slice_seconds is not None)


def test_screened_chunks_handed_over_in_pieces_equal_push(half_second):
    """``screen`` (checks and the hot-pixel filter) on large read chunks, then ``push_screened`` of the screened
    events in small pieces (the real-time replay) is ``push`` of the stream: the same windows, trajectory and map."""
    seq, ev = half_second
    pushed = OnlineSlam(seq.camera, SlamConfig())
    for chunk in _random_chunks(ev, np.random.default_rng(2), 40_000):
        pushed.push(chunk)
    pushed = pushed.close()
    online = OnlineSlam(seq.camera, SlamConfig())
    for i in range(0, len(ev), 120_000):
        for part in online.screen(ev[i:i + 120_000]):
            for piece in _random_chunks(part, np.random.default_rng(i), 9_000):
                online.push_screened(piece)
    result = online.close()
    assert [w.t_start for w in result.windows] == [w.t_start for w in pushed.windows] and len(result.windows) >= 3
    np.testing.assert_allclose(result.frontend.omega, pushed.frontend.omega, atol=1e-6)
    assert np.max(so3.geodesic_angle(result.trajectory.R, pushed.trajectory.R)) < 1e-5
    np.testing.assert_allclose(result.map, pushed.map, rtol=1e-4, atol=1e-4)
    assert result.report["events_processed"] == pushed.report["events_processed"] == len(ev)
    with pytest.raises(RuntimeError):
        online.push_screened(ev[:10])


def test_a_chunk_longer_than_the_pause_bound_is_searched_for_its_pauses():
    """The check skips the search for a pause when a chunk (with the previous one's end) spans no more than
    max_event_gap; a longer chunk is searched: dense events pass, one pause beyond the bound is named."""
    from ti_cmax import Events
    from ti_cmax.config import FrontendConfig, load_config
    from ti_cmax.camera import Camera
    from ti_cmax.pipelines.frontend import FrontendRunner

    cfg = load_config(FrontendConfig, None, ["max_event_gap=0.01"])
    t = np.arange(20_000) * 1e-5  # 0.2 s, gaps of 10 us
    xy = np.zeros(len(t), np.uint16)
    dense = Events(t, xy, xy, np.ones(len(t), np.int8))
    runner = FrontendRunner(Camera.ideal(64, 48), cfg)
    runner.check(dense)
    runner.check(Events(t + 0.2 + 1e-5, xy, xy, dense.p))  # and on, across chunks
    t_pause = t.copy()
    t_pause[10_000:] += 0.02
    with pytest.raises(InputError, match="no events for 0.02001 s after t=0.0999"):
        FrontendRunner(Camera.ideal(64, 48), cfg).check(Events(t_pause, xy, xy, dense.p))

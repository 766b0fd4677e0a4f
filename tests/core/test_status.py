"""A run says when its result cannot be trusted: status and reasons in report.json and on the summary line."""
import json

import numpy as np
import pytest

from ti_cmax.cli import main
from ti_cmax.status import apply_status, run_status, status_text


def _frontend(**over):
    fe = {"packets": 100, "still_packets": 0, "flat_packets": 0, "checked_packets": 10, "suspect_packets": 0,
          "small_packets": 0, "min_packet_events": 1000,
          "event_rate": {"moving": 2e6, "flat": None, "floor": 1e4}}
    fe.update(over)
    return {"status": "ok", "frontend": fe}


def test_a_run_without_warning_signs_is_ok():
    assert run_status(_frontend()) == ("ok", [])
    assert run_status({"status": "ok", "backend": {"windows": 10, "windows_still": 2, "windows_rejected": 3}},
                      events_range=(0, 2), trajectory_range=(0.05, 2)) == ("ok", [])


@pytest.mark.parametrize("report, words", [
    (_frontend(small_packets=3, packets=4, checked_packets=0), "too few events: 3 of 4 moving packets"),
    (_frontend(suspect_packets=6), "6 of 10 checked packets barely sharpen"),
    # a star field turning fast: most packets flat while 8 M events/s arrive
    (_frontend(flat_packets=63, event_rate={"moving": 6e6, "flat": 8e6, "floor": 1e3}),
     "63 of 100 packets set to omega = 0 while events arrive at 8 M ev/s"),
    ({"status": "ok", "backend": {"windows": 9, "windows_still": 0, "windows_rejected": 8}},
     "8 of 9 back-end windows rejected"),
])
def test_each_warning_sign_makes_the_run_suspect(report, words):
    status, reasons = run_status(report)
    assert status == "suspect" and len(reasons) == 1 and words in reasons[0], reasons


def test_a_still_camera_seeing_noise_is_not_a_lost_motion():
    """Most packets flat at a noise rate (far below the moving packets' and 100x the floor): a real stop."""
    report = _frontend(flat_packets=70, event_rate={"moving": 2e6, "flat": 5e4, "floor": 1e4})
    assert run_status(report) == ("ok", [])


def test_a_trajectory_that_does_not_cover_the_events_is_suspect():
    status, reasons = run_status({"status": "ok"}, events_range=(0.0, 2.0), trajectory_range=(0.0, 0.5))
    assert status == "suspect" and "covers 25 % of the events' time range" in reasons[0]


def test_a_lost_method_stays_lost_and_the_summary_line_says_why():
    report = apply_status({"status": "lost", "backend": {"windows": 4, "windows_rejected": 3}})
    assert report["status"] == "lost" and len(report["reasons"]) == 1
    assert status_text(report).startswith("; LOST: 3 of 4 back-end windows rejected")
    assert status_text(apply_status({"status": "ok"})) == ""


def test_frontend_result_status_flags_flat_packets_at_a_high_rate():
    from ti_cmax.config import FrontendConfig
    from ti_cmax.pipelines.frontend import FrontendResult
    from ti_cmax.pipelines.motion import Motion

    m = 20
    flat = np.arange(m) >= 5  # 15 of 20 packets flat, all at 8 M ev/s
    motion = np.array([Motion.FLAT if f else Motion.MOVING for f in flat], dtype=object)
    res = FrontendResult(t=np.arange(m) * 0.01, omega=np.where(flat[:, None], 0.0, 3.0) * np.ones((m, 3)),
                         motion=motion, num_events=np.full(m, 80_000), span=np.full(m, 0.01),
                         iterations=np.ones(m, int), evaluations=np.ones(m, int), cost=np.ones(m),
                         gain=np.full(m, 1.5), suspect=np.zeros(m, bool), lookback=np.zeros(m),
                         config=FrontendConfig(frontend_min_event_rate=1e4))
    assert res.status == "suspect"
    summary = res.summary()
    assert summary["event_rate"]["flat"] == pytest.approx(8e6) and summary["small_packets"] == 0
    assert "15 of 20 packets set to omega = 0" in run_status({"frontend": summary})[1][0]


def _sequence(folder, n, duration):
    from ti_cmax.camera import Camera
    from ti_cmax.events import Events
    from ti_cmax.io import write_events_h5

    rng = np.random.default_rng(1)
    ev = Events(np.sort(rng.uniform(0, duration, n)), rng.integers(0, 240, n).astype(np.uint16),
                rng.integers(0, 180, n).astype(np.uint16), rng.integers(0, 2, n).astype(np.int8) * 2 - 1)
    folder.mkdir()
    write_events_h5(folder / "events.h5", ev, camera=Camera(240, 180, 199.0, 199.0, 120.0, 90.0))
    return folder


def test_frontend_on_too_few_events_says_so(tmp_path, capsys):
    """100 events gave omega 40 rad/s off with status ok."""
    seq = _sequence(tmp_path / "seq", 100, 0.002)
    assert main(["frontend", str(seq), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["status"] == "suspect" and report["reasons"][0].startswith("too few events"), report["reasons"]
    assert "; SUSPECT: too few events" in line


def test_map_of_a_trajectory_covering_a_quarter_of_the_events_says_so(tmp_path, capsys):
    seq = _sequence(tmp_path / "seq", 20_000, 1.0)
    traj = tmp_path / "traj.txt"
    traj.write_text("".join(f"{0.05 * i:.2f} 0 0 0 0 0 0 1\n" for i in range(6)))  # 0 to 0.25 s
    out = tmp_path / "m.png"
    assert main(["map", str(seq), "--trajectory", str(traj), "--out", str(out), "--size", "256x128"]) == 0
    figures = json.loads(out.with_suffix(".json").read_text())
    assert figures["status"] == "suspect" and "covers 25 %" in figures["reasons"][0]
    assert "; SUSPECT: the trajectory" in capsys.readouterr().out


def test_a_run_that_warns_is_suspect():
    """A workflow's own warning (star tracking beyond its motion range) is a reason not to trust the result."""
    warning = "the camera turns at up to 268 deg/s, beyond the 60 deg/s star tracking handles"
    status, reasons = run_status({"status": "ok", "warnings": [warning]})
    assert status == "suspect" and reasons == [warning]

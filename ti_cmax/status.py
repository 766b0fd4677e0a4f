"""Whether a run's result can be trusted: one status and its reasons, derived from the run's own counters.

Every command that writes a report calls :func:`apply_status`: report.json gets ``"status"`` ("ok", "suspect", or a
method's own "lost") and ``"reasons"`` (one sentence each), and the command's summary line ends with them
(:func:`status_text`). A suspect result is written all the same; the status says not to trust it without a look.

Reasons (thresholds below):
- too few events: most moving packets of the front-end hold fewer events than the still rule's floor
  (``frontend_min_event_rate`` x ``still_span_factor`` x ``dt_ang_vel``: 1 000 events on a DAVIS240C, scaled with
  the pixel count). A packet of 100 events gave omega 40 rad/s off; the smallest input that gives a trustworthy
  omega is one packet of at least that floor, better ``num_events_per_packet`` (10 000 on a DAVIS240C).
- most checked packets suspect: the optimum barely sharpens the image of warped events (the events do not
  constrain omega).
- most packets set to omega = 0 while events keep arriving at a high rate: a still camera sees only noise, far
  fewer events than a moving one; a front-end that calls most packets still at the rate of its moving packets (or
  at 100x the floor rate) has lost the motion (e.g. a star field turning at 100-250 deg/s).
- most windows rejected by the back-end (false maxima: a correction beyond ``backend_max_correction``, or an optimum
  that failed the back-end's check and so did its refit; the windows kept their initialisation).
- a trajectory that does not cover the events' time range (under 90 %).
- the run's own warnings (``report["warnings"]``, e.g. star tracking on a motion beyond what it handles).
"""
from __future__ import annotations

MOST = 0.5  # "most": more than this fraction
HIGH_RATE_FLOOR_FACTOR = 100.0  # an event rate this many times the still rule's floor is not a still camera
HIGH_RATE_MOVING_FRACTION = 0.5  # nor one at least this fraction of the rate of the packets that moved
MIN_COVERAGE = 0.9  # of the events' time range by the trajectory


def _frontend_reasons(fe: dict) -> list[str]:
    reasons = []
    packets, still = int(fe.get("packets", 0)), int(fe.get("still_packets", 0))
    moving = packets - still
    small, floor = int(fe.get("small_packets", 0)), int(fe.get("min_packet_events", 0))
    if moving and small > MOST * moving:
        reasons.append(f"too few events: {small} of {moving} moving packets hold fewer than {floor} events "
                       "(omega from so few is unreliable)")
    checked, suspect = int(fe.get("checked_packets", 0)), int(fe.get("suspect_packets", 0))
    if checked and suspect > MOST * checked:
        reasons.append(f"{suspect} of {checked} checked packets barely sharpen the image (the events do not "
                       "constrain omega)")
    flat = int(fe.get("flat_packets", 0))
    rate = fe.get("event_rate") or {}
    flat_rate, moving_rate, floor_rate = rate.get("flat"), rate.get("moving"), rate.get("floor") or 0.0
    if packets and still + flat > MOST * packets and flat_rate is not None and flat_rate > 0:
        high = (floor_rate > 0 and flat_rate >= HIGH_RATE_FLOOR_FACTOR * floor_rate) or \
            (moving_rate is not None and flat_rate >= HIGH_RATE_MOVING_FRACTION * moving_rate)
        if high and flat > MOST * (still + flat):
            reasons.append(f"{still + flat} of {packets} packets set to omega = 0 while events arrive at "
                           f"{flat_rate / 1e6:.3g} M ev/s (the motion is likely lost, not stopped)")
    return reasons


def _backend_reasons(be: dict) -> list[str]:
    windows = int(be.get("windows", 0)) - int(be.get("windows_still", 0))
    rejected = int(be.get("windows_rejected", 0))
    if windows > 0 and rejected > MOST * windows:
        return [f"{rejected} of {windows} back-end windows rejected (false maxima: they kept their initialisation)"]
    return []


def _coverage_reasons(events_range, trajectory_range) -> list[str]:
    if events_range is None or trajectory_range is None:
        return []
    (e0, e1), (t0, t1) = (float(v) for v in events_range), (float(v) for v in trajectory_range)
    if e1 <= e0:
        return []
    covered = max(0.0, min(e1, t1) - max(e0, t0)) / (e1 - e0)
    if covered < MIN_COVERAGE:
        return [f"the trajectory [{t0:.3f}, {t1:.3f}] s covers {100 * covered:.0f} % of the events' time range "
                f"[{e0:.3f}, {e1:.3f}] s"]
    return []


def run_status(report: dict, *, events_range=None, trajectory_range=None) -> tuple[str, list[str]]:
    """(status, reasons) of a run from its report's counters: ``frontend`` (FrontendResult.summary; the frontend
    command's ``summary``), ``backend`` (windows, windows_still, windows_rejected) and, when given, the time ranges
    of the events and of the trajectory. A method's own "lost" stays; otherwise "suspect" when there is a reason."""
    reasons: list[str] = []
    fe = report.get("frontend") or report.get("summary")
    if isinstance(fe, dict):
        reasons += _frontend_reasons(fe)
    if isinstance(report.get("backend"), dict):
        reasons += _backend_reasons(report["backend"])
    reasons += _coverage_reasons(events_range, trajectory_range)
    reasons += [str(w) for w in report.get("warnings") or [] if str(w) not in reasons]
    own = report.get("status", "ok")
    status = own if own not in ("ok", "suspect") else ("suspect" if reasons else "ok")
    return status, reasons


def apply_status(report: dict, **ranges) -> dict:
    """Set ``report["status"]`` and ``report["reasons"]`` (see run_status); returns the report."""
    report["status"], report["reasons"] = run_status(report, **ranges)
    return report


def status_text(report: dict) -> str:
    """The end of a command's summary line: "" when ok, else "; STATUS: reason; reason"."""
    status, reasons = report.get("status", "ok"), report.get("reasons") or []
    if status == "ok" and not reasons:
        return ""
    return f"; {status.upper()}" + (f": {'; '.join(reasons)}" if reasons else "")

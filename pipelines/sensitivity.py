"""Sensitivity of CMax-SLAM to its main parameters (paper Sec. IV-H, Fig. 19).

One parameter varies at a time around the reference defaults, on one simulated sequence: control-pose frequency
(1/dt_knots), time-window size (stride = half the window), panoramic map resolution, and event sampling rate
(front-end and back-end both keep 1 of Q). Each run reports the absolute and relative rotation RMSE against
ground truth and the runtime per input event (steady state, compilation apart).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from ti_cmax.config import SlamConfig, update_config
from ti_cmax.metrics import evaluate_rotations

# parameter -> (label, values, overrides builder)
SWEEPS = {
    "control_pose_frequency": ("control-pose frequency [Hz]", (10.0, 20.0, 40.0),
                               lambda v: {"dt_knots": 1.0 / v}),
    "window_size": ("time-window size [s]", (0.1, 0.2, 0.5, 1.0),
                    lambda v: {"backend_time_window_size": v, "backend_sliding_window_stride": v / 2}),
    "map_height": ("map resolution [px, height]", (128, 256, 512, 1024),
                   lambda v: {"pano_height": int(v)}),
    "event_sample_rate": ("event sampling rate Q", (1, 2, 5, 10),
                          lambda v: {"frontend_event_sample_rate": int(v), "backend_event_sample_rate": int(v)}),
}
QUICK_VALUES = {
    "control_pose_frequency": (10.0, 20.0),
    "window_size": (0.2, 0.5),
    "map_height": (256, 512),
    "event_sample_rate": (1, 5),
}


@dataclass
class SweepRow:
    parameter: str
    value: float
    abs_rmse_deg: float
    rel_rmse_deg_per_s: float
    us_per_event_frontend: float
    us_per_event_backend: float
    wall_seconds: float


def run_sweep(sequence, base: SlamConfig = SlamConfig(), parameters=tuple(SWEEPS), quick: bool = False,
              progress=None) -> list[SweepRow]:
    """Run CMax-SLAM on ``sequence`` (a SimulatedSequence) once per parameter value."""
    from .slam import run_slam

    rows = []
    for name in parameters:
        _, values, build = SWEEPS[name]
        for value in (QUICK_VALUES[name] if quick else values):
            cfg = update_config(base, build(value))
            tic = time.perf_counter()
            res = run_slam(sequence.events, sequence.camera, cfg)
            err = evaluate_rotations(sequence.groundtruth, res.trajectory)
            us = res.report["us_per_event"]
            rows.append(SweepRow(name, float(value), err.abs_rmse_deg, err.rel_rmse_deg_per_s,
                                 us["frontend"], us["backend"], time.perf_counter() - tic))
            if progress is not None:
                progress(rows[-1])
    return rows


def rows_to_markdown(rows: list[SweepRow]) -> str:
    lines = ["| parameter | value | abs RMSE [deg] | rel RMSE [deg/s] | front-end [us/ev] | back-end [us/ev] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {SWEEPS[r.parameter][0]} | {r.value:g} | {r.abs_rmse_deg:.3f} | {r.rel_rmse_deg_per_s:.3f} "
                     f"| {r.us_per_event_frontend:.2f} | {r.us_per_event_backend:.2f} |")
    return "\n".join(lines)


def plot_sweep(path, rows: list[SweepRow]) -> None:
    """Fig. 19-like figure: one column per parameter, abs error (left axis) and runtime (right axis)."""
    from matplotlib.figure import Figure

    params = list(dict.fromkeys(r.parameter for r in rows))
    fig = Figure(figsize=(4 * len(params), 3.2), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(params)))
    for ax, name in zip(axes, params):
        sel = [r for r in rows if r.parameter == name]
        x = [r.value for r in sel]
        ax.plot(x, [r.abs_rmse_deg for r in sel], "o-", color="tab:blue")
        ax.set_xlabel(SWEEPS[name][0])
        ax.set_ylabel("abs RMSE [deg]", color="tab:blue")
        if name in ("map_height", "event_sample_rate", "window_size"):
            ax.set_xscale("log")
        twin = ax.twinx()
        twin.plot(x, [r.us_per_event_frontend + r.us_per_event_backend for r in sel], "s--", color="tab:red")
        twin.set_ylabel("runtime [us/event]", color="tab:red")
    fig.savefig(path, dpi=120)


def rows_to_dicts(rows: list[SweepRow]) -> list[dict]:
    return [asdict(r) for r in rows]

"""Sensitivity of CMax-SLAM to its main parameters (paper Sec. IV-H, Fig. 19).

One parameter varies at a time around the reference defaults, on one simulated sequence: control-pose frequency
(1/dt_knots), time-window size (stride = half the window), panoramic map resolution, and event sampling rate
(front-end and back-end both keep 1 of Q). Each run reports the absolute and relative rotation RMSE against
ground truth and the runtime per input event (steady state, compilation apart). Each run is a task
(``pipelines.tasks``): runs go in parallel on a local pool or a Dask cluster and a rerun skips finished ones.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ti_cmax.config import SlamConfig, build_config, config_to_dict, update_config
from ti_cmax.pipelines.evaluation.benchmark import suite_tasks
from ti_cmax.pipelines.evaluation.methods import BenchmarkConfig
from ti_cmax.pipelines.evaluation.tasks import LocalExecutor, run_tasks

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
    status: str = "ok"  # or "failed: <error>" (the run's task failed; figures nan)


def sweep_configs(base: SlamConfig = SlamConfig(), parameters=tuple(SWEEPS), quick: bool = False) -> list:
    """(run name, parameter, value, SlamConfig) per run: one parameter varied at a time around ``base``."""
    runs = []
    for name in parameters:
        _, values, build = SWEEPS[name]
        for value in (QUICK_VALUES[name] if quick else values):
            runs.append((f"{name}={value:g}", name, float(value), update_config(base, build(value))))
    return runs


def as_task_config(cfg: SlamConfig):
    """A SlamConfig as the task model's BenchmarkConfig: CMax-SLAM at its own spline degree only."""
    values = {**config_to_dict(cfg), "benchmark": {"slam_degrees": str(cfg.backend.spline_degree)}}
    return build_config(BenchmarkConfig, values, source="sweep")


def run_sweep(dataset, name: str, base: SlamConfig = SlamConfig(), parameters=tuple(SWEEPS), quick: bool = False,
              *, out_dir, executor=None, quiet: bool = True, log=None) -> list[SweepRow]:
    """CMax-SLAM on the dataset at ``dataset`` (with ground truth) once per parameter value, each run a task
    (``pipelines.tasks``) with its files in out_dir/tasks; finished runs are skipped on a rerun."""
    runs = sweep_configs(base, parameters, quick)
    tasks = suite_tasks([(name, str(dataset), {})], ["cmax-slam"], {r[0]: as_task_config(r[3]) for r in runs})
    summary = run_tasks(tasks, out_dir, executor or LocalExecutor(), quiet=quiet, log=log)
    rows = []
    for (_, param, value, _), res in zip(runs, summary.results):
        slam = [r for r in res.get("rows", []) if r["kind"] == "slam"]
        r = slam[0] if slam else {}
        status = "ok" if r.get("status") == "ok" else \
            f"failed: {res.get('error') or r.get('note') or r.get('status')}"
        nan = float("nan")
        rows.append(SweepRow(param, value, _num(r.get("abs_rmse_deg")), _num(r.get("rel_rmse_deg_per_s")),
                             _num(r.get("frontend_us_per_event")), _num(r.get("backend_us_per_event")),
                             res.get("wall_seconds") or nan, status))
    return rows


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def rows_to_markdown(rows: list[SweepRow]) -> str:
    lines = ["| parameter | value | abs RMSE [deg] | rel RMSE [deg/s] | front-end [us/ev] | back-end [us/ev] |",
             "|---|---|---|---|---|---|"]
    failed = [r for r in rows if r.status != "ok"]
    for r in rows:
        lines.append(f"| {SWEEPS[r.parameter][0]} | {r.value:g} | {r.abs_rmse_deg:.3f} | {r.rel_rmse_deg_per_s:.3f} "
                     f"| {r.us_per_event_frontend:.2f} | {r.us_per_event_backend:.2f} |")
    lines += [""] + [f"- {r.parameter}={r.value:g}: {r.status}" for r in failed] if failed else []
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

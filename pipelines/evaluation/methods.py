"""One benchmark method on one sequence: the benchmark's parameters, the sequences simulated on demand, the
methods run (front-ends, their offline BA, CMax-SLAM, ground truth) and their rows scored against ground truth
(what one task of ``ti-cmax benchmark`` does, :func:`run_method`)."""
from __future__ import annotations

import dataclasses
import json
import shutil
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ti_cmax.config import Params, SlamConfig, param, update_config
from ti_cmax.errors import InputError
from ti_cmax.io import open_dataset_from_config
from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude, revolution_errors, worst_stretch
from ti_cmax.simulate import SimulatorConfig, simulate_to_folder

from ti_cmax.pipelines.frontend import as_chunks, estimate_angular_velocity
from ti_cmax.pipelines.panorama import render_panorama
from ti_cmax.pipelines.slam import refine, run_slam
from ti_cmax.pipelines.baselines.imu import dead_reckoning
from ti_cmax.pipelines.workflows.grayscale import resolve_contrast
from ti_cmax.pipelines.evaluation.bench_slam import _slam_extra
from ti_cmax.pipelines.evaluation.suites import FRONTENDS, LABELS, METHOD_KEYS, SUITES, SequenceSpec

try:  # an unimportable baselines registry gives "not implemented" rows instead of stopping the benchmark
    from ti_cmax.pipelines.baselines import BASELINES, BaselineConfig
    BASELINES_IMPORT_ERROR = None
except Exception as exc:  # noqa: BLE001 - any failure of the registry only removes the baselines
    BASELINES, BaselineConfig = {}, None
    BASELINES_IMPORT_ERROR = f"{type(exc).__name__}: {exc}"


DEGREE_NAMES = {1: "linear", 3: "cubic"}
STATUS = ("ok", "lost", "not implemented", "skipped", "error", "failed")  # failed: the task itself failed

# --quick: two short sequences, linear BA only, at a 512x256 map for the SLAM and BA rows, capped CG iterations
QUICK_SEQUENCES = ("playroom", "city")
QUICK_SETTINGS = {"duration": 1.5, "ba_degrees": "1", "ba_pano_height": 256}
# the flat "pano_height" resolves to smt.mapping.pano_height in BenchmarkConfig (ambiguous name): the back-end's is
# named in full
QUICK_OVERRIDES = {"pano_height": 256, "backend.pano_height": 256, "frontend_cg_max_iters": 20,
                   "backend_cg_max_iters": 10}

ROW_FIELDS = ("sequence", "sensor", "scene", "duration_s", "events", "method", "key", "kind", "source",
              "spline_degree", "status", "note", "lost_at", "abs_rmse_deg", "rel_rmse_deg_per_s", "abs_max_deg",
              "num_rel", "ea_percent", "gm", "map_events", "frontend_us_per_event", "backend_us_per_event",
              "us_per_event", "compile_seconds", "wall_seconds", "worst_stretch_deg", "turn_swing_deg", "loops_applied")


@dataclass(frozen=True)
class BenchmarkSettings(Params):
    """The benchmark's own parameters (section ``benchmark``)."""

    seed: int = param(0, "simulator seed of the first sequence (the others: seed + their index in the suite)")
    duration: float = param(0.0, "length of each sequence", unit="s", gt=0,
                            zero="each sequence's own (2.5 s playroom, 5 s the others)")
    map_height: int = param(512, "Tab. IV maps: 2 map_height x map_height (the paper's 1024x512)", unit="px", ge=8)
    ba_degrees: str = param("1,3", "spline degrees of the offline BA rows: 1, 3 or 1,3 (empty: none)")
    ba_pano_height: int = param(0, "map height of the BA rows' back-end", unit="px", ge=8, zero="backend.pano_height")
    # denser source trajectories (IMU 1 kHz, RTPT ~2 kHz) are resampled to this rate (Slerp) before the BA: it only
    # initializes control poses every dt_knots, and the back-end's cost grows with the source's pose count
    # (measured, city 5 s, cubic BA: 195 s from RTPT's poses vs 13-17 s from CMax-omega's 100 Hz); 0: as given
    ba_source_rate: float = param(200.0, "denser BA sources are resampled to this rate", unit="Hz", gt=0,
                                  zero="as given")
    slam_degrees: str = param("1,3", "spline degrees of the CMax-SLAM rows (the sweep runs one)")

    def _relations(self) -> None:
        self.degrees()
        self.degrees("slam_degrees")

    def degrees(self, name: str = "ba_degrees") -> tuple[int, ...]:
        """Spline degrees listed in ``ba_degrees`` (or ``slam_degrees``)."""
        text = getattr(self, name)
        out = []
        for s in str(text).replace(" ", "").split(","):
            if not s:
                continue
            if s not in ("1", "3"):
                raise InputError(f"benchmark.{name}: expected 1 and/or 3, got {text!r}")
            out.append(int(s))
        return tuple(dict.fromkeys(out))


def _make_config_class():
    """BenchmarkConfig: SlamConfig's sections, the baselines' sections (whatever BaselineConfig holds) and
    ``benchmark``. Shared sections (dataset, backend, output) are one, so ``--set pano_height=...`` reaches all."""
    sections: dict[str, type] = dict(typing.get_type_hints(SlamConfig))
    if BaselineConfig is not None:
        for name, typ in typing.get_type_hints(BaselineConfig).items():
            sections.setdefault(name, typ)
    sections["benchmark"] = BenchmarkSettings
    cls = dataclasses.make_dataclass(
        "BenchmarkConfig", [(n, t, field(default_factory=t)) for n, t in sections.items()], frozen=True)
    cls.__module__ = __name__
    cls.__doc__ = "All parameters of ``ti-cmax benchmark`` (CMax-SLAM, BA, baselines, benchmark settings)."
    return cls


BenchmarkConfig = _make_config_class()


def slam_config(cfg, degree: int | None = None, pano_height: int = 0) -> SlamConfig:
    """The SlamConfig inside a BenchmarkConfig (optionally with another spline degree / map height)."""
    out = SlamConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(SlamConfig)})
    values = {}
    if degree is not None:
        values["spline_degree"] = int(degree)
    if pano_height:
        values["pano_height"] = int(pano_height)
    return update_config(out, values) if values else out


def ba_source(traj, rate: float):
    """The trajectory given to the BA: resampled at ``rate`` Hz (same time range) when it is denser."""
    if not rate or len(traj) < 2 or (len(traj) - 1) <= rate * (traj.t_end - traj.t_start):
        return traj
    times = np.append(np.arange(traj.t_start, traj.t_end, 1.0 / rate), traj.t_end)
    times = times[np.concatenate([[True], np.diff(times) > 1e-9])]
    return traj.resampled(times)


def baseline_config(cfg):
    return BaselineConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(BaselineConfig)})


def quick_overrides() -> dict:
    return {**QUICK_OVERRIDES, **{f"benchmark.{k}": v for k, v in QUICK_SETTINGS.items()}}


# ------------------------------------------------------------------------------------------------------------
# sequences
# ------------------------------------------------------------------------------------------------------------

def resolve_sequences(names: list[str] | None, quick: bool = False, suite: str = "paper") -> list[SequenceSpec]:
    """Sequences of ``suite`` by name (default: all of it; ``quick``: QUICK_SEQUENCES of the paper suite)."""
    if suite not in SUITES:
        raise InputError(f"--suite: unknown {suite!r} (expected one of {', '.join(SUITES)})")
    specs = SUITES[suite]
    names = list(names) if names else list(QUICK_SEQUENCES if quick and suite == "paper" else specs)
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise InputError(f"--sequences: unknown {', '.join(unknown)} (expected some of {', '.join(specs)})")
    return [specs[n] for n in dict.fromkeys(names)]


# methods of a suite when --methods is not given (the sensor suite: the front-end and CMax-SLAM only; SMT or
# RTPT on 30 M events/s of HD data would take hours)
SUITE_METHODS = {"sensors": ("cmax-omega", "cmax-slam"), "realtime": ("cmax-omega", "cmax-slam"),
                 "heldout": ("smt-ekf", "smt-pf", "cmax-omega"), "long": ("cmax-slam",)}


def resolve_methods(keys: list[str] | None, suite: str = "paper") -> list[str]:
    keys = list(keys) if keys else list(SUITE_METHODS.get(suite, METHOD_KEYS))
    unknown = [k for k in keys if k not in METHOD_KEYS]
    if unknown:
        raise InputError(f"--methods: unknown {', '.join(unknown)} (expected some of {', '.join(METHOD_KEYS)})")
    return [k for k in METHOD_KEYS if k in keys]


def _simulator_config(spec: SequenceSpec, settings: BenchmarkSettings):
    return SimulatorConfig(scene=spec.scene, sensor=spec.sensor, duration=settings.duration or spec.duration,
                           trajectory=spec.trajectory, seed=settings.seed + spec.seed,
                           **dict(spec.options)).resolved()  # as simulation.json records it


def sequence_folder(spec: SequenceSpec, settings: BenchmarkSettings, cache_dir) -> Path:
    sim = _simulator_config(spec, settings)
    return Path(cache_dir) / f"{spec.name}-{sim.sensor}-{sim.scene}-{sim.duration:g}s-seed{sim.seed}"


def ensure_sequence(spec: SequenceSpec, settings: BenchmarkSettings, cache_dir, show_progress: bool = False):
    """Folder of the simulated sequence (simulated now unless a complete one with the same config is cached).

    Returns (folder, info from simulation.json, seconds spent simulating (0 when cached))."""
    sim = _simulator_config(spec, settings)
    folder = sequence_folder(spec, settings, cache_dir)
    meta = folder / "simulation.json"
    wanted = json.loads(json.dumps(dataclasses.asdict(sim)))
    if meta.is_file():
        info = json.loads(meta.read_text())
        if info.get("config") == wanted:
            return folder, info, 0.0
    if folder.exists():  # incomplete or made with other simulator settings: it is ours to redo
        shutil.rmtree(folder)
    tic = time.perf_counter()
    info = simulate_to_folder(sim, folder, show_progress=show_progress)
    return folder, info, time.perf_counter() - tic


# ------------------------------------------------------------------------------------------------------------
# rows
# ------------------------------------------------------------------------------------------------------------

@dataclass
class MethodRun:
    """One row's outcome before scoring: a trajectory (None unless usable) and its report figures."""

    key: str
    method: str
    kind: str  # "reference" (ground truth), "front-end", "ba", "slam"
    status: str
    trajectory: object = None
    source: str = ""
    spline_degree: int | None = None
    note: str = ""
    lost_at: float | None = None
    frontend_us: float | None = None
    backend_us: float | None = None
    compile_s: float | None = None
    wall_s: float | None = None
    extra: dict = field(default_factory=dict)


def _us(report: dict, part: str = "frontend") -> float | None:
    v = report.get("us_per_event")
    if isinstance(v, dict):
        v = v.get(part)
    return None if v is None else float(v)


def _run_baseline(key, events, camera, cfg, imu, contrast_threshold=None) -> MethodRun:
    label = LABELS[key]
    if key not in BASELINES:
        why = BASELINES_IMPORT_ERROR or f"{key!r} is not in the baselines registry"
        return MethodRun(key, label, "front-end", "not implemented", note=why)
    extra = {"contrast_threshold": contrast_threshold} if key.startswith("smt") and contrast_threshold else {}
    res = BASELINES[key](events, camera, baseline_config(cfg), imu, **extra)
    rep = res.report
    status = rep.get("status", "ok")
    lost_at = rep.get("lost_at")
    run = MethodRun(key, label, "front-end", "lost" if status == "lost" else "ok", trajectory=res.trajectory,
                    lost_at=None if lost_at is None else float(lost_at), frontend_us=_us(rep),
                    compile_s=rep.get("compile_seconds"), wall_s=rep.get("wall_seconds"))
    if run.status == "lost":
        run.note = f"lost at {run.lost_at:.2f} s" if run.lost_at is not None else "lost"
        if rep.get("lost_reason"):
            run.note += f" ({rep['lost_reason']})"
    return run


def _chunks(events):
    """Fresh input for one run: ``events`` is an ``Events`` object or a zero-argument callable returning an
    iterable of chunks (a dataset read again for each run, so memory does not grow with the file)."""
    return events() if callable(events) else events


def _guarded(key, label, kind, fn, **kw) -> MethodRun:
    """``fn()``'s MethodRun, or an "error" row with the exception: one failing method must not sink the
    benchmark; wall_s measured here when the method does not report it."""
    tic = time.perf_counter()
    try:
        run = fn()
    except Exception as exc:  # noqa: BLE001 - reported as the method's row
        run = MethodRun(key, label, kind, "error", note=f"{type(exc).__name__}: {exc}"[:300], **kw)
    if run.wall_s is None:
        run.wall_s = time.perf_counter() - tic
    return run


def _frontend_run(key, events, camera, cfg, imu, contrast_threshold) -> MethodRun:
    """One front-end (a FRONTENDS key) on the sequence, as in :func:`run_sequence_methods`."""
    if key == "cmax-omega":  # the front-end of CMax-SLAM alone (the same packets as in its SLAM runs)
        def omega_run():
            res = estimate_angular_velocity(_chunks(events), camera, slam_config(cfg).frontend)
            t = res.timing
            return MethodRun("cmax-omega", LABELS["cmax-omega"], "front-end", "ok", trajectory=res.trajectory(),
                             frontend_us=t["us_per_event"], compile_s=t.get("compile_seconds"),
                             wall_s=t.get("wall_seconds"), extra={"packets": len(res)})
        return _guarded(key, LABELS[key], "front-end", omega_run)
    if key == "imu":
        def imu_run():
            if imu is None:
                raise InputError("the sequence has no IMU data")
            tic = time.perf_counter()
            traj = dead_reckoning(imu.t, imu.gyro)
            return MethodRun("imu", LABELS["imu"], "front-end", "ok", trajectory=traj,
                             wall_s=time.perf_counter() - tic)
        return _guarded("imu", LABELS["imu"], "front-end", imu_run)
    return _guarded(key, LABELS[key], "front-end",
                   lambda: _run_baseline(key, _chunks(events), camera, cfg, imu, contrast_threshold))


def run_sequence_methods(events, camera, groundtruth, imu, cfg, methods: list[str], on_row=None,
                         contrast_threshold=None) -> list[MethodRun]:
    """Run every selected method (and the BA of each front-end that kept track) on one sequence; "gt" in
    ``methods`` adds the ground-truth row (its map: the reference of Tab. IV). ``contrast_threshold``: the
    sequence's C for SMT (App. B: the simulator's value on synthetic data)."""
    settings = cfg.benchmark
    degrees = settings.degrees()
    runs: list[MethodRun] = []

    def add(run: MethodRun):
        runs.append(run)
        if on_row:
            on_row(run)

    if "gt" in methods:
        add(MethodRun("gt", LABELS["gt"], "reference", "ok" if groundtruth is not None else "skipped",
                      trajectory=groundtruth, note="" if groundtruth is not None else "no ground truth"))
    frontends: list[MethodRun] = []
    for key in FRONTENDS:
        if key not in methods:
            continue
        run = _frontend_run(key, events, camera, cfg, imu, contrast_threshold)
        frontends.append(run)
        add(run)
    for fe_run in frontends:
        for d in degrees:
            name = f"{fe_run.method} + BA ({DEGREE_NAMES[d]})"
            key = f"{fe_run.key}+ba{d}"
            if fe_run.status != "ok":  # the BA of a missing method is missing too; of a lost one, skipped
                status = "not implemented" if fe_run.status == "not implemented" else "skipped"
                add(MethodRun(key, name, "ba", status, source=fe_run.key, spline_degree=d,
                              note=f"front-end {fe_run.status}"))
                continue

            def ba_run(traj=fe_run.trajectory, d=d, key=key, name=name, src=fe_run.key):
                res = refine(_chunks(events), camera, ba_source(traj, settings.ba_source_rate),
                             slam_config(cfg, d, settings.ba_pano_height))
                rep = res.report
                return MethodRun(key, name, "ba", "ok", trajectory=res.trajectory, source=src, spline_degree=d,
                                 backend_us=_us(rep, "backend"), compile_s=rep["compile_seconds"],
                                 wall_s=rep["wall_seconds"], extra=_slam_extra(rep))
            add(_guarded(key, name, "ba", ba_run, source=fe_run.key, spline_degree=d))
    if "cmax-slam" in methods:
        for d in settings.degrees("slam_degrees"):
            def slam_run(d=d):
                res = run_slam(_chunks(events), camera, slam_config(cfg, d))
                rep = res.report
                return MethodRun(f"cmax-slam{d}", f"CMax-SLAM ({DEGREE_NAMES[d]})", "slam", "ok",
                                 trajectory=res.trajectory, spline_degree=d, frontend_us=_us(rep, "frontend"),
                                 backend_us=_us(rep, "backend"), compile_s=rep["compile_seconds"],
                                 wall_s=rep["wall_seconds"], extra=_slam_extra(rep))
            add(_guarded(f"cmax-slam{d}", f"CMax-SLAM ({DEGREE_NAMES[d]})", "slam", slam_run, spline_degree=d))
    return runs


def long_recording_figures(groundtruth, err) -> dict:
    """The worst 0.2 s stretch of the start-aligned abs error and its error per revolution of a pan
    (``metrics.worst_stretch``, ``metrics.revolution_errors``; swing None without a complete turn)."""
    worst, worst_at = worst_stretch(err.abs_times, err.abs_errors_deg)
    turns = revolution_errors(groundtruth, err.abs_times, err.abs_errors_deg).to_dict()
    return {"worst_stretch_deg": worst, "worst_stretch_at_s": worst_at, "turn_swing_deg": turns["swing_deg"],
            "turn_means_deg": turns["means_deg"]}


def score(run: MethodRun, groundtruth, events, camera, cfg) -> tuple[dict, dict]:
    """Row dict of a run (errors vs ground truth if any, EA/GM of its panoramic IWE) and its per-sample arrays +
    map. ``events`` as in :func:`run_sequence_methods`."""
    row = {k: None for k in ROW_FIELDS}
    fe, be = run.frontend_us, run.backend_us
    total = None if fe is None and be is None else (fe or 0.0) + (be or 0.0)
    row.update(method=run.method, key=run.key, kind=run.kind, source=run.source or None,
               spline_degree=run.spline_degree, status=run.status, note=run.note or None, lost_at=run.lost_at,
               frontend_us_per_event=fe, backend_us_per_event=be, us_per_event=total,
               compile_seconds=run.compile_s, wall_seconds=run.wall_s)
    row.update(run.extra)
    arrays = {}
    if run.trajectory is None or len(run.trajectory) < 2:
        return row, arrays
    if run.kind != "reference" and groundtruth is not None:
        err = evaluate_rotations(groundtruth, run.trajectory)
        prefix = "" if run.status == "ok" else "partial_"  # a lost method's figures stay out of the tables
        row.update({f"{prefix}abs_rmse_deg": err.abs_rmse_deg, f"{prefix}rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
                    f"{prefix}abs_max_deg": err.abs_max_deg, "num_rel": err.num_rel})
        arrays["trajectory_aligned"] = run.trajectory.aligned_to(groundtruth, err.t0)
        if run.status == "ok":
            arrays["abs"], arrays["rel"] = err.abs_errors_deg, err.rel_errors_deg_per_s
            row.update(long_recording_figures(groundtruth, err))
    if run.status == "ok":
        h = cfg.benchmark.map_height
        pano = render_panorama(as_chunks(_chunks(events)), camera, run.trajectory, 2 * h, h,
                               batch_size=cfg.backend.event_batch_size)
        row.update(ea_percent=event_area_percent(pano.image, cfg.backend.lambda0),
                   gm=gradient_magnitude(pano.image), map_events=int(pano.events_used))
        arrays["map"] = pano.image
    return row, arrays


@dataclass
class MethodOutput:
    """What one task produces: scored rows, each row's trajectory (None for ground truth), the arrays of the plots
    (keys "<row index>_<abs|rel|map|t|R>") and facts about the dataset."""

    rows: list
    trajectories: list
    arrays: dict
    dataset_info: dict


def run_method(dataset, cfg, method: str, log=None) -> MethodOutput:
    """One task: ``method`` (a METHOD_KEYS key, or "gt") on the dataset at ``dataset``, scored. The events are
    streamed from the dataset for each run and each map."""
    ds = open_dataset_from_config(dataset, cfg.dataset)
    t0, t1 = ds.time_range()
    info = {"events": int(ds.num_events()), "duration_s": float(t1 - t0),
            "camera_size": [int(ds.camera.width), int(ds.camera.height)]}

    def events():
        return ds.iter_events(cfg.dataset.chunk_size)

    def on_row(run: MethodRun):
        if log:
            log(f"{run.method}: {run.status}" + (f", {run.wall_s:.1f} s" if run.wall_s is not None else "")
                + (f" ({run.note})" if run.note else ""))

    smt_c = resolve_contrast(cfg.smt.mapping, dataset) if hasattr(cfg, "smt") else None
    out = MethodOutput([], [], {}, info)
    for run in run_sequence_methods(events, ds.camera, ds.groundtruth, ds.imu, cfg, [method], on_row, smt_c):
        row, arr = score(run, ds.groundtruth, events, ds.camera, cfg)
        i = len(out.rows)
        out.rows.append(row)
        out.trajectories.append(None if run.kind == "reference" else run.trajectory)
        for k, v in arr.items():
            if k == "trajectory_aligned":
                out.arrays[f"{i}_t"], out.arrays[f"{i}_R"] = v.t, v.R
            else:
                out.arrays[f"{i}_{k}"] = v
    return out

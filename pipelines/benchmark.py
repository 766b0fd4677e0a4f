"""The paper's benchmark tables (Tab. II, IV, VI) on a suite of simulated sequences (``ti-cmax benchmark``).

Suite (modelled on the paper's synthetic sequences): ``playroom``, a 2.5 s DVS128 sequence (scene "town", indoor-like
large shapes), and 5 s DAVIS240C sequences with the textures ``bicycle``, ``city``, ``street``, ``town``, ``bay``.
Each sequence (its own seed: its own motion, scene layout and gyro bias) is simulated once into ``DIR/sequences/<name>-<sensor>-<scene>-<duration>s-seed<seed>`` (ECD layout,
:func:`ti_cmax.simulate.simulate_to_folder`; simulation.json is written last and marks a complete folder) and read
back from there, so a re-run skips simulation.

Per sequence, methods (``--methods`` keys in :data:`METHOD_KEYS`):

* front-ends: EKF-SMT, PF-SMT, RTPT, CMax-GAE (the baselines registry ``pipelines.baselines.BASELINES``), CMax-omega
  (the front-end of the CMax-SLAM linear run, integrated) and IMU dead reckoning;
* the offline BA (``refine``, linear and/or cubic: ``ba_degrees``) of every front-end trajectory that did not lose
  track; the BA of a lost front-end is a row with status "skipped";
* CMax-SLAM linear and cubic.

A baseline missing from the registry (or a registry that fails to import) gives rows with status "not implemented";
a method that raises gives a row with status "error" and the message: no method is silently dropped.
Every trajectory is scored against ground truth (``evaluate_rotations``, default t0) and rendered into a panoramic IWE
of ``2 map_height x map_height`` (1024x512 by default, Tab. IV) with ``render_panorama``; ground truth is rendered too.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ti_cmax.config import Params, SlamConfig, config_to_dict, param, update_config
from ti_cmax.errors import InputError

from .bench_slam import PAPER_TAB2, PAPER_TAB6, _fmt, _slam_extra, peak_rss_mb

try:  # the baselines are written concurrently: an unimportable registry means "not implemented" rows
    from .baselines import BASELINES, BaselineConfig
    BASELINES_IMPORT_ERROR = None
except Exception as exc:  # noqa: BLE001 - any failure of the registry only removes the baselines
    BASELINES, BaselineConfig = {}, None
    BASELINES_IMPORT_ERROR = f"{type(exc).__name__}: {exc}"


@dataclass(frozen=True)
class SequenceSpec:
    name: str
    sensor: str
    scene: str
    duration: float
    seed: int  # added to benchmark.seed: each sequence has its own motion, scene layout and gyro bias


SUITE = {s.name: s for s in (
    SequenceSpec("playroom", "DVS128", "town", 2.5, 0),
    SequenceSpec("bicycle", "DAVIS240C", "bicycle", 5.0, 1),
    SequenceSpec("city", "DAVIS240C", "city", 5.0, 2),
    SequenceSpec("street", "DAVIS240C", "street", 5.0, 3),
    SequenceSpec("town", "DAVIS240C", "town", 5.0, 4),
    SequenceSpec("bay", "DAVIS240C", "bay", 5.0, 5),
)}

# front-end keys in the paper's table order; "cmax-slam" adds the two SLAM rows
FRONTENDS = ("smt-ekf", "smt-pf", "rtpt", "cmax-gae", "cmax-omega", "imu")
METHOD_KEYS = FRONTENDS + ("cmax-slam",)
LABELS = {"smt-ekf": "EKF-SMT", "smt-pf": "PF-SMT", "rtpt": "RTPT", "cmax-gae": "CMax-GAE",
          "cmax-omega": "CMax-omega", "imu": "IMU dead reckoning", "cmax-slam": "CMax-SLAM", "gt": "ground truth"}
DEGREE_NAMES = {1: "linear", 3: "cubic"}
STATUS = ("ok", "lost", "not implemented", "skipped", "error")

# --quick: two short sequences, linear BA only, at a 512x256 map for the SLAM and BA rows, capped CG iterations
QUICK_SEQUENCES = ("playroom", "city")
QUICK_SETTINGS = {"duration": 1.5, "ba_degrees": "1", "ba_pano_height": 256}
QUICK_OVERRIDES = {"pano_height": 256, "frontend_cg_max_iters": 20, "backend_cg_max_iters": 10}

ROW_FIELDS = ("sequence", "sensor", "scene", "duration_s", "events", "method", "key", "kind", "source",
              "spline_degree", "status", "note", "lost_at", "abs_rmse_deg", "rel_rmse_deg_per_s", "abs_max_deg",
              "num_rel", "ea_percent", "gm", "map_events", "frontend_us_per_event", "backend_us_per_event",
              "us_per_event", "compile_seconds", "wall_seconds")


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

    def _relations(self) -> None:
        self.degrees()

    def degrees(self) -> tuple[int, ...]:
        out = []
        for s in str(self.ba_degrees).replace(" ", "").split(","):
            if not s:
                continue
            if s not in ("1", "3"):
                raise InputError(f"benchmark.ba_degrees: expected 1 and/or 3, got {self.ba_degrees!r}")
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

def resolve_sequences(names: list[str] | None, quick: bool = False) -> list[SequenceSpec]:
    names = list(names) if names else list(QUICK_SEQUENCES if quick else SUITE)
    unknown = [n for n in names if n not in SUITE]
    if unknown:
        raise InputError(f"--sequences: unknown {', '.join(unknown)} (expected some of {', '.join(SUITE)})")
    return [SUITE[n] for n in dict.fromkeys(names)]


def resolve_methods(keys: list[str] | None) -> list[str]:
    keys = list(keys) if keys else list(METHOD_KEYS)
    unknown = [k for k in keys if k not in METHOD_KEYS]
    if unknown:
        raise InputError(f"--methods: unknown {', '.join(unknown)} (expected some of {', '.join(METHOD_KEYS)})")
    return [k for k in METHOD_KEYS if k in keys]


def _simulator_config(spec: SequenceSpec, settings: BenchmarkSettings):
    from ti_cmax.simulate import SimulatorConfig

    return SimulatorConfig(scene=spec.scene, sensor=spec.sensor, duration=settings.duration or spec.duration,
                           seed=settings.seed + spec.seed).resolved()  # as simulation.json records it


def ensure_sequence(spec: SequenceSpec, settings: BenchmarkSettings, cache_dir, show_progress: bool = False):
    """Folder of the simulated sequence (simulated now unless a complete one with the same config is cached).

    Returns (folder, info from simulation.json, seconds spent simulating (0 when cached))."""
    from ti_cmax.simulate import simulate_to_folder

    sim = _simulator_config(spec, settings)
    folder = Path(cache_dir) / f"{spec.name}-{sim.sensor}-{sim.scene}-{sim.duration:g}s-seed{sim.seed}"
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


def run_sequence_methods(events, camera, groundtruth, imu, cfg, methods: list[str], on_row=None,
                         contrast_threshold=None) -> list[MethodRun]:
    """Run every selected method (and the BA of each front-end that kept track) on one sequence
    (``contrast_threshold``: the sequence's C for SMT, App. B: the simulator's value on synthetic data)."""
    from .imu import dead_reckoning
    from .slam import refine, run_slam

    settings = cfg.benchmark
    degrees = settings.degrees()
    runs: list[MethodRun] = []

    def add(run: MethodRun):
        runs.append(run)
        if on_row:
            on_row(run)

    def guarded(key, label, kind, fn, **kw) -> MethodRun:
        tic = time.perf_counter()
        try:
            run = fn()
        except Exception as exc:  # noqa: BLE001 - one failing method must not sink the benchmark
            run = MethodRun(key, label, kind, "error", note=f"{type(exc).__name__}: {exc}"[:300], **kw)
        if run.wall_s is None:
            run.wall_s = time.perf_counter() - tic
        return run

    add(MethodRun("gt", LABELS["gt"], "reference", "ok", trajectory=groundtruth))
    slam = {}
    if "cmax-slam" in methods or "cmax-omega" in methods:
        wanted = (1, 3) if "cmax-slam" in methods else (1,)
        for d in wanted:
            tic = time.perf_counter()
            try:
                slam[d] = run_slam(events, camera, slam_config(cfg, d))
            except Exception as exc:  # noqa: BLE001
                slam[d] = exc
            if isinstance(slam[d], Exception):
                slam[d] = (slam[d], time.perf_counter() - tic)
    frontends: list[MethodRun] = []
    for key in FRONTENDS:
        if key not in methods:
            continue
        if key == "cmax-omega":
            res = slam[1]
            if isinstance(res, tuple):
                run = MethodRun(key, LABELS[key], "front-end", "error", wall_s=res[1],
                                note=f"{type(res[0]).__name__}: {res[0]}"[:300])
            else:
                fe = res.frontend
                run = MethodRun(key, LABELS[key], "front-end", "ok", trajectory=fe.trajectory(),
                                frontend_us=_us(res.report, "frontend"), compile_s=fe.timing.get("compile_seconds"),
                                wall_s=fe.timing.get("wall_seconds"), extra={"packets": len(fe)})
        elif key == "imu":
            def imu_run():
                if imu is None:
                    raise InputError("the sequence has no IMU data")
                tic = time.perf_counter()
                traj = dead_reckoning(imu.t, imu.gyro)
                return MethodRun("imu", LABELS["imu"], "front-end", "ok", trajectory=traj,
                                 wall_s=time.perf_counter() - tic)
            run = guarded("imu", LABELS["imu"], "front-end", imu_run)
        else:
            run = guarded(key, LABELS[key], "front-end", lambda k=key: _run_baseline(k, events, camera, cfg, imu,
                                                                                  contrast_threshold))
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
                res = refine(events, camera, ba_source(traj, settings.ba_source_rate),
                             slam_config(cfg, d, settings.ba_pano_height))
                rep = res.report
                return MethodRun(key, name, "ba", "ok", trajectory=res.trajectory, source=src, spline_degree=d,
                                 backend_us=_us(rep, "backend"), compile_s=rep["compile_seconds"],
                                 wall_s=rep["wall_seconds"], extra=_slam_extra(rep))
            add(guarded(key, name, "ba", ba_run, source=fe_run.key, spline_degree=d))
    if "cmax-slam" in methods:
        for d in (1, 3):
            res = slam[d]
            name = f"CMax-SLAM ({DEGREE_NAMES[d]})"
            if isinstance(res, tuple):
                add(MethodRun(f"cmax-slam{d}", name, "slam", "error", spline_degree=d, wall_s=res[1],
                              note=f"{type(res[0]).__name__}: {res[0]}"[:300]))
                continue
            rep = res.report
            add(MethodRun(f"cmax-slam{d}", name, "slam", "ok", trajectory=res.trajectory, spline_degree=d,
                          frontend_us=_us(rep, "frontend"), backend_us=_us(rep, "backend"),
                          compile_s=rep["compile_seconds"], wall_s=rep["wall_seconds"], extra=_slam_extra(rep)))
    return runs


def score(run: MethodRun, groundtruth, events, camera, cfg) -> tuple[dict, dict]:
    """Row dict of a run (errors vs ground truth, EA/GM of its panoramic IWE) and its per-sample arrays + map."""
    from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude

    from .panorama import render_panorama

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
    if run.kind != "reference":
        err = evaluate_rotations(groundtruth, run.trajectory)
        prefix = "" if run.status == "ok" else "partial_"  # a lost method's figures stay out of the tables
        row.update({f"{prefix}abs_rmse_deg": err.abs_rmse_deg, f"{prefix}rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
                    f"{prefix}abs_max_deg": err.abs_max_deg, "num_rel": err.num_rel})
        arrays["trajectory_aligned"] = run.trajectory.aligned_to(groundtruth, err.t0)
        if run.status == "ok":
            arrays["abs"], arrays["rel"] = err.abs_errors_deg, err.rel_errors_deg_per_s
    if run.status == "ok":
        h = cfg.benchmark.map_height
        pano = render_panorama([events], camera, run.trajectory, 2 * h, h, batch_size=cfg.backend.event_batch_size)
        row.update(ea_percent=event_area_percent(pano.image, cfg.backend.lambda0),
                   gm=gradient_magnitude(pano.image), map_events=int(pano.events_used))
        arrays["map"] = pano.image
    return row, arrays


def bench_sequence(spec: SequenceSpec, cfg, methods: list[str], cache_dir, *, plots_dir=None, log=None) -> dict:
    """Simulate (or reuse) one sequence, run and score every method, optionally write its plots."""
    from ti_cmax.io import open_dataset

    settings = cfg.benchmark
    tic = time.perf_counter()
    load0 = os.getloadavg()
    folder, info, sim_s = ensure_sequence(spec, settings, cache_dir)
    ds = open_dataset(folder)
    events, camera, gt, imu = ds.read_events(), ds.camera, ds.groundtruth, ds.imu
    duration = float(info["duration"])
    base = {"sequence": spec.name, "sensor": spec.sensor, "scene": spec.scene, "duration_s": duration,
            "events": int(len(events))}
    rows, arrays = [], {}

    def on_row(run: MethodRun):
        if log and run.kind != "reference":
            extra = f" ({run.note})" if run.note else ""
            wall = f", {run.wall_s:.1f} s" if run.wall_s is not None else ""
            log(f"  {spec.name}: {run.method}: {run.status}{wall}{extra}")

    from ti_cmax.pipelines.mapping import resolve_contrast

    smt_c = resolve_contrast(cfg.smt.mapping, folder) if hasattr(cfg, "smt") else None
    for run in run_sequence_methods(events, camera, gt, imu, cfg, methods, on_row, smt_c):
        row, arr = score(run, gt, events, camera, cfg)
        rows.append({**row, **base})
        arrays[run.method] = arr
    result = {
        **base, "folder": str(folder), "event_rate_mev_s": len(events) / duration / 1e6,
        "simulate_seconds": sim_s, "cached": sim_s == 0.0, "gyro_bias_deg_s": np.degrees(info["gyro_bias"]).tolist(),
        "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg()), "peak_rss_mb": peak_rss_mb(),
        "wall_seconds": time.perf_counter() - tic, "rows": rows,
    }
    if plots_dir is not None:
        result["plots"] = write_plots(plots_dir, spec.name, arrays, gt)
    return result


# ------------------------------------------------------------------------------------------------------------
# plots
# ------------------------------------------------------------------------------------------------------------

def write_plots(plots_dir, name: str, arrays: dict, groundtruth) -> list[str]:
    """errors_<seq>.png (violins), trajectories_<seq>.png (per axis, aligned), maps_<seq>.png (side by side)."""
    from ti_cmax.plots import plot_error_distributions, plot_maps, plot_trajectories

    plots_dir = Path(plots_dir)
    plots_dir.mkdir(parents=True, exist_ok=True)
    written = []
    abs_e = {m: a["abs"] for m, a in arrays.items() if "abs" in a}
    rel_e = {m: a["rel"] for m, a in arrays.items() if "rel" in a}
    if abs_e:
        path = plots_dir / f"errors_{name}.png"
        plot_error_distributions(path, abs_e, rel_e, title=f"{name}: rotation errors")
        written.append(path.name)
    trajs = {m: a["trajectory_aligned"] for m, a in arrays.items() if "trajectory_aligned" in a and "+ BA" not in m}
    if trajs:
        path = plots_dir / f"trajectories_{name}.png"
        plot_trajectories(path, trajs, groundtruth, title=f"{name}: front-ends and CMax-SLAM vs ground truth")
        written.append(path.name)
    maps = [(m, a["map"]) for m, a in arrays.items() if "map" in a]
    if maps:
        path = plots_dir / f"maps_{name}.png"
        plot_maps(path, maps, title=f"{name}: panoramic IWE per trajectory")
        written.append(path.name)
    return written


# ------------------------------------------------------------------------------------------------------------
# tables
# ------------------------------------------------------------------------------------------------------------

def _method_order(results: list[dict]) -> list[tuple[str, str]]:
    """(method, kind) in first-seen order over all sequences."""
    seen = {}
    for res in results:
        for r in res["rows"]:
            seen.setdefault(r["method"], r["kind"])
    return list(seen.items())


class _Notes:
    def __init__(self):
        self.items: list[str] = []

    def ref(self, text: str) -> str:
        if text not in self.items:
            self.items.append(text)
        return f"[{self.items.index(text) + 1}]"

    def lines(self) -> list[str]:
        return [f"[{i}] {t}" for i, t in enumerate(self.items, start=1)]


def _cell(row: dict | None, keys_digits, notes: _Notes, seq: str, show_lost: bool = False) -> list[str]:
    """Cells of one method in one sequence: figures if ok, else the status (with a note). ``show_lost``: a lost
    run still shows its figures (runtime: they cover the events processed until the loss), tagged."""
    if row is None:
        return ["n/a"] * len(keys_digits)
    figures = [_fmt(row[k], d) if row[k] is not None else "-" for k, d in keys_digits]
    if row["status"] == "ok":
        return figures
    if row["status"] == "not implemented":
        return ["not implemented"] + [""] * (len(keys_digits) - 1)
    tag = notes.ref(f"{row['method']} on {seq}: {row['status']}" + (f", {row['note']}" if row.get("note") else ""))
    if show_lost and row["status"] == "lost" and figures[0] != "-":
        return [f"{figures[0]} {tag}"] + figures[1:]
    return [f"- {tag}"] + ["-"] * (len(keys_digits) - 1)


def _grid(results, kinds, keys_digits, sub_headers, notes, show_lost: bool = False) -> list[str]:
    seqs = [r["sequence"] for r in results]
    by = {(res["sequence"], r["method"]): r for res in results for r in res["rows"]}
    header = "| method | " + " | ".join(f"{s} {h}" for s in seqs for h in sub_headers) + " |"
    lines = [header, "|---" * (1 + len(seqs) * len(sub_headers)) + "|"]
    for method, kind in _method_order(results):
        if kind not in kinds:
            continue
        cells = []
        for res in results:
            cells += _cell(by.get((res["sequence"], method)), keys_digits, notes, res["sequence"], show_lost)
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def format_tables(results: list[dict], meta: dict) -> str:
    """tables.md: Tab. II (accuracy), Tab. IV (map sharpness), Tab. VI (runtime) and the runtime of every row."""
    notes = _Notes()
    out = ["# CMax-SLAM benchmark (simulated suite)", ""]
    out.append("Sequences: " + "; ".join(
        f"{r['sequence']} = {r['sensor']} {r['scene']} {r['duration_s']:g} s, {r['events']} events "
        f"({r['event_rate_mev_s']:.2f} Mev/s)" for r in results))
    out.append(f"Settings: {meta.get('settings_line', '')}")
    out += ["", "## Tab. II: absolute [deg] / relative [deg/s] rotation RMSE", ""]
    out += _grid(results, ("front-end", "ba", "slam"), (("abs_rmse_deg", 3), ("rel_rmse_deg_per_s", 3)),
                 ("abs", "rel"), notes)
    out += ["", "## Tab. IV: event area EA% and gradient magnitude GM of the panoramic IWE "
            f"({2 * meta['map_height']}x{meta['map_height']})", ""]
    out += _grid(results, ("reference", "front-end", "ba", "slam"), (("ea_percent", 2), ("gm", 4)),
                 ("EA%", "GM"), notes)
    out += ["", "## Tab. VI: runtime of CMax-SLAM [us/event] (steady state; compilation apart)", "",
            "| sequence | events | front-end | back-end linear | back-end cubic | compile s (FE+BE, linear run) |",
            "|---|---|---|---|---|---|"]
    for res in results:
        by = {r["method"]: r for r in res["rows"]}
        lin, cub = by.get("CMax-SLAM (linear)"), by.get("CMax-SLAM (cubic)")
        fe = lin if lin else by.get("CMax-omega")

        def val(r, k, d=2):
            return _fmt(r[k], d) if r and r["status"] == "ok" and r[k] is not None else "-"
        out.append(f"| {res['sequence']} | {res['events']} | {val(fe, 'frontend_us_per_event')} | "
                   f"{val(lin, 'backend_us_per_event')} | {val(cub, 'backend_us_per_event')} | "
                   f"{val(lin, 'compile_seconds', 1)} |")
    out += ["", "## Runtime of every method: us/event (compilation apart) / wall s (with compilation)", ""]
    out += _grid(results, ("front-end", "ba", "slam"), (("us_per_event", 2), ("wall_seconds", 1)),
                 ("us/ev", "wall s"), notes, show_lost=True)
    out += ["", "## Per sequence", "",
            "| sequence | simulate s (0: cached) | benchmark wall s | load avg start / end (1 min) | peak RSS MB |",
            "|---|---|---|---|---|"]
    for res in results:
        out.append(f"| {res['sequence']} | {res['simulate_seconds']:.1f} | {res['wall_seconds']:.1f} | "
                   f"{res['loadavg_start'][0]:.2f} / {res['loadavg_end'][0]:.2f} | {res['peak_rss_mb']:.0f} |")
    out += ["", "## Notes", ""]
    out += notes.lines() or ["(none)"]
    out += ["", "- \"-\": lost (trajectory cut at lost_at; figures of the part before are in results.json as "
            "partial_*; runtimes of a lost run, tagged, cover the events processed until the loss), skipped (BA "
            "of a lost or failed front-end) or error; \"not implemented\": the method is not in the baselines "
            "registry" + (f" (registry import failed: {BASELINES_IMPORT_ERROR})"
                                               if BASELINES_IMPORT_ERROR else "") + ".",
            "- rel RMSE uses 1 s pairs every 0.1 s (nan if the sequence is shorter); errors at each estimate's own "
            "timestamps after alignment at t0 = start of the overlap + 0.1 s.",
            "- CMax-omega is the front-end of the CMax-SLAM linear run (same packets), integrated from the identity.",
            f"- Paper, synthetic: CMax-SLAM abs {PAPER_TAB2['abs_rmse_deg'][0]}-{PAPER_TAB2['abs_rmse_deg'][1]} deg, "
            f"rel {PAPER_TAB2['rel_rmse_deg_per_s'][0]}-{PAPER_TAB2['rel_rmse_deg_per_s'][1]} deg/s (Tab. II); "
            f"back-end {PAPER_TAB6['linear'][0]}-{PAPER_TAB6['linear'][1]} us/event linear, "
            f"{PAPER_TAB6['cubic'][0]}-{PAPER_TAB6['cubic'][1]} cubic (Tab. VI, C++).",
            f"- Timings are only comparable on an idle machine: load averages above; {meta.get('threads_line', '')}"]
    return "\n".join(out) + "\n"


def rows_for_csv(results: list[dict]) -> list[dict]:
    return [{k: r.get(k) for k in ROW_FIELDS} for res in results for r in res["rows"]]


def json_ready(obj):
    """NaN/inf -> None, numpy scalars -> Python (results.json is strict JSON)."""
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def run_benchmark(cfg, sequences: list[SequenceSpec], methods: list[str], out_dir, *, log=None,
                  plots: bool = True) -> list[dict]:
    """Run the suite; sequences are cached in out_dir/sequences, plots go to out_dir/plots. Returns the results."""
    out_dir = Path(out_dir)
    results = []
    for spec in sequences:
        if log:
            log(f"{spec.name}: {spec.sensor} {spec.scene} {cfg.benchmark.duration or spec.duration:g} s")
        res = bench_sequence(spec, cfg, methods, out_dir / "sequences",
                             plots_dir=(out_dir / "plots") if plots else None, log=log)
        results.append(res)
        if log:
            log(f"{spec.name}: done in {res['wall_seconds']:.1f} s (simulation {res['simulate_seconds']:.1f} s)")
    return results


def settings_line(cfg, quick: bool) -> str:
    b = cfg.backend
    s = cfg.benchmark
    size = f"{b.pano_size[0]}x{b.pano_size[1]}" if b.pano_height else "derived from the focal length"
    return (f"back-end map {size}, BA map height {s.ba_pano_height or b.pano_height or 'derived'}, "
            f"BA degrees {','.join(map(str, s.degrees())) or 'none'}, frontend_cg_max_iters "
            f"{cfg.frontend.frontend_cg_max_iters}, backend_cg_max_iters {b.backend_cg_max_iters}, seed {s.seed}"
            + (" [quick]" if quick else ""))


__all__ = ["SUITE", "SequenceSpec", "FRONTENDS", "METHOD_KEYS", "LABELS", "BenchmarkConfig", "BenchmarkSettings",
           "QUICK_SEQUENCES", "quick_overrides", "resolve_sequences", "resolve_methods", "ensure_sequence",
           "run_sequence_methods", "score", "bench_sequence", "run_benchmark", "format_tables", "rows_for_csv",
           "json_ready", "write_plots", "slam_config", "ROW_FIELDS"]

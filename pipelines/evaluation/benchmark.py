"""The paper's benchmark tables (Tab. II, IV, VI) on a suite of simulated sequences (``ti-cmax benchmark``).

Suites (``SUITES``, data: sensor, scene, duration, trajectory, seed per sequence). "paper" (modelled on the paper's
synthetic sequences): ``playroom``, a 2.5 s DVS128 sequence (scene "town", indoor-like
large shapes), and 5 s DAVIS240C sequences with the textures ``bicycle``, ``city``, ``street``, ``town``, ``bay``.
Each sequence (its own seed: its own motion, scene layout and gyro bias) is simulated once into ``DIR/sequences/<name>-<sensor>-<scene>-<duration>s-seed<seed>`` (ECD layout,
:func:`ti_cmax.simulate.simulate_to_folder`; simulation.json is written last and marks a complete folder) and read
back from there, so a re-run skips simulation.

Per sequence, methods (``--methods`` keys in :data:`METHOD_KEYS`):

* front-ends: EKF-SMT, PF-SMT, RTPT, CMax-GAE (the baselines registry ``pipelines.baselines.BASELINES``), CMax-omega
  (the front-end of CMax-SLAM alone, integrated) and IMU dead reckoning;
* the offline BA (``refine``, linear and/or cubic: ``ba_degrees``) of every front-end trajectory that did not lose
  track; the BA of a lost front-end is a row with status "skipped";
* CMax-SLAM linear and cubic.

Each method on each sequence is a task (``pipelines.tasks``: one process or machine runs it, writes its own files
in ``DIR/tasks/<sequence>-<method>/``, a rerun skips it); so is each sequence's ground-truth map. The tables are
built from the tasks' files.

A baseline missing from the registry (or a registry that fails to import) gives rows with status "not implemented";
a method that raises gives a row with status "error" and the message: no method is silently dropped.
Every trajectory is scored against ground truth (``evaluate_rotations``, default t0) and rendered into a panoramic IWE
of ``2 map_height x map_height`` (1024x512 by default, Tab. IV) with ``render_panorama``; ground truth is rendered too.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ti_cmax.config import config_to_dict
from ti_cmax.errors import InputError
from ti_cmax.io import open_dataset
from ti_cmax.outputs import json_ready
from ti_cmax.plots import plot_error_distributions, plot_maps, plot_trajectories
from ti_cmax.trajectory import Trajectory

from ti_cmax.pipelines.evaluation.bench_slam import PAPER_TAB2, PAPER_TAB6, _fmt
from ti_cmax.pipelines.evaluation.methods import (
    BASELINES, BASELINES_IMPORT_ERROR, QUICK_SEQUENCES, ROW_FIELDS, BenchmarkConfig, BenchmarkSettings, ensure_sequence, quick_overrides,
    resolve_methods, resolve_sequences, run_method, run_sequence_methods, score, sequence_folder, slam_config)
from ti_cmax.pipelines.evaluation.suites import FRONTENDS, LABELS, METHOD_KEYS, SUITE, SUITES, SequenceSpec, make_suite
from ti_cmax.pipelines.evaluation.tasks import TASKS_DIR, LocalExecutor, Task, dataset_fingerprint, run_calls, \
    run_tasks, task_id


# ------------------------------------------------------------------------------------------------------------
# a suite of tasks
# ------------------------------------------------------------------------------------------------------------

KIND_ORDER = {"reference": 0, "front-end": 1, "ba": 2, "slam": 3}


def method_kind(key: str) -> str:
    return "reference" if key == "gt" else "slam" if key == "cmax-slam" else "front-end"


def failed_row(method: str, error: str) -> dict:
    """The row of a task that failed as a whole (its exception, a lost worker)."""
    row = {k: None for k in ROW_FIELDS}
    row.update(method=LABELS.get(method, method), key=method, kind=method_kind(method), status="failed",
               note=str(error)[:300])
    return row


def prepare_sequences(sequences: list[SequenceSpec], settings: BenchmarkSettings, cache_dir, executor, *,
                      quiet: bool = True) -> dict:
    """Simulate the sequences not cached yet (in parallel on ``executor``). Returns name -> (folder, info,
    simulate seconds) or name -> error text for a sequence that could not be simulated."""
    Path(cache_dir).mkdir(parents=True, exist_ok=True)

    def remove_incomplete():  # after Ctrl-C stopped the workers: a folder without simulation.json is partial
        for spec in sequences:
            folder = sequence_folder(spec, settings, cache_dir)
            if folder.is_dir() and not (folder / "simulation.json").is_file():
                shutil.rmtree(folder, ignore_errors=True)

    executor.on_interrupt = remove_incomplete
    outs = run_calls(executor, ensure_sequence, [(spec, settings, str(cache_dir)) for spec in sequences],
                     desc="simulate", quiet=quiet)
    return {spec.name: (value if ok else str(value)) for spec, (ok, value) in zip(sequences, outs)}


def suite_tasks(datasets: list[tuple[str, str, dict]], methods: list[str], configs: dict) -> list:
    """Tasks for datasets x parameter sets x methods. ``datasets``: (name, path, labels); ``configs``: parameter
    set name -> BenchmarkConfig ("" for a single unnamed set)."""
    tasks = []
    for name, path, labels in datasets:
        fp = dataset_fingerprint(path)
        for pname, cfg in configs.items():
            cdict = config_to_dict(cfg)
            for m in methods:
                tasks.append(Task(task_id(pname, name, m), m, str(path), fp, cdict,
                                  {"sequence": name, **labels, **({"parameters": pname} if pname else {})}))
    return tasks


def group_results(tasks, results, extra: dict | None = None) -> list[dict]:
    """Per (parameter set, dataset), in task order: the fields :func:`format_tables` reads, rows in table order
    (ground truth, front-ends, BA rows, SLAM rows; tasks in the given order within each)."""
    groups: dict = {}
    for task, res in zip(tasks, results):
        key = (task.labels.get("parameters", ""), task.labels["sequence"])
        g = groups.get(key)
        if g is None:
            g = groups[key] = {**{k: task.labels.get(k, "") for k in ("sequence", "sensor", "scene", "parameters")},
                               "folder": task.dataset, "rows": [], "tasks": {"done": 0, "failed": 0},
                               "task_ids": [], "wall_seconds": 0.0, "loadavg_start": None, "loadavg_end": None,
                               "peak_rss_mb": 0.0, "events": 0, "duration_s": 0.0}
        g["task_ids"].append(task.id)
        if res.get("status") == "done":
            g["tasks"]["done"] += 1
            g["rows"] += [dict(r) for r in res["rows"]]
            info = res.get("dataset_info") or {}
            g["events"], g["duration_s"] = info.get("events", g["events"]), info.get("duration_s", g["duration_s"])
            if not g["sensor"] and info.get("camera_size"):
                g["sensor"] = "x".join(map(str, info["camera_size"]))
        else:
            g["tasks"]["failed"] += 1
            g["rows"].append({**task.labels, **failed_row(task.method, res.get("error", "failed"))})
        g["wall_seconds"] += res.get("wall_seconds") or 0.0
        g["loadavg_start"] = g["loadavg_start"] or res.get("loadavg_start")
        g["loadavg_end"] = res.get("loadavg_end") or g["loadavg_end"]
        g["peak_rss_mb"] = max(g["peak_rss_mb"], res.get("peak_rss_mb") or 0.0)
    out = []
    for g in groups.values():
        g.update((extra or {}).get(g["sequence"], {}))
        for r in g["rows"]:
            r.update(duration_s=g["duration_s"], events=g["events"])
        order = {m: i for i, m in enumerate(dict.fromkeys(r["key"].split("+")[0] for r in g["rows"]))}
        g["rows"].sort(key=lambda r: (KIND_ORDER.get(r["kind"], 9), order[r["key"].split("+")[0]]))
        g["event_rate_mev_s"] = g["events"] / g["duration_s"] / 1e6 if g["duration_s"] else 0.0
        g["loadavg_start"] = g["loadavg_start"] or [float("nan")] * 3
        g["loadavg_end"] = g["loadavg_end"] or [float("nan")] * 3
        out.append(g)
    return out


def plot_group(plots_dir, group: dict, out_dir, suffix: str = "", note: str = "") -> list[str]:
    """The plots of one dataset from its tasks' arrays.npz (nothing without ground truth)."""
    arrays: dict = {}
    for tid in group["task_ids"]:
        path = Path(out_dir) / TASKS_DIR / tid / "arrays.npz"
        result = Path(out_dir) / TASKS_DIR / tid / "result.json"
        if not path.is_file() or not result.is_file():
            continue
        rows = json.loads(result.read_text())["rows"]
        with np.load(path) as npz:
            for i, row in enumerate(rows):
                a = {k: npz[f"{i}_{k}"] for k in ("abs", "rel", "map") if f"{i}_{k}" in npz}
                if f"{i}_t" in npz:
                    a["trajectory_aligned"] = Trajectory(npz[f"{i}_t"], npz[f"{i}_R"])
                if a:
                    arrays[row["method"]] = a
    order = [r["method"] for r in group["rows"]]
    arrays = {m: arrays[m] for m in order if m in arrays}
    if not arrays:  # every task of the dataset failed (e.g. it cannot be read): nothing to plot, nor to open
        return []
    try:
        gt = open_dataset(group["folder"]).groundtruth
    except InputError:  # the tasks' results say what is wrong with the dataset: no plot rather than no tables
        return []
    if gt is None:
        return []
    return write_plots(plots_dir, group["sequence"] + suffix, arrays, gt, note)


def run_benchmark(cfg, sequences: list[SequenceSpec], methods: list[str], out_dir, *, executor=None, log=None,
                  plots: bool = True, quiet: bool = True, plot_note: str = "") -> list[dict]:
    """Run the suite as tasks (one per sequence and method, plus its ground-truth map) on ``executor`` (default:
    in this process). Sequences are cached in out_dir/sequences, task results in out_dir/tasks (finished ones are
    skipped on a rerun), plots go to out_dir/plots (``plot_note`` ends their titles, e.g. "smoke test"). Returns the
    per-sequence results."""
    out_dir = Path(out_dir)
    executor = executor or LocalExecutor()
    methods = [k for k in METHOD_KEYS if k in methods]  # the tables' order
    prepared = prepare_sequences(sequences, cfg.benchmark, out_dir / "sequences", executor, quiet=quiet)
    ready = [s for s in sequences if isinstance(prepared[s.name], tuple)]
    datasets = [(s.name, str(prepared[s.name][0]), {"sensor": s.sensor, "scene": s.scene}) for s in ready]
    tasks = suite_tasks(datasets, ["gt", *methods], {"": cfg})
    summary = run_tasks(tasks, out_dir, executor, quiet=quiet, log=log)
    extra = {}
    for s in ready:
        folder, info, sim_s = prepared[s.name]
        extra[s.name] = {"simulate_seconds": sim_s, "cached": sim_s == 0.0, "duration_s": float(info["duration"]),
                         "gyro_bias_deg_s": np.degrees(info["gyro_bias"]).tolist()}
    groups = {g["sequence"]: g for g in group_results(tasks, summary.results, extra)}
    results = []
    for s in sequences:
        if s.name not in groups:  # simulation failed: every method of it failed
            g = {"sequence": s.name, "sensor": s.sensor, "scene": s.scene, "duration_s": 0.0, "events": 0,
                 "event_rate_mev_s": 0.0, "simulate_seconds": 0.0, "cached": False, "wall_seconds": 0.0,
                 "loadavg_start": [float("nan")] * 3, "loadavg_end": [float("nan")] * 3, "peak_rss_mb": 0.0,
                 "tasks": {"done": 0, "failed": len(methods) + 1},
                 "rows": [failed_row(m, f"simulation failed: {prepared[s.name]}") for m in ["gt", *methods]]}
            for r in g["rows"]:
                r.update(sequence=s.name, sensor=s.sensor, scene=s.scene)
        else:
            g = groups[s.name]
            if plots:
                g["plots"] = plot_group(out_dir / "plots", g, out_dir, note=plot_note)
        g["tasks"]["skipped"] = sum(1 for t in tasks if t.labels["sequence"] == s.name and t.id in summary.skipped)
        results.append(g)
    return results


# ------------------------------------------------------------------------------------------------------------
# plots
# ------------------------------------------------------------------------------------------------------------

def write_plots(plots_dir, name: str, arrays: dict, groundtruth, note: str = "") -> list[str]:
    """errors_<seq>.png (violins), trajectories_<seq>.png (per axis, aligned), maps_<seq>.png (side by side);
    ``note`` ends every title."""
    note = f" ({note})" if note else ""
    plots_dir = Path(plots_dir)
    plots_dir.mkdir(parents=True, exist_ok=True)
    written = []
    abs_e = {m: a["abs"] for m, a in arrays.items() if "abs" in a}
    rel_e = {m: a["rel"] for m, a in arrays.items() if "rel" in a}
    if abs_e:
        path = plots_dir / f"errors_{name}.png"
        plot_error_distributions(path, abs_e, rel_e, title=f"{name}: rotation errors{note}")
        written.append(path.name)
    trajs = {m: a["trajectory_aligned"] for m, a in arrays.items() if "trajectory_aligned" in a and "+ BA" not in m}
    if trajs:
        path = plots_dir / f"trajectories_{name}.png"
        plot_trajectories(path, trajs, groundtruth, title=f"{name}: front-ends and CMax-SLAM vs ground truth{note}")
        written.append(path.name)
    maps = [(m, a["map"]) for m, a in arrays.items() if "map" in a]
    if maps:
        path = plots_dir / f"maps_{name}.png"
        plot_maps(path, maps, title=f"{name}: panoramic IWE per trajectory{note}")
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
    out = [meta.get("title", "# CMax-SLAM benchmark (simulated suite)"), ""]
    if meta.get("notice"):
        out += [meta["notice"], ""]
    out.append("Sequences: " + "; ".join(
        f"{r['sequence']} = {r['sensor']} {r['scene']} {r['duration_s']:g} s, {r['events']} events "
        f"({r['event_rate_mev_s']:.2f} Mev/s)" for r in results))
    out.append(f"Settings: {meta.get('settings_line', '')}")
    out += ["", "## Tab. II: absolute [deg] / relative [deg/s] rotation RMSE", ""]
    out += _grid(results, ("front-end", "ba", "slam"), (("abs_rmse_deg", 3), ("rel_rmse_deg_per_s", 3)),
                 ("abs", "rel"), notes)
    if any(r.get("turn_swing_deg") is not None for res in results for r in res["rows"]):
        out += ["", "## Long recordings: worst 0.2 s stretch [deg], swing in a turn [deg], loops applied", ""]
        out += _grid(results, ("front-end", "ba", "slam"), (("worst_stretch_deg", 3), ("turn_swing_deg", 3),
                                                            ("loops_applied", 0)), ("worst 0.2 s", "swing", "loops"),
                     notes)
        out += ["", "worst 0.2 s: the largest RMS of the abs error (aligned at t0) over any 0.2 s window; swing: the "
                "largest max - min of the abs error's quarter-turn means within one complete turn of the pan "
                "(\"-\" without a complete turn); loops: loop corrections applied."]
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
            "| sequence | simulate s (0: cached) | tasks wall s (sum) | load avg start / end (1 min) | peak RSS MB (max) |",
            "|---|---|---|---|---|"]
    for res in results:
        out.append(f"| {res['sequence']} | {res.get('simulate_seconds', 0.0):.1f} | {res['wall_seconds']:.1f} | "
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
            "- CMax-omega is the front-end of CMax-SLAM run alone (the same packets), integrated from the identity.",
            f"- Paper, synthetic: CMax-SLAM abs {PAPER_TAB2['abs_rmse_deg'][0]}-{PAPER_TAB2['abs_rmse_deg'][1]} deg, "
            f"rel {PAPER_TAB2['rel_rmse_deg_per_s'][0]}-{PAPER_TAB2['rel_rmse_deg_per_s'][1]} deg/s (Tab. II); "
            f"back-end {PAPER_TAB6['linear'][0]}-{PAPER_TAB6['linear'][1]} us/event linear, "
            f"{PAPER_TAB6['cubic'][0]}-{PAPER_TAB6['cubic'][1]} cubic (Tab. VI, C++).",
            f"- Timings are only comparable on an idle machine: load averages above; {meta.get('threads_line', '')}"]
    return "\n".join(out) + "\n"


def rows_for_csv(results: list[dict]) -> list[dict]:
    return [{k: r.get(k) for k in ROW_FIELDS} for res in results for r in res["rows"]]


def settings_line(cfg, quick: bool) -> str:
    b = cfg.backend
    s = cfg.benchmark
    size = f"{b.pano_size[0]}x{b.pano_size[1]}" if b.pano_height else "derived from the focal length"
    return (f"back-end map {size}, BA map height {s.ba_pano_height or b.pano_height or 'derived'}, "
            f"BA degrees {','.join(map(str, s.degrees())) or 'none'}, frontend_cg_max_iters "
            f"{cfg.frontend.frontend_cg_max_iters}, backend_cg_max_iters {b.backend_cg_max_iters}, seed {s.seed}"
            + (" [quick]" if quick else ""))


# the names of the suites, the methods and the tasks' runner are the benchmark's public face (commands, tests)
__all__ = ["BASELINES", "run_method", "SUITE", "SequenceSpec", "FRONTENDS", "METHOD_KEYS", "LABELS", "BenchmarkConfig", "BenchmarkSettings",
           "QUICK_SEQUENCES", "quick_overrides", "resolve_sequences", "resolve_methods", "ensure_sequence",
           "run_sequence_methods", "score", "run_method", "suite_tasks", "group_results", "run_benchmark",
           "format_tables", "rows_for_csv", "json_ready", "write_plots", "slam_config", "ROW_FIELDS", "SUITES",
           "make_suite", "prepare_sequences", "plot_group", "failed_row"]

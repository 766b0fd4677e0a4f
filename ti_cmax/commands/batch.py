"""``ti-cmax batch SUITE.yaml --out DIR``: datasets x methods x parameter sets, one task each, resumable.

SUITE.yaml (paths relative to the file)::

    datasets:                      # name: path (ECD folder or events file), or name: {simulate: {...}}
      shapes: ../data/shapes_rotation
      city2s: {simulate: {sensor: DAVIS240C, scene: city, duration: 2.0, seed: 3}}
    suite: paper                   # optional: also every sequence of a named simulated suite
    methods: [cmax-slam, rtpt]     # keys of ``ti-cmax benchmark --methods`` (default: all)
    config: {pano_height: 512}     # parameters of every task (like --set; --set on the command line wins)
    parameters:                    # named parameter sets (default: one set, "default")
      default: {}
      knots10hz: {dt_knots: 0.1}

Writes DIR/tasks/<set>-<dataset>-<method>/ per task, then DIR/tables.md (the benchmark's tables per parameter set),
DIR/results.csv, DIR/results.json, DIR/config.yaml (the base config). The options ``--scheduler``, ``--jobs``,
``--address`` (shared with ``benchmark`` and ``sweep``) choose where tasks run.
"""
from __future__ import annotations

import argparse
import sys

HELP = "run datasets x methods x parameter sets from SUITE.yaml as resumable tasks (local pool or Dask)"

SUITE_KEYS = ("datasets", "suite", "methods", "config", "parameters")


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    """--scheduler / --jobs / --address (benchmark, sweep, batch)."""
    parser.add_argument("--scheduler", choices=("local", "dask"), default="local",
                        help="local: this machine, --jobs processes (default); dask: a dask.distributed scheduler")
    parser.add_argument("--jobs", type=int, default=1, metavar="N",
                        help="local scheduler: tasks in parallel, one spawned process each (default 1: in this "
                             "process); --threads is then per process (default: CPU count / N)")
    parser.add_argument("--address", default=None, metavar="tcp://HOST:PORT", help="Dask scheduler address")


def executor_from_args(args):
    from ti_cmax.pipelines.evaluation.tasks import make_executor

    return make_executor(args.scheduler, args.jobs, args.threads, args.address)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("suite", metavar="SUITE.yaml", help="datasets, methods, parameter sets (see the module doc)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (task results in DIR/tasks)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    add_executor_arguments(parser)


def load_suite(path, cli_overrides: dict):
    """(datasets [(name, path or SequenceSpec, labels)], methods, {set name: BenchmarkConfig}) from SUITE.yaml."""
    from pathlib import Path

    import yaml

    from ..config import update_config
    from ..errors import InputError
    from ti_cmax.pipelines.evaluation import benchmark as B
    from ti_cmax.pipelines.evaluation.tasks import dataset_fingerprint

    src = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except FileNotFoundError:
        raise InputError("suite file not found", source=src) from None
    except yaml.YAMLError as exc:
        line = getattr(getattr(exc, "problem_mark", None), "line", None)
        raise InputError("not valid YAML", source=src, line=None if line is None else line + 1) from None
    if not isinstance(doc, dict):
        raise InputError("expected a mapping with datasets, methods, config, parameters", source=src)
    unknown = [k for k in doc if k not in SUITE_KEYS]
    if unknown:
        raise InputError(f"unknown key {unknown[0]!r} (expected some of {', '.join(SUITE_KEYS)})", source=src)
    base_dir = Path(path).resolve().parent
    datasets = []
    entries = doc.get("datasets") or {}
    if not isinstance(entries, dict):
        raise InputError("datasets: expected a mapping of name: path or name: {simulate: {...}}", source=src)
    for name, entry in entries.items():
        name = str(name)
        if not name or "/" in name or "\\" in name or name.startswith("."):  # names become file names
            raise InputError(f"datasets: the name {name!r} must not be empty, hold '/' or '\\' or start with '.' "
                             "(it names output files)", source=src)
        if isinstance(entry, str):
            p = Path(entry) if Path(entry).is_absolute() else base_dir / entry
            if not p.exists():
                raise InputError(f"datasets.{name}: {entry} not found", source=src)
            try:  # readable: an unreadable file (permissions, I/O error) gave a traceback, before any task ran
                dataset_fingerprint(p)
            except InputError as exc:
                raise InputError(f"datasets.{name}: {exc}", source=src) from None
            datasets.append((name, str(p), {"sensor": "", "scene": p.name}))
        elif isinstance(entry, dict) and set(entry) == {"simulate"} and isinstance(entry["simulate"], dict):
            spec = _spec(name, entry["simulate"], src)
            datasets.append((name, spec, {"sensor": spec.sensor, "scene": spec.scene}))
        else:
            raise InputError(f"datasets.{name}: expected a path or {{simulate: {{sensor, scene, duration, ...}}}}",
                             source=src)
    if doc.get("suite"):
        for spec in B.resolve_sequences(None, suite=str(doc["suite"])):
            datasets.append((spec.name, spec, {"sensor": spec.sensor, "scene": spec.scene}))
    if not datasets:
        raise InputError("no datasets (datasets: or suite:)", source=src)
    if len({d[0] for d in datasets}) != len(datasets):
        raise InputError("dataset names must be unique", source=src)
    methods = doc.get("methods") or []
    if isinstance(methods, str):
        methods = [m.strip() for m in methods.split(",") if m.strip()]
    if not isinstance(methods, list):
        raise InputError("methods: expected a list of method names or a comma-separated string", source=src)
    try:
        methods = B.resolve_methods([str(m) for m in methods])
    except InputError as exc:
        raise InputError(f"methods: {str(exc).split(': ', 1)[-1]}", source=src) from None
    base = _overrides(doc.get("config"), "config", src)
    sets = doc.get("parameters") or {"default": {}}
    if not isinstance(sets, dict):
        raise InputError("parameters: expected a mapping of set name: {parameter: value}", source=src)
    configs = {}
    base_cfg = update_config(B.BenchmarkConfig(), base, source=f"{src}: config")
    for pname, values in sets.items():
        values = _overrides(values, f"parameters.{pname}", src)
        configs[str(pname)] = update_config(base_cfg, {**values, **cli_overrides}, source=f"{src}: parameters.{pname}")
    return datasets, methods, configs, update_config(base_cfg, cli_overrides, source="--set")


def _overrides(values, where: str, src: str) -> dict:
    from ..config import _flatten
    from ..errors import InputError

    if values is None:
        return {}
    if not isinstance(values, dict):
        raise InputError(f"{where}: expected a mapping of parameter: value", source=src)
    return _flatten(values)


def _spec(name: str, values: dict, src: str):
    from dataclasses import fields

    from ..errors import InputError
    from ti_cmax.pipelines.evaluation.benchmark import SequenceSpec
    from ..simulate import SimulatorConfig

    known = {f.name for f in fields(SimulatorConfig)}
    bad = [k for k in values if k not in known]
    if bad:
        raise InputError(f"datasets.{name}.simulate: unknown field {bad[0]!r}", source=src)
    d = SimulatorConfig()
    core = {"sensor": d.sensor, "scene": d.scene, "duration": d.duration, "seed": d.seed, "trajectory": d.trajectory}
    core.update({k: values[k] for k in core if k in values})
    options = tuple(sorted((k, v) for k, v in values.items() if k not in core))
    try:
        spec = SequenceSpec(name, str(core["sensor"]), str(core["scene"]), float(core["duration"]),
                            int(core["seed"]), str(core["trajectory"]), options)
        SimulatorConfig(**{k: v for k, v in core.items() if k != "seed"}, seed=spec.seed, **dict(options))
    except (TypeError, ValueError, InputError) as exc:
        raise InputError(f"datasets.{name}.simulate: {exc}", source=src) from None
    return spec


def write_tables(out, groups: list[dict], meta: dict, extra_doc: dict) -> str:
    """tables.md (one set of tables per parameter set), results.csv, results.json; returns the tables' text."""
    import csv
    import json

    from ..outputs import atomic_path
    from ti_cmax.pipelines.evaluation import benchmark as B

    sets = list(dict.fromkeys(g.get("parameters", "") for g in groups))
    parts = []
    for pname in sets:
        sel = [g for g in groups if g.get("parameters", "") == pname]
        title = meta.get("title", "# CMax-SLAM benchmark (simulated suite)")
        if pname:
            title += f": parameter set {pname}"
        parts.append(B.format_tables(sel, {**meta, "title": title}))
    table = "\n".join(parts)
    with atomic_path(out / "tables.md") as p:
        p.write_text(table)
    fields = (["parameters"] if any(sets) else []) + list(B.ROW_FIELDS)
    with atomic_path(out / "results.csv") as p, open(p, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(B.json_ready([r for g in groups for r in g["rows"]]))
    with atomic_path(out / "results.json") as p:
        p.write_text(json.dumps(B.json_ready({**extra_doc, "results": groups}), indent=2) + "\n")
    return table


def tasks_line(groups: list[dict], wall: float) -> str:
    n = {k: sum(g["tasks"].get(k, 0) for g in groups) for k in ("done", "failed", "skipped")}
    errors = sum(r.get("status") == "error" for g in groups for r in g["rows"])  # a method raised on a dataset
    return (f"tasks: {n['done'] + n['failed']} ({n['skipped']} skipped as done before, {n['failed']} failed) "
            f"in {wall:.1f} s" + (f"; {errors} method run(s) ended in an error (their notes in tables.md)"
                                  if errors else ""))


def run(args) -> int:
    import time
    from pathlib import Path

    from ..config import parse_overrides

    tic = time.perf_counter()
    datasets, methods, configs, base_cfg = load_suite(args.suite, parse_overrides(args.overrides))
    from ..outputs import OutputLock

    out = Path(args.out)
    executor = executor_from_args(args)
    # finished tasks stay in DIR for a rerun to reuse; the lock keeps a second run from interleaving with this one
    try:
        with OutputLock(out):
            return _run(args, tic, datasets, methods, configs, base_cfg, out, executor)
    finally:
        executor.close()


def _run(args, tic, datasets, methods, configs, base_cfg, out, executor) -> int:
    import json
    import os
    import time

    from ..config import save_config
    from ..kernels import runtime
    from ..outputs import atomic_path
    from ti_cmax.pipelines.evaluation import benchmark as B
    from ti_cmax.pipelines.evaluation.tasks import run_tasks

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    # finished tasks and simulated sequences stay when a run is interrupted or fails: a rerun goes on from there
    specs = [d[1] for d in datasets if not isinstance(d[1], str)]
    extra = {}
    if specs:
        prepared = B.prepare_sequences(specs, B.BenchmarkSettings(), out / "sequences", executor, quiet=args.quiet)
        for spec in specs:
            if not isinstance(prepared[spec.name], tuple):
                from ..errors import InputError

                raise InputError(f"simulating {spec.name} failed: {prepared[spec.name]}")
            folder, info, sim_s = prepared[spec.name]
            extra[spec.name] = {"simulate_seconds": sim_s, "duration_s": float(info["duration"])}
        datasets = [(n, str(prepared[p.name][0]) if not isinstance(p, str) else p, lab) for n, p, lab in datasets]
    tasks = B.suite_tasks(datasets, ["gt", *methods], configs)
    log(f"{len(tasks)} tasks ({len(datasets)} datasets x {len(configs)} parameter sets x {len(methods)} methods "
        f"+ ground truth) on {executor.describe()}")
    summary = run_tasks(tasks, out, executor, quiet=args.quiet, log=log)
    groups = B.group_results(tasks, summary.results, extra)
    for g in groups:
        g["tasks"]["skipped"] = sum(1 for t in g["task_ids"] if t in summary.skipped)
        if not args.no_plots:
            suffix = f"-{g['parameters']}" if g.get("parameters") else ""
            g["plots"] = B.plot_group(out / "plots", g, out, suffix)
    wall = time.perf_counter() - tic
    meta = {"map_height": base_cfg.benchmark.map_height, "title": "# ti-cmax batch",
            "settings_line": f"{args.suite}; parameter sets: "
                             + "; ".join(f"{k} = {json.dumps(v)}" for k, v in _set_overrides(args.suite).items()),
            "threads_line": f"{executor.describe()}, cpu count {os.cpu_count()}, total wall {wall:.1f} s."}
    table = write_tables(out, groups, meta, {"suite": str(args.suite), "methods": methods,
                                             "parameter_sets": list(configs), "total_wall_seconds": wall,
                                             "executor": executor.describe(), "threads": runtime.num_threads()})
    with atomic_path(out / "config.yaml") as p:
        save_config(base_cfg, p)
    print(table)
    print(f"{tasks_line(groups, wall)}; wrote {out}/tables.md, results.csv, results.json, config.yaml, tasks/")
    return exit_code(groups)


def exit_code(groups: list[dict]) -> int:
    """1 when a task failed (its row says why), else 0."""
    return 1 if any(g["tasks"].get("failed") for g in groups) else 0


def _set_overrides(path) -> dict:
    import yaml
    from pathlib import Path

    doc = yaml.safe_load(Path(path).read_text()) or {}
    return doc.get("parameters") or {"default": {}}

"""``ti-cmax benchmark --out DIR``: the paper's Tab. II (abs/rel RMSE), Tab. IV (EA, GM) and Tab. VI (us/event) on a
suite of simulated sequences (``--suite paper``: playroom-like DVS128 2.5 s; bicycle, city, street, town, bay
DAVIS240C 5 s; ``--suite sensors``: DVS128, DAVIS240C, DAVIS346, DVXplorer and HD sequences of 1.5-2 s with the
sensor-derived defaults, CMax-omega and CMax-SLAM only unless ``--methods`` says otherwise; ``--suite heldout``: four
3 s DAVIS240C sequences of seeds 201-204 declared for the SMT baselines, EKF-SMT, PF-SMT and CMax-omega by default;
``--suite long``: three 60 s DAVIS240C pans of 3.7 turns with wobble and sensor defects, CMax-SLAM by default, with
the worst 0.2 s stretch, the swing of the error within a turn and the loops applied; the fuller table with
``--realtime`` figures, wall time and memory is ``python -m ti_cmax.pipelines.evaluation.bench_long``).

Each method on each sequence is a task (see ``ti-cmax batch``): ``--jobs N`` runs N at once in spawned processes,
``--scheduler dask --address tcp://HOST:PORT`` on a Dask cluster; a rerun skips finished tasks (DIR/tasks) and
simulated sequences (DIR/sequences). Writes DIR/tables.md, DIR/results.csv (one row per sequence x method),
DIR/results.json, DIR/plots/ (violins of the errors, trajectories per axis, maps side by side, per sequence) and
DIR/config.yaml. ``--quick``: 2 sequences of 1.5 s, linear BA only, 512x256 back-end maps and capped CG iterations
(smoke runs; figures not comparable with the full suite). ``--realtime``: the real-time table instead
(``pipelines/evaluation/bench_realtime.py``: ``slam --realtime --parallel`` against the offline run, 1-12 M events/s).
"""
from __future__ import annotations

import argparse
import sys

from .batch import add_executor_arguments, executor_from_args, exit_code, tasks_line, write_tables

QUICK_NOTICE = ("**Smoke test.** `--quick` checks that every method runs end to end: 1.5 s sequences, a linear "
                "spline only, 256-row maps and capped optimiser iterations. Its figures are not the methods' "
                "accuracy: the back-end has too few windows to settle and the maps are coarse; run the full suite "
                "(without `--quick`) to compare methods.")



def smoke_test_meta() -> dict:
    """Title and notice of the tables of ``--quick``: they must not read as the methods' accuracy."""
    return {"title": "# CMax-SLAM benchmark: smoke test (--quick), not an accuracy comparison", "notice": QUICK_NOTICE}


HELP = "paper-style benchmark tables (Tab. II, IV, VI) on simulated sequences: tables.md, results.csv, plots"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ti_cmax.pipelines.evaluation.suites import METHOD_KEYS, SUITES

    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (sequences are cached in DIR/sequences)")
    parser.add_argument("--quick", action="store_true", help="2 short sequences, linear BA only, smaller maps")
    parser.add_argument("--suite", default="paper", choices=tuple(SUITES), help="suite of simulated sequences")
    parser.add_argument("--sequences", default="", metavar="A,B",
                        help="comma-separated subset of the suite's sequences (paper: playroom,bicycle,city,street,"
                             "town,bay; default: all; --quick: playroom,city)")
    parser.add_argument("--methods", default="", metavar="A,B",
                        help=f"comma-separated subset of {','.join(METHOD_KEYS)} (default: all)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--realtime", action="store_true",
                        help="real-time table instead (pipelines/evaluation/bench_realtime.py): slam --realtime --parallel vs "
                             "offline at 1, 2, 5 (DAVIS240C) and 12 (VGA) M events/s; --sequences picks cases")
    parser.add_argument("--rounds", type=int, default=1, metavar="N",
                        help="with --realtime: run the cases N times, case after case, and count per case the rounds "
                             "meeting the target (a machine's speed varies from run to run: one run decides nothing)")
    add_executor_arguments(parser)


def _split(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def run(args) -> int:
    """The benchmark with a lock on --out: finished tasks and sequences stay in DIR for a rerun to reuse, and a
    second run into DIR refuses instead of interleaving with this one."""
    from pathlib import Path

    from ..outputs import OutputLock

    with OutputLock(Path(args.out)):
        return _run(args)


def _run(args) -> int:
    import os
    import time
    from pathlib import Path

    from ..config import load_config, parse_overrides, save_config
    from ..kernels import runtime
    from ..outputs import atomic_path
    from ti_cmax.pipelines.evaluation import benchmark as B

    if args.realtime:
        from ti_cmax.pipelines.evaluation import bench_realtime

        log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
        print(bench_realtime.run(Path(args.out), _split(args.sequences), threads=args.threads,
                                 overrides=args.overrides, log=log, rounds=args.rounds))
        return 0
    overrides = {**(B.quick_overrides() if args.quick else {}), **parse_overrides(args.overrides)}
    cfg = load_config(B.BenchmarkConfig, args.config, overrides)
    sequences = B.resolve_sequences(_split(args.sequences), quick=args.quick, suite=args.suite)
    methods = B.resolve_methods(_split(args.methods), args.suite)
    executor = executor_from_args(args)
    out = Path(args.out)
    tic = time.perf_counter()

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    log(f"{len(sequences)} sequences x {len(methods)} methods on {executor.describe()}")
    # sequences and finished tasks outlive an interrupted or failed run: a rerun goes on from there
    try:
        results = B.run_benchmark(cfg, sequences, methods, out, executor=executor, log=log,
                                  plots=not args.no_plots, quiet=args.quiet,
                                  plot_note="smoke test (--quick), not an accuracy comparison" if args.quick else "")
    finally:
        executor.close()
    total = time.perf_counter() - tic
    meta = {"map_height": cfg.benchmark.map_height, "settings_line": B.settings_line(cfg, args.quick),
            "threads_line": f"{executor.describe()}, cpu count {os.cpu_count()}, total wall {total:.1f} s."}
    if args.quick:
        meta.update(smoke_test_meta())
    table = write_tables(out, results, meta, {
        "quick": bool(args.quick), "suite": args.suite, "sequences": [s.name for s in sequences], "methods": methods,
        "total_wall_seconds": total, "executor": executor.describe(), "threads": runtime.num_threads()})
    with atomic_path(out / "config.yaml") as p:
        save_config(cfg, p)
    print(table)
    print(f"{tasks_line(results, total)}; wrote {args.out}/tables.md, results.csv, results.json, config.yaml"
          + ("" if args.no_plots else ", plots/"))
    return exit_code(results)

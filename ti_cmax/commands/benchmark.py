"""``ti-cmax benchmark --out DIR``: the paper's Tab. II (abs/rel RMSE), Tab. IV (EA, GM) and Tab. VI (us/event) on a
suite of simulated sequences (playroom-like DVS128 2.5 s; bicycle, city, street, town, bay DAVIS240C 5 s).

Writes DIR/tables.md, DIR/results.csv (one row per sequence x method), DIR/results.json, DIR/plots/ (violins of the
errors, trajectories per axis, maps side by side, per sequence) and DIR/config.yaml. Simulated sequences are cached
in DIR/sequences (a re-run skips simulation). ``--quick``: 2 sequences of 1.5 s, linear BA only, 512x256 back-end
maps and capped CG iterations (smoke runs; figures not comparable with the full suite).
"""
from __future__ import annotations

import argparse
import sys

HELP = "paper-style benchmark tables (Tab. II, IV, VI) on simulated sequences: tables.md, results.csv, plots"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (sequences are cached in DIR/sequences)")
    parser.add_argument("--quick", action="store_true", help="2 short sequences, linear BA only, smaller maps")
    parser.add_argument("--sequences", default="", metavar="A,B",
                        help="comma-separated subset of playroom,bicycle,city,street,town,bay (default: all; "
                             "--quick: playroom,city)")
    parser.add_argument("--methods", default="", metavar="A,B",
                        help="comma-separated subset of smt-ekf,smt-pf,rtpt,cmax-gae,cmax-omega,imu,cmax-slam "
                             "(default: all)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def _split(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def run(args) -> int:
    import csv
    import json
    import os
    import time

    from ..config import load_config, parse_overrides, save_config
    from ..kernels import runtime
    from ..outputs import OutputDir, atomic_path
    from ..pipelines import benchmark as B

    overrides = {**(B.quick_overrides() if args.quick else {}), **parse_overrides(args.overrides)}
    cfg = load_config(B.BenchmarkConfig, args.config, overrides)
    sequences = B.resolve_sequences(_split(args.sequences), quick=args.quick)
    methods = B.resolve_methods(_split(args.methods))
    tic = time.perf_counter()

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    from pathlib import Path

    from .. import progress

    progress.set_quiet(True)  # one log line per method instead of a bar per run
    # the sequence cache outlives a failed run (OutputDir only removes what it created inside the folder)
    (Path(args.out) / "sequences").mkdir(parents=True, exist_ok=True)
    with OutputDir(args.out) as out:
        results = B.run_benchmark(cfg, sequences, methods, out, log=log, plots=not args.no_plots)
        total = time.perf_counter() - tic
        meta = {"map_height": cfg.benchmark.map_height, "settings_line": B.settings_line(cfg, args.quick),
                "threads_line": f"threads {runtime.num_threads()}, cpu count {os.cpu_count()}, "
                                f"total wall {total:.1f} s."}
        table = B.format_tables(results, meta)
        with atomic_path(out / "tables.md") as p:
            p.write_text(table)
        with atomic_path(out / "results.csv") as p, open(p, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(B.ROW_FIELDS))
            writer.writeheader()
            writer.writerows(B.json_ready(B.rows_for_csv(results)))
        doc = {"quick": bool(args.quick), "sequences": [s.name for s in sequences], "methods": methods,
               "total_wall_seconds": total, "threads": runtime.num_threads(), "results": results}
        with atomic_path(out / "results.json") as p:
            p.write_text(json.dumps(B.json_ready(doc), indent=2) + "\n")
        save_config(cfg, out / "config.yaml")
    print(table)
    print(f"wrote {args.out}/tables.md, results.csv, results.json, config.yaml"
          + ("" if args.no_plots else ", plots/") + f" in {total:.1f} s")
    return 0

"""``ti-cmax sweep``: sensitivity of CMax-SLAM to control-pose frequency, window size, map resolution and event
sampling rate (paper Sec. IV-H, Fig. 19) on a simulated sequence or a dataset with ground truth.

Each run is a task (see ``ti-cmax batch``): ``--jobs N`` / ``--scheduler dask`` run them in parallel, a rerun
skips finished ones (DIR/tasks); the simulated sequence is cached in DIR/sequences."""
from __future__ import annotations

import argparse
import sys

from . import positive_float
from .batch import add_executor_arguments, executor_from_args

HELP = "sensitivity sweep (Fig. 19): abs error and runtime vs dt_knots, window, map size, event sampling"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder: sweep.md, sweep.csv, sweep.png")
    parser.add_argument("--dataset", default=None, help="dataset with groundtruth.txt (default: simulate one)")
    from ..simulate.config import SCENES

    parser.add_argument("--scene", default="bicycle", choices=SCENES,
                        help="simulated scene (default: bicycle, as in the paper)")
    parser.add_argument("--duration", type=positive_float, default=5.0, help="simulated duration (s)")
    parser.add_argument("--parameters", default="control_pose_frequency,window_size,map_height,event_sample_rate",
                        help="comma-separated subset")
    parser.add_argument("--quick", action="store_true", help="two values per parameter")
    add_executor_arguments(parser)


def run(args) -> int:
    from pathlib import Path

    from ..config import SlamConfig, load_config
    from ..errors import InputError
    from ti_cmax.pipelines.evaluation.sensitivity import SWEEPS

    cfg = load_config(SlamConfig, args.config, args.overrides)
    params = [p.strip() for p in args.parameters.split(",") if p.strip()]
    unknown = [p for p in params if p not in SWEEPS]
    if not params:
        raise InputError(f"--parameters: expected some of {', '.join(SWEEPS)}, got {args.parameters!r}")
    if unknown:
        raise InputError(f"--parameters: unknown {', '.join(unknown)} (expected some of {', '.join(SWEEPS)})")
    out = Path(args.out)
    if args.dataset:
        from ..io import open_dataset_from_config

        if open_dataset_from_config(args.dataset, cfg.dataset).groundtruth is None:
            raise InputError("the sweep needs ground truth (groundtruth.txt)", source=str(args.dataset))
    from ..outputs import OutputLock

    executor = executor_from_args(args)
    # finished runs stay in DIR for a rerun to reuse; the lock keeps a second sweep from interleaving with this one
    try:
        with OutputLock(out):
            return _run(args, cfg, params, out, executor)
    finally:
        executor.close()


def _run(args, cfg, params, out, executor) -> int:
    import csv
    import json
    from pathlib import Path

    from ..config import save_config
    from ..errors import InputError
    from ..outputs import atomic_path
    from ti_cmax.pipelines.evaluation.benchmark import json_ready
    from ti_cmax.pipelines.evaluation.sensitivity import plot_sweep, rows_to_dicts, rows_to_markdown, run_sweep

    if args.dataset:
        dataset, name = args.dataset, Path(args.dataset).name
    else:
        from ti_cmax.pipelines.evaluation.benchmark import BenchmarkSettings, SequenceSpec, prepare_sequences

        spec = SequenceSpec(f"sweep-{args.scene}", "DAVIS240C", args.scene, args.duration, 0,
                            options=(("max_angular_velocity", 3.0),))
        prepared = prepare_sequences([spec], BenchmarkSettings(), out / "sequences", executor,
                                     quiet=args.quiet)[spec.name]
        if not isinstance(prepared, tuple):
            raise InputError(f"simulating the sequence failed: {prepared}")
        dataset, name = prepared[0], spec.name

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    rows = run_sweep(dataset, name, cfg, params, quick=args.quick, out_dir=out, executor=executor,
                     quiet=args.quiet, log=log)
    table = rows_to_markdown(rows)
    with atomic_path(out / "sweep.md") as p:
        p.write_text(table + "\n")
    with atomic_path(out / "sweep.csv") as p, open(p, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows_to_dicts(rows)[0]))
        writer.writeheader()
        writer.writerows(rows_to_dicts(rows))
    with atomic_path(out / "sweep.json") as p:
        p.write_text(json.dumps(json_ready(rows_to_dicts(rows)), indent=2))
    with atomic_path(out / "sweep.png") as p:
        plot_sweep(p, rows)
    with atomic_path(out / "config.yaml") as p:
        save_config(cfg, p)
    print(table)
    return 1 if any(r.status != "ok" for r in rows) else 0

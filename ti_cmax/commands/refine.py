"""``ti-cmax refine``: offline CMax bundle adjustment of any trajectory (Sec. IV-C2 / IV-D3)."""
from __future__ import annotations

import argparse

from . import add_map_arguments

HELP = "refine a given trajectory by the sliding-window CMax BA: trajectory.txt, map.png, map.npy, run.png, report.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (ECD layout) or events file")
    parser.add_argument("--trajectory", required=True, metavar="TRAJ.txt", help="initial trajectory (TUM)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--spline", choices=("linear", "cubic"), default=None, help="trajectory model")
    parser.add_argument("--loop-closure", action="store_true",
                        help="close loops on revisits (the default; the same as --set loop_closure=true; "
                             "--set loop_closure=false turns it off; report.json lists the candidates)")
    add_map_arguments(parser)


def run(args) -> int:
    from ..config import SlamConfig, check_workload, load_config
    from ..io import open_dataset_from_config, read_tum
    from ..outputs import OutputDir
    from ..pipelines.slam import refine
    from ..status import status_text
    from .slam import print_derived, spline_override, write_result

    cfg = load_config(SlamConfig, args.config, list(args.overrides) + spline_override(args)
                      + (["loop_closure=true"] if args.loop_closure else []))
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    camera = dataset.camera
    initial = read_tum(args.trajectory)
    t0, t1 = dataset.time_range()
    check_workload(cfg, max(t0, initial.t_start), min(t1, initial.t_end))
    with OutputDir(args.out) as out:  # locked from here: a second run into --out refuses
        result = refine(dataset.iter_events(cfg.dataset.chunk_size, t_start=initial.t_start, t_end=initial.t_end),
                        camera, initial, cfg, progress_total=min(t1, initial.t_end) - max(t0, initial.t_start))
        report = write_result(out, result, cfg, camera, events_range=(t0, t1), full_sphere=args.full_sphere,
                              groundtruth=dataset.groundtruth, title=f"refined: {args.trajectory}")
    print_derived(result.report)
    print(f"refined {len(result.trajectory)} poses over {result.trajectory.t_end - result.trajectory.t_start:.3f} s, "
          f"back-end {result.report['us_per_event']['backend']:.3f} us/event -> {args.out}{status_text(report)}")
    return 0

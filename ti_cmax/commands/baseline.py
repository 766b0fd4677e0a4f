"""``ti-cmax baseline NAME DATASET --out DIR``: run a baseline tracker (RTPT, CMax-GAE, IMU dead reckoning, ...).

Writes trajectory.txt (TUM), the method's map (map.png, map.npy), run.png, report.json (status "ok" or "lost" with
lost_at) and config.yaml; with ``--refine`` also the offline BA of that trajectory in DIR/refined/ (same files).
"""
from __future__ import annotations

import argparse

from . import add_map_arguments

HELP = ("run a baseline method (smt-ekf, smt-pf, rtpt, cmax-gae, imu): trajectory.txt, map.png, run.png, report.json "
        "[--refine]")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", metavar="NAME", help="baseline method (rtpt, cmax-gae, imu, ...)")
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (ECD layout) or events file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--refine", action="store_true",
                        help="also refine the baseline's trajectory by the offline BA into DIR/refined/")
    add_map_arguments(parser)


def run(args) -> int:
    from ..config import check_workload, load_config
    from ..errors import InputError
    from ..io import open_dataset_from_config
    from ..outputs import OutputDir
    from ..pipelines.baselines import BASELINES, BaselineConfig, run_baseline
    from ..status import status_text
    from .slam import write_result

    if args.name not in BASELINES:  # fail before reading any data
        raise InputError(f"unknown baseline {args.name!r} (expected one of {', '.join(BASELINES)})")
    cfg = load_config(BaselineConfig, args.config, args.overrides)
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    camera = dataset.camera
    check_workload(cfg, *dataset.time_range())
    imu = dataset.imu  # the imu baseline needs it; others may use it (e.g. bootstrapping)
    extra = {}
    if args.name.startswith("smt"):  # SMT bootstraps from IMU, or ground truth where no IMU exists (playroom)
        from ..pipelines.baselines.smt import smt_contrast

        extra = {"groundtruth": dataset.groundtruth, "contrast_threshold": smt_contrast(cfg.smt, args.dataset)}
    with OutputDir(args.out) as out:  # locked from here: a second run into --out refuses
        result = run_baseline(args.name, dataset.stream(cfg.dataset.chunk_size), camera, cfg, imu=imu, **extra)
        refined = None
        if args.refine:
            from ..pipelines.slam import refine

            t0, t1 = result.trajectory.t_start, result.trajectory.t_end
            refined = refine(dataset.iter_events(cfg.dataset.chunk_size), camera, result.trajectory,
                             cfg.slam_config(), progress_total=t1 - t0)
        span = dataset.time_range()
        rep = write_result(out, result, cfg, camera, events_range=span, full_sphere=args.full_sphere,
                           groundtruth=dataset.groundtruth, title=f"baseline {args.name}")
        if refined is not None:
            (out / "refined").mkdir()
            write_result(out / "refined", refined, cfg.slam_config(), camera, events_range=span,
                         full_sphere=args.full_sphere, groundtruth=dataset.groundtruth,
                         title=f"baseline {args.name}, refined")
    lost = f", lost at {rep['lost_at']:.3f} s" if rep["status"] == "lost" else ""
    print(f"{args.name}: {rep['status']}{lost}, {rep['events_processed']} events, {len(result.trajectory)} poses, "
          f"{rep['us_per_event']['frontend']:.3f} us/event -> {args.out}{status_text(rep)}")
    return 0

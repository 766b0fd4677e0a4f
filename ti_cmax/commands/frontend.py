"""``ti-cmax frontend``: CMax-omega angular velocity (Sec. II-B, III-C1) and its integrated trajectory."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "estimate angular velocity by contrast maximisation; write angular_velocity.txt, trajectory.txt, run.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (ECD layout) or events file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")


def run(args) -> int:
    import time

    from ..config import SlamConfig, check_workload, config_to_dict, load_config, save_config
    from ..io import open_dataset_from_config, write_angular_velocity, write_tum
    from ..outputs import OutputDir, write_report
    from ..pipelines.frontend import estimate_angular_velocity
    from ..pipelines.sensor_defaults import derived_summary, describe, resolve_config
    from .slam import write_run_figure
    from ..status import apply_status, status_text

    tic = time.perf_counter()
    cfg = load_config(SlamConfig, args.config, args.overrides)
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    camera = dataset.camera
    t0, t1 = dataset.time_range()
    check_workload(cfg, t0, t1)
    derived = derived_summary(cfg, camera)
    cfg = resolve_config(cfg, camera)
    with OutputDir(args.out) as out:  # locked from here: a second run into --out refuses
        result = estimate_angular_velocity(dataset.iter_events(), camera, cfg.frontend, progress_total=t1 - t0)
        write_angular_velocity(out / "angular_velocity.txt", result.t, result.omega)
        trajectory = result.trajectory()
        write_tum(out / "trajectory.txt", trajectory)
        write_run_figure(out / "run.png", trajectory, result, groundtruth=dataset.groundtruth,
                         title=f"CMax-omega front-end: {Path(args.dataset).name}")
        save_config(cfg, out / "config.yaml")
        timing = result.timing
        report = {
            "status": result.status,
            "method": "cmax-omega",
            "events_processed": timing["events_processed"],
            "wall_seconds": time.perf_counter() - tic,
            "frontend_wall_seconds": timing["wall_seconds"],
            "compile_seconds": timing["compile_seconds"],
            "us_per_event": {"frontend": timing["us_per_event"], "backend": None},  # per input event
            "packet_events": timing["packet_events"],  # counted once per overlapping packet
            "us_per_packet_event": timing["us_per_packet_event"],
            "summary": result.summary(),
            "hot_pixels": result.hot_pixels,
            "parameters": config_to_dict(cfg.frontend),
            "derived_parameters": {k: v for k, v in derived.items() if hasattr(cfg.frontend, k)},
            "camera": camera.to_dict(),
        }
        apply_status(report)
        write_report(out, report)
    if derived:
        print(f"derived from the sensor: {describe({k: v for k, v in derived.items() if hasattr(cfg.frontend, k)})}")
    print(f"{len(result)} angular velocities ({int(result.sparse.sum())} still, {int(result.flat.sum())} flat), "
          f"{timing['events_processed']} input events, {timing['us_per_event']:.3f} us per input event "
          f"({timing['packet_events']} packet events, {timing['us_per_packet_event']:.3f} us each) -> {args.out}"
          f"{status_text(report)}")
    return 0

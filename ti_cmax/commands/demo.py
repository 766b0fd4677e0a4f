"""``ti-cmax demo``: simulate a built-in sequence, run CMax-SLAM, evaluate against ground truth, plot."""
from __future__ import annotations

import argparse

HELP = "generate a built-in sequence, run CMax-SLAM on it, evaluate and plot (a few minutes at most)"

DEMO_SEQUENCE = dict(scene="bay", sensor="DAVIS240C", duration=3.0, trajectory="random",
                     max_angular_velocity=3.0, seed=7)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo_out", metavar="DIR", help="output folder (default: demo_out)")
    parser.add_argument("--duration", type=float, default=DEMO_SEQUENCE["duration"], help="sequence length (s)")
    parser.add_argument("--spline", choices=("linear", "cubic"), default=None, help="trajectory model")
    parser.add_argument("--text", action="store_true",
                        help="also write the sequence's events as ECD text (events.txt; default: events.h5 only)")


def run(args) -> int:
    import time
    from pathlib import Path

    from ..config import SlamConfig, load_config
    from ..io import open_dataset
    from ..metrics import evaluate_rotations
    from ..outputs import OutputDir
    from ..pipelines.panorama import render_panorama
    from ..pipelines.sensor_defaults import pano_size
    from ..pipelines.slam import default_backend_process, run_slam
    from ..plots import plot_error_distributions, plot_errors_over_time, plot_maps, plot_trajectories
    from ..simulate import SimulatorConfig, simulate_to_folder
    from .slam import spline_override, write_result

    tic = time.perf_counter()
    cfg = load_config(SlamConfig, args.config, list(args.overrides) + spline_override(args))
    with OutputDir(args.out) as out:
        seq_dir = out / "sequence"
        shown = Path(args.out)  # where the outputs end up (``out`` is where they are built)
        print(f"[1/3] simulating {args.duration:.1f} s of a {DEMO_SEQUENCE['sensor']} sequence -> {shown / 'sequence'}")
        info = simulate_to_folder(SimulatorConfig(**{**DEMO_SEQUENCE, "duration": args.duration}), seq_dir,
                                  show_progress=not args.quiet, events_format="both" if args.text else "h5")
        dataset = open_dataset(seq_dir)
        t0, t1 = dataset.time_range()
        print(f"      {info.get('num_events', dataset.num_events())} events in {t1 - t0:.2f} s")
        print("[2/3] running CMax-SLAM")
        result = run_slam(dataset.iter_events(cfg.dataset.chunk_size), dataset.camera, cfg, progress_total=t1 - t0,
                          backend_process=default_backend_process(dataset.camera))  # as `ti-cmax slam` runs by default
        slam_dir = out / "slam"
        slam_dir.mkdir(exist_ok=True)
        report = write_result(slam_dir, result, cfg, dataset.camera, events_range=(t0, t1),
                              groundtruth=dataset.groundtruth, title="demo: CMax-SLAM")

        print("[3/3] evaluating against ground truth")
        gt = dataset.groundtruth
        estimates = {"CMax-omega (front-end)": result.frontend.trajectory(), "CMax-SLAM": result.trajectory}
        errors = {name: evaluate_rotations(gt, est) for name, est in estimates.items()}
        aligned = {name: est.aligned_to(gt, errors[name].t0) for name, est in estimates.items()}
        plot_trajectories(out / "trajectories.png", aligned, gt, title="demo: estimated vs ground truth")
        plot_errors_over_time(out / "errors_over_time.png", errors, title="demo: rotation error over time")
        plot_error_distributions(out / "errors.png", {k: e.abs_errors_deg for k, e in errors.items()},
                                 {k: e.rel_errors_deg_per_s for k, e in errors.items()})
        width, height = pano_size(cfg.backend, dataset.camera)
        maps = {name: render_panorama(dataset.iter_events(), dataset.camera, traj, width, height,
                                      cfg.backend.event_batch_size).image
                for name, traj in (("front-end", aligned["CMax-omega (front-end)"]), ("CMax-SLAM", result.trajectory),
                                   ("ground truth", gt))}
        plot_maps(out / "maps.png", maps, gamma=cfg.output.gamma, ncols=1, panel_width=9)  # cropped, stretched
        us = result.report["us_per_event"]
        lines = [
            "ti_cmax demo summary",
            f"sequence      : {shown / 'sequence'} ({DEMO_SEQUENCE['sensor']}, scene {DEMO_SEQUENCE['scene']}, "
            f"{t1 - t0:.2f} s, {result.report['events_processed']} events)",
            f"spline        : {'cubic' if cfg.backend.spline_degree == 3 else 'linear'}, "
            f"map {width}x{height}",
        ]
        for name, e in errors.items():
            lines.append(f"{name:<24}: abs RMSE {e.abs_rmse_deg:.3f} deg, rel RMSE {e.rel_rmse_deg_per_s:.3f} deg/s")
        lines += [
            f"speed         : front-end {us['frontend']:.2f} us/event, back-end {us['backend']:.2f} us/event "
            f"(compile {result.report['compile_seconds']:.1f} s apart)",
            f"results       : {shown / 'slam'}/trajectory.txt, map.png, run.png; plots: {shown}/trajectories.png, "
            "errors_over_time.png, errors.png, maps.png",
            f"status        : {report['status']}" + "".join(f"; {r}" for r in report["reasons"]),
            f"total time    : {time.perf_counter() - tic:.1f} s",
        ]
        (out / "summary.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0

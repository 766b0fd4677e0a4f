"""``ti-cmax star-tracking``: front-end + offline BA on a star field (paper Sec. V, Tab. VIII, Fig. 20)."""
from __future__ import annotations

import argparse
import json
import sys


from . import add_map_arguments, positive_float

HELP = ("star tracking: front-end + offline BA; trajectory.txt, angular_velocity.txt, star_map.png, "
        "angular_velocity.png, report.json (400 ms relative-rotation RMSE/std when ground truth exists)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET",
                        help="star-form folder (events.txt with float coordinates + 3x3 calibration.txt) or any "
                             "dataset `ti-cmax info` reads (ECD layout, events file)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--spline", choices=("linear", "cubic"), default=None,
                        help="trajectory model of the BA (default: spline_degree of the config, linear)")
    parser.add_argument("--window", type=positive_float, default=0.4, metavar="S",
                        help="interval of the relative rotations evaluated (default 0.4 s, as Chin et al.)")
    parser.add_argument("--groundtruth", default=None, metavar="GT.txt",
                        help="ground truth (TUM); default: groundtruth.txt of the dataset when present")
    add_map_arguments(parser)


def run(args) -> int:
    import dataclasses

    import imageio.v3 as iio

    from ..config import check_workload
    from ..io import read_tum
    from ..outputs import OutputDir, json_ready
    from ..pipelines.panorama import map_image
    from ti_cmax.pipelines.workflows.star_tracking import open_star_or_dataset, run_star_tracking, star_tracking_config
    from ..plots import angular_velocity_from_trajectory, plot_angular_velocity, plot_trajectories
    from ..status import status_text
    from .slam import spline_override, write_result

    cfg = star_tracking_config(args.config, list(args.overrides) + spline_override(args))
    dataset = open_star_or_dataset(args.dataset, cfg.dataset)
    gt = read_tum(args.groundtruth) if args.groundtruth else dataset.groundtruth
    t0, t1 = dataset.time_range()
    check_workload(cfg, t0, t1)
    with OutputDir(args.out) as out:  # locked from here: a second run into --out refuses
        res = run_star_tracking(dataset, dataset.camera, cfg, groundtruth=gt, window=args.window,
                                progress_total=t1 - t0)
        report = dict(res.report)
        report["dataset"] = {"path": str(args.dataset), "format": getattr(dataset, "format", ""),
                             "calibration": getattr(dataset, "calibration_source", None),
                             "groundtruth": gt is not None}
        report = write_result(out, dataclasses.replace(res.ba, frontend=res.frontend, report=report), cfg,
                              dataset.camera, events_range=(t0, t1), full_sphere=args.full_sphere)
        iio.imwrite(out / "star_map.png", map_image(res.map, cfg.output.gamma, full_sphere=args.full_sphere)[0],
                    extension=".png")
        est = {"front-end": (res.frontend.t, res.frontend.omega),
               "BA": angular_velocity_from_trajectory(res.trajectory, cfg.backend.dt_knots)}
        gt_w = angular_velocity_from_trajectory(gt.slice_time(t0, t1)) if gt is not None and len(gt) > 2 else None
        plot_angular_velocity(out / "angular_velocity.png", est, gt_w, title="angular velocity")
        if gt is not None:
            tref = max(res.trajectory.t_start, gt.t_start)
            plot_trajectories(out / "trajectories.png",
                              {"front-end": res.frontend_trajectory.aligned_to(gt, tref),
                               "BA": res.trajectory.aligned_to(gt, tref)},
                              gt.slice_time(t0, t1), title="absolute rotation (aligned at the first pose)")
    line = (f"star tracking: {report['events_processed']} events, front-end {report['us_per_event']['frontend']:.2f} "
            f"us/event, BA {report['us_per_event']['backend']:.2f} us/event")
    if res.errors is not None:
        e = res.errors
        line += (f"; {args.window * 1000:.0f} ms relative rotation RMSE {e['ba']['rmse_deg']:.3f} deg "
                 f"(std {e['ba']['std_deg']:.3f}), front-end alone {e['frontend']['rmse_deg']:.3f} deg")
    print(f"{line} -> {args.out}{status_text(report)}")
    for warning in report.get("warnings", []):
        print(f"ti-cmax star-tracking: warning: {warning}", file=sys.stderr)
    print(json.dumps(json_ready({k: report.get(k) for k in ("rmse_deg", "std_deg")} if res.errors else {})))
    return 0

"""``ti-cmax plot``: figures of estimated trajectories, compared with ground truth when given (paper Fig. 6-9).

Writes, into ``--out DIR``: trajectories.png (orientation per axis, each estimate aligned to the ground truth at
t0) and angular_velocity.png (differences of each trajectory); with ``--groundtruth`` also errors_over_time.png
(absolute and relative error against time), errors.png (violins of both) and errors.json (RMSE per estimate).
Labels are the file names (their folder's name when names repeat) or ``--labels``. Evaluation parameters as in
``ti-cmax evaluate`` (EvaluationConfig: ``--config``/``--set``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = ("plot estimated trajectories (orientation and angular velocity per axis); with ground truth also the error "
        "over time and error violins")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--groundtruth", default=None, metavar="GT.txt",
                        help="ground-truth trajectory (TUM; without it only the estimates are drawn)")
    parser.add_argument("--estimate", required=True, nargs="+", metavar="EST.txt", help="estimated trajectories (TUM)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--labels", nargs="+", default=None, metavar="NAME", help="one label per estimate")
    parser.add_argument("--t0", type=float, default=None, metavar="S", help="alignment time (default as evaluate)")
    parser.add_argument("--angles", choices=("euler", "rotvec"), default="euler",
                        help="orientation shown per axis: extrinsic xyz Euler angles (default) or rotation vector")


def default_labels(paths: list[str]) -> list[str]:
    """File stems; where two are equal (e.g. two trajectory.txt), folder/stem."""
    stems = [Path(p).stem for p in paths]
    return [f"{Path(p).parent.name}/{s}" if stems.count(s) > 1 else s for p, s in zip(paths, stems)]


def run(args) -> int:
    from ..config import load_config
    from ..errors import InputError
    from ..io import read_tum
    from ..metrics import EvaluationConfig, evaluate_with_config
    from ..outputs import OutputDir
    from ..plots import (angular_velocity_from_trajectory, plot_angular_velocity, plot_error_distributions,
                         plot_errors_over_time, plot_trajectories)

    cfg = load_config(EvaluationConfig, args.config, args.overrides)
    labels = args.labels or default_labels(args.estimate)
    if len(labels) != len(args.estimate):
        raise InputError(f"--labels: expected {len(args.estimate)} labels (one per --estimate), got {len(labels)}")
    if len(set(labels)) != len(labels):
        raise InputError(f"labels must differ, got {', '.join(labels)}")
    estimates = {label: read_tum(path) for label, path in zip(labels, args.estimate)}
    rates = {label: angular_velocity_from_trajectory(est) for label, est in estimates.items()}
    if args.groundtruth is None:
        with OutputDir(args.out) as out:
            plot_trajectories(out / "trajectories.png", estimates, representation=args.angles,
                              title="orientation (no ground truth)")
            plot_angular_velocity(out / "angular_velocity.png", rates, title="angular velocity (camera frame)")
        print(f"wrote {args.out}/trajectories.png, angular_velocity.png")
        return 0
    gt = read_tum(args.groundtruth)
    errors = {label: evaluate_with_config(gt, est, cfg, t0=args.t0) for label, est in estimates.items()}
    aligned = {label: est.aligned_to(gt, errors[label].t0) if errors[label].aligned else est
               for label, est in estimates.items()}
    summary = {label: {"estimate": str(path), **e.to_dict()} for (label, e), path in zip(errors.items(), args.estimate)}
    with OutputDir(args.out) as out:
        plot_trajectories(out / "trajectories.png", aligned, gt, representation=args.angles)
        gt_rate = angular_velocity_from_trajectory(gt.slice_time(min(e.t_start for e in estimates.values()),
                                                                  max(e.t_end for e in estimates.values())))
        plot_angular_velocity(out / "angular_velocity.png", rates, gt_rate, title="angular velocity (camera frame)")
        plot_errors_over_time(out / "errors_over_time.png", errors)
        plot_error_distributions(out / "errors.png", {k: e.abs_errors_deg for k, e in errors.items()},
                                 {k: e.rel_errors_deg_per_s for k, e in errors.items()})
        (out / "errors.json").write_text(json.dumps(summary, indent=2) + "\n")
    width = max(len(label) for label in labels)
    for label, e in summary.items():
        rel = "n/a (overlap shorter than delta)" if e["rel_rmse_deg_per_s"] is None else \
            f"{e['rel_rmse_deg_per_s']:.3f} deg/s"
        print(f"{label:<{width}}  abs RMSE {e['abs_rmse_deg']:.3f} deg  rel RMSE {rel}")
    print(f"wrote {args.out}/trajectories.png, angular_velocity.png, errors_over_time.png, errors.png, errors.json")
    return 0

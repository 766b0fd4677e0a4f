"""``ti-cmax evaluate``: absolute and relative rotation RMSE of an estimated trajectory (Sec. IV-B).

Prints a short summary; the results as JSON go to ``--out FILE.json``, or, without ``--out``, to the last line
of stdout. Parameters come from EvaluationConfig (``--config``/``--set``); the options below override them.
"""
from __future__ import annotations

import argparse
import json

HELP = "absolute/relative rotation RMSE of an estimated trajectory against ground truth (TUM files)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--groundtruth", required=True, metavar="GT.txt", help="ground-truth trajectory (TUM)")
    parser.add_argument("--estimate", required=True, metavar="EST.txt", help="estimated trajectory (TUM)")
    parser.add_argument("--t0", type=float, default=None, metavar="S",
                        help="alignment time in seconds (default: start of the overlap + t0_offset, 0.1 s)")
    parser.add_argument("--t0-offset", type=float, default=None, metavar="S",
                        help="default alignment delay after the start (0.1 synthetic; use 1.0 for real data)")
    parser.add_argument("--no-align", action="store_true", help="compare without aligning at t0")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="evaluate absolute errors on a grid at HZ (50 for continuous trajectories) "
                             "instead of at the estimate's timestamps")
    parser.add_argument("--delta", type=float, default=None, metavar="S", help="relative-error pair span (1.0 s)")
    parser.add_argument("--gt-filter", type=float, default=None, metavar="S",
                        help="Gaussian low-pass the ground truth on SO(3) over S seconds (paper: 0.05 for mocap)")
    parser.add_argument("--out", default=None, metavar="FILE.json", help="write the results as JSON here")


def run(args) -> int:
    from dataclasses import replace

    from ..config import config_to_dict, load_config
    from ..io import read_tum
    from ..metrics import EvaluationConfig, evaluate_with_config
    from ..outputs import atomic_path, check_output_file

    if args.out:
        check_output_file(args.out)
    cfg = load_config(EvaluationConfig, args.config, args.overrides)
    changes = {}
    if args.t0_offset is not None:
        changes["t0_offset"] = args.t0_offset
    if args.no_align:
        changes["align"] = False
    if args.rate is not None:
        changes["sample_rate"] = args.rate
    if args.delta is not None:
        changes["rel_delta"] = args.delta
    if args.gt_filter is not None:
        changes["gt_filter_span"] = args.gt_filter
    cfg = replace(cfg, **changes)

    groundtruth = read_tum(args.groundtruth)
    estimate = read_tum(args.estimate)
    res = evaluate_with_config(groundtruth, estimate, cfg, t0=args.t0)
    out = res.to_dict()
    out.update(groundtruth=str(args.groundtruth), estimate=str(args.estimate), parameters=config_to_dict(cfg))

    def fmt(v, unit):
        return "n/a (overlap shorter than delta)" if v is None else f"{v:.4f} {unit}"

    print(f"absolute RMSE: {fmt(out['abs_rmse_deg'], 'deg')}  ({res.num_abs} samples, "
          f"{'aligned at t0 = ' + format(res.t0, '.3f') + ' s' if res.aligned else 'not aligned'})")
    print(f"relative RMSE: {fmt(out['rel_rmse_deg_per_s'], 'deg/s')}  ({res.num_rel} pairs of {res.rel_delta:g} s)")
    text = json.dumps(out)
    if args.out:
        with atomic_path(args.out) as tmp:
            tmp.write_text(text + "\n")
        print(f"wrote {args.out}")
    else:
        print(text)
    return 0


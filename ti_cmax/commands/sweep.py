"""``ti-cmax sweep``: sensitivity of CMax-SLAM to control-pose frequency, window size, map resolution and event
sampling rate (paper Sec. IV-H, Fig. 19) on a simulated sequence or a dataset with ground truth."""
from __future__ import annotations

import argparse
import json

HELP = "sensitivity sweep (Fig. 19): abs error and runtime vs dt_knots, window, map size, event sampling"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder: sweep.md, sweep.csv, sweep.png")
    parser.add_argument("--dataset", default=None, help="dataset with groundtruth.txt (default: simulate one)")
    parser.add_argument("--scene", default="bicycle", help="simulated scene (default: bicycle, as in the paper)")
    parser.add_argument("--duration", type=float, default=5.0, help="simulated duration (s)")
    parser.add_argument("--parameters", default="control_pose_frequency,window_size,map_height,event_sample_rate",
                        help="comma-separated subset")
    parser.add_argument("--quick", action="store_true", help="two values per parameter")


def run(args) -> int:
    import csv
    from types import SimpleNamespace

    from ..config import SlamConfig, load_config, save_config
    from ..errors import InputError
    from ..outputs import OutputDir
    from ..pipelines.sensitivity import SWEEPS, plot_sweep, rows_to_dicts, rows_to_markdown, run_sweep

    cfg = load_config(SlamConfig, args.config, args.overrides)
    params = [p.strip() for p in args.parameters.split(",") if p.strip()]
    unknown = [p for p in params if p not in SWEEPS]
    if unknown:
        raise InputError(f"--parameters: unknown {', '.join(unknown)} (expected some of {', '.join(SWEEPS)})")
    if args.dataset:
        from ..io import open_dataset_from_config

        ds = open_dataset_from_config(args.dataset, cfg.dataset)
        if ds.groundtruth is None:
            raise InputError("the sweep needs ground truth (groundtruth.txt)", source=str(args.dataset))
        sequence = SimpleNamespace(events=ds.read_events(), camera=ds.camera, groundtruth=ds.groundtruth)
    else:
        from ..simulate import SimulatorConfig, simulate_sequence

        sequence = simulate_sequence(SimulatorConfig(scene=args.scene, duration=args.duration,
                                                     max_angular_velocity=3.0))

    def show(row):
        print(f"{row.parameter}={row.value:g}: abs {row.abs_rmse_deg:.3f} deg, rel {row.rel_rmse_deg_per_s:.3f} "
              f"deg/s, {row.us_per_event_frontend + row.us_per_event_backend:.2f} us/event", flush=True)

    rows = run_sweep(sequence, cfg, params, quick=args.quick, progress=show)
    table = rows_to_markdown(rows)
    with OutputDir(args.out) as out:
        (out / "sweep.md").write_text(table + "\n")
        with open(out / "sweep.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows_to_dicts(rows)[0]))
            writer.writeheader()
            writer.writerows(rows_to_dicts(rows))
        (out / "sweep.json").write_text(json.dumps(rows_to_dicts(rows), indent=2))
        plot_sweep(out / "sweep.png", rows)
        save_config(cfg, out / "config.yaml")
    print(table)
    return 0

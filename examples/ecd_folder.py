"""CMax-SLAM on an ECD-layout folder (events.txt or events.h5, calib.txt, optional groundtruth.txt / imu.txt),
e.g. a sequence of the Event Camera Dataset: shapes_rotation, poster_rotation, boxes_rotation, dynamic_rotation.

    python examples/ecd_folder.py DATASET_DIR [--out ecd_example] [--t-end 10]

Per-dataset packet sizes of the reference (DESIGN.md): shapes 10k, poster 50k, boxes 30k, dynamic 20k events.
Real data is evaluated aligned at t0 = start + 1.0 s (Sec. IV-B).
"""
import argparse
import json
from pathlib import Path

import ti_cmax
from ti_cmax.config import load_config
from ti_cmax.metrics import T0_OFFSET_REAL

PACKET_SIZES = {"shapes": 10000, "poster": 50000, "boxes": 30000, "dynamic": 20000}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--out", default="ecd_example")
    ap.add_argument("--t-end", type=float, default=None, help="use events up to this time (s)")
    args = ap.parse_args()
    ds = ti_cmax.open_dataset(args.dataset)
    name = Path(args.dataset).name
    overrides = [f"num_events_per_packet={n}" for key, n in PACKET_SIZES.items() if name.startswith(key)]
    cfg = load_config(ti_cmax.SlamConfig, None, overrides)
    res = ti_cmax.run_slam(ds.iter_events(t_end=args.t_end), ds.camera, cfg)
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    from ti_cmax.commands.slam import write_result

    write_result(out, res, cfg, ds.camera)
    print(json.dumps(res.report["us_per_event"]), "->", out)
    if ds.groundtruth is not None:
        for label, traj in (("CMax-omega", res.frontend.trajectory()), ("CMax-SLAM", res.trajectory)):
            e = ti_cmax.evaluate_rotations(ds.groundtruth, traj, t0_offset=T0_OFFSET_REAL)
            print(f"{label:<11} abs RMSE {e.abs_rmse_deg:.3f} deg, rel RMSE {e.rel_rmse_deg_per_s:.3f} deg/s")


if __name__ == "__main__":
    main()

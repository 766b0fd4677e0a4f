"""``ti-cmax imu``: IMU dead reckoning (gyro integration) of a dataset's imu.txt, written as a TUM trajectory."""
from __future__ import annotations

import argparse

HELP = "integrate the gyro of a dataset (IMU dead reckoning) into trajectory.txt"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder with imu.txt (or an AEDAT4 file)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--start-from-groundtruth", action="store_true",
                        help="start from the ground-truth orientation instead of the identity")


def run(args) -> int:
    import time

    from ..config import SlamConfig, load_config, save_config
    from ..errors import InputError
    from ..io import open_dataset_from_config, write_tum
    from ..outputs import OutputDir, write_report
    from ti_cmax.pipelines.baselines.imu import dead_reckoning

    tic = time.perf_counter()
    cfg = load_config(SlamConfig, args.config, args.overrides)
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    imu = dataset.imu
    if imu is None:
        raise InputError("no IMU data found (expected imu.txt in the dataset folder)", source=str(args.dataset))
    r0 = None
    if args.start_from_groundtruth and dataset.groundtruth is not None:
        r0 = dataset.groundtruth.at(imu.t[0])[0]
    traj = dead_reckoning(imu.t, imu.gyro, r0=r0)
    with OutputDir(args.out) as out:
        write_tum(out / "trajectory.txt", traj)
        save_config(cfg, out / "config.yaml")
        report = {"status": "ok", "method": "imu", "samples": len(imu.t), "t_start": float(imu.t[0]),
                  "t_end": float(imu.t[-1]), "wall_seconds": time.perf_counter() - tic}
        write_report(out, report)
    print(f"integrated {len(imu.t)} gyro samples over {imu.t[-1] - imu.t[0]:.3f} s -> {args.out}/trajectory.txt")
    return 0

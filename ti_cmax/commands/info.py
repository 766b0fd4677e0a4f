"""``ti-cmax info DATASET``: what a dataset holds (events, duration, rate, sensor, calibration, GT, IMU).

Cheap: time range from the file's ends, event count from the format's metadata (text: data lines counted on
raw bytes). ``--json`` prints one JSON object instead of the table.
"""
from __future__ import annotations

import argparse
import json

HELP = "print what a dataset holds: events, duration, event rate, sensor size, calibration, ground truth, IMU"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="ECD-layout folder or events file (.txt .h5 .bag .aedat4 .raw)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--width", type=int, default=None, help="sensor width (overrides what the files say)")
    parser.add_argument("--height", type=int, default=None, help="sensor height")
    parser.add_argument("--topic", default=None, help="ROS bag event topic (default: the only EventArray topic)")


def dataset_info(ds) -> dict:
    """Summary of an opened dataset as a JSON-ready dict."""
    t0, t1 = ds.time_range()
    n = ds.num_events()
    dur = t1 - t0
    cam_src = ds.calibration_source
    info = {
        "name": ds.name, "path": str(ds.path), "events_file": str(ds.events_path), "format": ds.format,
        "num_events": n, "t_start": t0, "t_end": t1, "duration_s": dur,
        "event_rate_per_s": n / dur if dur > 0 else None,
        "sensor": {"width": ds.width, "height": ds.height, "from": ds.size_source},
        "calibration": None,
        "groundtruth": None, "imu": None,
    }
    if cam_src is not None:
        info["calibration"] = dict(ds.camera.to_dict(), source=cam_src)
    gt = ds.groundtruth
    if gt is not None:
        info["groundtruth"] = {"poses": len(gt), "t_start": gt.t_start, "t_end": gt.t_end,
                               "file": str(ds.groundtruth_path) if ds.groundtruth_path else ds.format}
    imu = ds.imu
    if imu is not None:
        span = float(imu.t[-1] - imu.t[0]) if len(imu) > 1 else 0.0
        info["imu"] = {"samples": len(imu), "rate_hz": (len(imu) - 1) / span if span > 0 else None,
                       "file": str(ds.imu_path) if ds.imu_path else ds.format}
    return info


def format_info(info: dict) -> str:
    lines = [
        f"dataset       {info['name']}  ({info['path']})",
        f"format        {info['format']}: {info['events_file']}",
        f"events        {info['num_events']:,}",
        f"time          {info['t_start']:.6f} .. {info['t_end']:.6f} s  (duration {info['duration_s']:.3f} s)",
    ]
    rate = info["event_rate_per_s"]
    lines.append(f"event rate    {rate / 1e6:.3f} M events/s" if rate else "event rate    n/a")
    s = info["sensor"]
    lines.append(f"sensor        {s['width']} x {s['height']}  ({s['from']})")
    c = info["calibration"]
    if c is None:
        lines.append("calibration   none (no calib.txt or camera_info YAML)")
    else:
        dist = " ".join(f"{v:.6g}" for v in c["dist"])
        lines.append(f"calibration   fx={c['fx']:.4f} fy={c['fy']:.4f} cx={c['cx']:.4f} cy={c['cy']:.4f} "
                     f"dist=[{dist}]  ({c['source']})")
    g = info["groundtruth"]
    lines.append(f"ground truth  {g['poses']} poses, {g['t_start']:.3f} .. {g['t_end']:.3f} s  ({g['file']})"
                 if g else "ground truth  none")
    m = info["imu"]
    if m:
        rate = f"{m['rate_hz']:.0f} Hz" if m["rate_hz"] else "n/a"
        lines.append(f"IMU           {m['samples']} samples, {rate}  ({m['file']})")
    else:
        lines.append("IMU           none")
    return "\n".join(lines)


def run(args) -> int:
    from dataclasses import replace

    from ..config import load_config
    from ..io.dataset import DatasetConfig, open_dataset_from_config

    cfg = load_config(DatasetConfig, args.config, args.overrides)
    if args.width or args.height:
        cfg = replace(cfg, width=args.width or 0, height=args.height or 0)
    if args.topic:
        cfg = replace(cfg, topic=args.topic)
    ds = open_dataset_from_config(args.dataset, cfg)
    info = dataset_info(ds)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0

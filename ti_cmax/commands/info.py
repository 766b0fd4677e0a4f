"""``ti-cmax info DATASET``: what a dataset holds (events, duration, rate, sensor, calibration, GT, IMU).

The events are read once, streamed, with the readers' checks (timestamps finite and sorted, pixels inside the
sensor): a bad file ends with exit 2 and one line naming the line (text) or event index (HDF5).
``--no-check`` only reads the file's ends and metadata (text: data lines counted on raw bytes).
``--json`` prints one JSON object instead of the table.
"""
from __future__ import annotations

import argparse
import json

from . import add_sensor_arguments, dataset_config

HELP = "print what a dataset holds: events, duration, event rate, sensor size, calibration, ground truth, IMU"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="ECD-layout folder or events file (.txt .h5 .bag .aedat4 .raw)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    add_sensor_arguments(parser, "ROS bag event topic (default: the only EventArray topic)")
    parser.add_argument("--no-check", action="store_true",
                        help="do not read the events (no check of timestamps and pixels; faster on big files)")


INFERRED_HOW = ("the smallest known sensor holding the largest x, y of the first chunk and centred on the "
                "principal point; if wrong: --set width=W --set height=H")


def check_events(ds, chunk_size: int) -> int:
    """Stream every event through the readers' checks (InputError naming the line on the first bad one)."""
    from ..progress import progress

    n = 0
    t0, t1 = ds.time_range()
    with progress(total=t1 - t0, desc="checking events", unit="s") as bar:
        for chunk in ds.iter_events(chunk_size):
            n += len(chunk)
            if len(chunk):
                bar.update(float(chunk.t[-1]) - t0 - bar.n)
    return n


def dataset_info(ds, checked_events: int | None = None) -> dict:
    """Summary of an opened dataset as a JSON-ready dict (``checked_events``: the count of a checked read)."""
    t0, t1 = ds.time_range()
    n = ds.num_events() if checked_events is None else checked_events
    dur = t1 - t0
    cam_src = ds.calibration_source
    info = {
        "name": ds.name, "path": str(ds.path), "events_file": str(ds.events_path), "format": ds.format,
        "num_events": n, "t_start": t0, "t_end": t1, "duration_s": dur,
        "event_rate_per_s": n / dur if dur > 0 else None,
        "sensor": {"width": ds.width, "height": ds.height, "from": ds.size_source},
        "events_checked": checked_events is not None,
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
    how = f": {INFERRED_HOW}" if s["from"].startswith("inferred") else ""
    lines.append(f"sensor        {s['width']} x {s['height']}  ({s['from']}{how})")
    lines.append("checked       timestamps finite and sorted, pixels inside the sensor" if info["events_checked"]
                 else "checked       no (--no-check)")
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
    from ..io.dataset import open_dataset_from_config

    cfg = dataset_config(args)
    ds = open_dataset_from_config(args.dataset, cfg)
    info = dataset_info(ds, None if args.no_check else check_events(ds, cfg.chunk_size))
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0

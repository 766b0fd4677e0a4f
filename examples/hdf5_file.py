"""Read an events HDF5 file (events/{t,x,y,p}, the E2VID {ts,xs,ys,ps} layout or DSEC-style int microseconds
with t_offset; compressed files need `pip install hdf5plugin`) in chunks and run the front-end and CMax-SLAM.

    python examples/hdf5_file.py EVENTS.h5 [--width 640 --height 480] [--calib calib.txt] [--out h5_example]

A text dataset converts to HDF5 first with `ti-cmax convert seq/events.txt seq/events.h5`.
"""
import argparse
from pathlib import Path

import ti_cmax
from ti_cmax.io import read_calib, write_angular_velocity, write_tum


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("events")
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--calib", help="calib.txt or camera_info YAML (default: next to the file)")
    ap.add_argument("--out", default="h5_example")
    args = ap.parse_args()
    ds = ti_cmax.open_dataset(args.events, args.width, args.height)
    camera = read_calib(args.calib, ds.width, ds.height) if args.calib else ds.camera
    t0, t1 = ds.time_range()
    print(f"{ds.num_events()} events, {t1 - t0:.3f} s, sensor {camera.width}x{camera.height}")
    front = ti_cmax.estimate_angular_velocity(ds.iter_events(chunk_size=500_000), camera)
    slam = ti_cmax.run_slam(ds.iter_events(chunk_size=500_000), camera)
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    write_angular_velocity(out / "angular_velocity.txt", front.t, front.omega)
    write_tum(out / "frontend_trajectory.txt", front.trajectory())
    write_tum(out / "slam_trajectory.txt", slam.trajectory)
    print(f"front-end {front.timing['us_per_event']:.2f} us/event; SLAM back-end "
          f"{slam.report['us_per_event']['backend']:.2f} us/event -> {out}")


if __name__ == "__main__":
    main()

"""Run CMax-SLAM on a ROS1 bag with dvs_msgs/EventArray messages (no ROS install needed: `pip install rosbags`).
The camera comes from a sensor_msgs/CameraInfo topic in the bag, or from --calib.

    python examples/ros_bag.py RECORDING.bag [--topic /dvs/events] [--calib calib.txt] [--out bag_example]
"""
import argparse
from pathlib import Path

import ti_cmax
from ti_cmax.commands.slam import write_result
from ti_cmax.io import read_calib


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bag")
    ap.add_argument("--topic", default=None)
    ap.add_argument("--calib", default=None)
    ap.add_argument("--out", default="bag_example")
    args = ap.parse_args()
    ds = ti_cmax.open_dataset(args.bag, topic=args.topic)
    camera = read_calib(args.calib, ds.width, ds.height) if args.calib else ds.camera
    cfg = ti_cmax.SlamConfig()
    res = ti_cmax.run_slam(ds.iter_events(), camera, cfg)
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    write_result(out, res, cfg, camera)
    print(f"{res.report['events_processed']} events -> {out}/trajectory.txt, map.png")


if __name__ == "__main__":
    main()

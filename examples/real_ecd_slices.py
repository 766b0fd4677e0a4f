"""The real recordings in ../shared/data/real: front-end on the four 30k-event ECD slices (compared with the
ST-PPP estimates where available) and CMax-SLAM on the first 1.43 s of shapes_rotation.

    python examples/real_ecd_slices.py [--data ../shared/data/real]
"""
import argparse
from pathlib import Path

import numpy as np

import ti_cmax
from ti_cmax.config import FrontendConfig
from ti_cmax.metrics import event_area_percent
from ti_cmax.pipelines.frontend import AngularVelocityEstimator


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    args = ap.parse_args()
    root = Path(args.data)
    print(f"{'slice':<18} {'omega [rad/s]':>28} {'ST-PPP [rad/s]':>28} {'diff %':>7}")
    for name in ("shapes_rotation", "poster_rotation", "boxes_rotation", "dynamic_rotation"):
        ds = ti_cmax.open_dataset(root / "ecd_slices" / name)
        ev = ds.read_events()
        est = AngularVelocityEstimator(ds.camera, FrontendConfig(num_events_per_packet=len(ev)))
        omega = est.estimate(ev, 0.5 * (ev.t[0] + ev.t[-1])).omega
        ref_file = root / "ecd_slices" / "stppp_output" / f"{name}_output.txt"
        ref, diff = "", ""
        if ref_file.exists():
            w = np.loadtxt(ref_file)[4:7]
            ref = np.array2string(w, precision=2)
            diff = f"{100 * np.linalg.norm(omega - w) / np.linalg.norm(w):.1f}"
        print(f"{name:<18} {np.array2string(omega, precision=2):>28} {ref:>28} {diff:>7}")
    ds = ti_cmax.open_dataset(root / "ecd_shapes_rotation_start")
    res = ti_cmax.run_slam(ds.iter_events(), ds.camera)
    w = res.frontend.omega
    print(f"shapes_rotation start: {len(res.frontend)} omegas, mean |omega| {np.linalg.norm(w, axis=1).mean():.2f} "
          f"rad/s, back-end {res.report['backend']['windows_optimized']} windows refined, "
          f"map event area {event_area_percent(res.map):.2f} %")


if __name__ == "__main__":
    main()

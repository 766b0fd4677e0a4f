"""Simulate a sequence, run the front-end, CMax-SLAM (linear and cubic) and the offline BA of IMU dead reckoning,
then compare all against ground truth.

    python examples/simulated_sequence.py [--scene city] [--sensor DAVIS240C] [--duration 3] [--out sim_example]
"""
import argparse
from pathlib import Path

import ti_cmax
from ti_cmax.config import load_config
from ti_cmax.plots import plot_error_distributions, plot_trajectories


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="city")
    ap.add_argument("--sensor", default="DAVIS240C")
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--out", default="sim_example")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(exist_ok=True)

    seq = ti_cmax.simulate_sequence(ti_cmax.SimulatorConfig(scene=args.scene, sensor=args.sensor,
                                                             duration=args.duration, max_angular_velocity=3.0))
    print(f"{len(seq.events)} events over {args.duration} s")
    estimates = {}
    for degree in (1, 3):
        cfg = load_config(ti_cmax.SlamConfig, None, [f"spline_degree={degree}"])
        res = ti_cmax.run_slam(seq.events, seq.camera, cfg)
        estimates[f"CMax-SLAM {'linear' if degree == 1 else 'cubic'}"] = res.trajectory
        if degree == 1:
            estimates["CMax-omega"] = res.frontend.trajectory()
    imu = ti_cmax.dead_reckoning(seq.imu.t, seq.imu.gyro)
    estimates["IMU dead reckoning"] = imu
    estimates["IMU + BA"] = ti_cmax.refine(seq.events, seq.camera, imu, ti_cmax.SlamConfig()).trajectory

    errors = {name: ti_cmax.evaluate_rotations(seq.groundtruth, traj) for name, traj in estimates.items()}
    print(f"{'method':<22} {'abs RMSE [deg]':>15} {'rel RMSE [deg/s]':>17}")
    for name, e in errors.items():
        print(f"{name:<22} {e.abs_rmse_deg:>15.3f} {e.rel_rmse_deg_per_s:>17.3f}")
    aligned = {n: t.aligned_to(seq.groundtruth, errors[n].t0) for n, t in estimates.items()}
    plot_trajectories(out / "trajectories.png", aligned, seq.groundtruth)
    plot_error_distributions(out / "errors.png", {n: e.abs_errors_deg for n, e in errors.items()},
                             {n: e.rel_errors_deg_per_s for n, e in errors.items()})
    print(f"plots in {out}/")


if __name__ == "__main__":
    main()

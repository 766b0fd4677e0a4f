"""Streaming CMax-SLAM from a live source: ``OnlineSlam.push`` takes each driver packet as it arrives, ``latest()``
gives the best pose now (refined spline where windows are done, integrated front-end beyond), a callback reports
every refined window, ``close()`` returns the same result as ``run_slam``.

    python examples/live_source.py [--sensor DVS128] [--duration 2] [--packet-us 1000] [--realtime] [--out live]

The "camera" here is a simulated sequence handed over in driver-sized packets (``--packet-us`` of sensor time
each); with ``--realtime`` each packet is released when the wall clock reaches its last timestamp. A real driver
plugs in the same way: turn each packet (dv-processing ``EventStore``, Metavision ``EventCD`` array, ROS
``EventArray``) into ``ti_cmax.Events(t, x, y, p)`` with its numpy arrays and push it.
"""
import argparse
import time
from pathlib import Path

import numpy as np

import ti_cmax
from ti_cmax import so3
from ti_cmax.io import write_tum
from ti_cmax.pipelines.slam import OnlineSlam


def live_packets(events, packet_s: float, realtime: bool):
    """Yield time-ordered packets of ``packet_s`` sensor seconds, optionally paced by the wall clock."""
    edges = np.arange(events.t[0], events.t[-1] + packet_s, packet_s)
    idx = np.searchsorted(events.t, edges, side="left")
    wall0, t0 = time.perf_counter(), float(events.t[0])
    for i0, i1 in zip(idx[:-1], idx[1:]):
        if i1 > i0:
            if realtime:
                time.sleep(max(0.0, (events.t[i1 - 1] - t0) - (time.perf_counter() - wall0)))
            yield events[i0:i1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sensor", default="DVS128")
    ap.add_argument("--scene", default="town")
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--packet-us", type=float, default=1000.0, help="driver packet length in sensor time")
    ap.add_argument("--realtime", action="store_true", help="release packets at their sensor time")
    ap.add_argument("--out", default="live_example")
    args = ap.parse_args()
    seq = ti_cmax.simulate_sequence(ti_cmax.SimulatorConfig(scene=args.scene, sensor=args.sensor,
                                                            duration=args.duration, seed=5))
    gt = seq.groundtruth
    t_first = float(seq.events.t[0])
    gt0 = gt.at(t_first)[0]

    def truth(t):  # ground truth in the estimate's world frame (the first camera frame)
        return gt0.T @ gt.at(t)[0]

    def on_window(w):
        state = "refined" if w.optimized else ("rejected" if w.rejected else "not refined")
        print(f"window [{w.t_start - t_first:5.2f}, {w.t_end - t_first:5.2f}] s: {w.num_events:7d} events, {state}")

    online = OnlineSlam(seq.camera, ti_cmax.SlamConfig(), on_window=on_window)
    print(f"{len(seq.events)} events, {args.duration:.1f} s, sensor {seq.camera.width}x{seq.camera.height}; "
          f"kernel preparation {online.startup['compile_cpu_seconds']:.1f} CPU s")
    errors, lags = [], []
    wall0 = time.perf_counter()
    for packet in live_packets(seq.events, args.packet_us * 1e-6, args.realtime):
        online.push(packet)
        t, r = online.latest()
        errors.append(np.degrees(so3.geodesic_angle(r, truth(t))))
        lags.append((time.perf_counter() - wall0) - (t - t_first))
    result = online.close()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.txt", result.trajectory)
    err = ti_cmax.evaluate_rotations(gt, result.trajectory)
    print(f"latest() pose error while streaming: mean {np.mean(errors):.3f} deg, max {np.max(errors):.3f} deg")
    if args.realtime:
        print(f"wall clock behind sensor time after each packet: mean {np.mean(lags):.3f} s, max {np.max(lags):.3f} s")
    print(f"final trajectory abs RMSE {err.abs_rmse_deg:.3f} deg ({len(result.windows)} windows) -> {out}")


if __name__ == "__main__":
    main()

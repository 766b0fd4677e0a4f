"""Benchmark of the CMax-omega front-end on simulated sequences (a command, not a test).

    python -m ti_cmax.pipelines.evaluation.bench_frontend [--duration 5] [--scenes city,town] [--sensors DAVIS240C,DVS128]
        [--threads 2] [--set key=value ...] [--rules bounded,paper] [--json OUT.json]

For each simulated sequence (ti_cmax.simulate; every scene x sensor) and slicing rule it prints a table row:
events, packets, still packets, us per processed event (events in the packets, before thinning) and per input
event (steady state, compile time apart; wall and CPU time, the CPU time counts every thread, so it is the
figure to compare when other jobs share the machine), mean evaluations per packet,
angular-velocity RMSE against the simulator's omega at the packet times (rad/s and deg/s), and the
absolute / relative rotation RMSE of the integrated trajectory (ti_cmax.metrics, aligned at t0).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from ti_cmax import progress
from ti_cmax.config import FrontendConfig, parse_overrides, update_config
from ti_cmax.kernels import runtime
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.pipelines.frontend import estimate_angular_velocity
from ti_cmax.simulate import SimulatorConfig, simulate_sequence


def _omega_rmse(result, seq) -> float:
    gt = np.column_stack([np.interp(result.t, seq.omega_t, seq.omega[:, i]) for i in range(3)])
    return float(np.sqrt(np.mean(np.sum((result.omega - gt) ** 2, axis=1))))


def run_one(scene: str, duration: float, rule: str, overrides: dict, seed: int = 0,
            sensor: str = "DAVIS240C") -> dict:
    t0 = time.perf_counter()
    seq = simulate_sequence(SimulatorConfig(scene=scene, duration=duration, sensor=sensor, seed=seed))
    sim_s = time.perf_counter() - t0
    cfg = update_config(FrontendConfig(), {**overrides, "frontend_slicing": rule})
    res = estimate_angular_velocity(seq.events, seq.camera, cfg)
    err = evaluate_rotations(seq.groundtruth, res.trajectory())
    rmse = _omega_rmse(res, seq)
    return {
        "scene": scene, "sensor": sensor, "rule": rule, "duration_s": duration, "events": int(len(seq.events)),
        "simulate_seconds": sim_s, "packets": int(len(res)), "still": int(res.sparse.sum()),
        "events_processed": res.timing["events_processed"], "compile_seconds": res.timing["compile_seconds"],
        "wall_seconds": res.timing["wall_seconds"], "us_per_event": res.timing["us_per_event"],  # per input event
        "us_per_packet_event": res.timing["us_per_packet_event"],
        "cpu_us_per_input_event": res.timing["cpu_seconds"] * 1e6 / max(1, len(seq.events)),
        "events_evaluated": res.timing.get("events_evaluated", 0),
        "mean_evaluations": float(np.mean(res.evaluations)) if len(res) else 0.0,
        "us_per_event_per_evaluation": res.timing["us_per_event_per_evaluation"],
        "omega_rmse_rad_s": rmse, "omega_rmse_deg_s": float(np.degrees(rmse)),
        "abs_rmse_deg": err.abs_rmse_deg, "rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ti_cmax.pipelines.evaluation.bench_frontend", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--scenes", default="city,town")
    ap.add_argument("--sensors", default="DAVIS240C")
    ap.add_argument("--rules", default="bounded")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    if args.threads:
        runtime.set_num_threads(args.threads)

    progress.set_quiet(True)
    overrides = parse_overrides(args.overrides)
    rows = []
    cols = ("scene", "sensor", "rule", "events", "packets", "still", "us_per_event", "us_per_packet_event",
            "cpu_us_per_input_event", "mean_evaluations", "omega_rmse_deg_s", "abs_rmse_deg", "rel_rmse_deg_per_s", "compile_seconds")
    print(" | ".join(cols))
    for sensor in args.sensors.split(","):
        for scene in args.scenes.split(","):
            for rule in args.rules.split(","):
                row = run_one(scene.strip(), args.duration, rule.strip(), overrides, args.seed, sensor.strip())
                rows.append(row)
                print(" | ".join(f"{row[c]:.3f}" if isinstance(row[c], float) else str(row[c]) for c in cols),
                      flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

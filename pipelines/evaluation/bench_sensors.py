"""Sensor suite: CMax-SLAM with the default (sensor-derived) settings from a DVS128 to an HD sensor.

    python -m ti_cmax.pipelines.evaluation.bench_sensors --out DIR [--sensors DVS128,DAVIS240C,...]
        [--engines taichi,quadrants]

The cases are ``pipelines.benchmark.SUITES["sensors"]`` (``ti-cmax benchmark --suite sensors`` runs the same
sequences through the task model; this script adds per-case peak memory, the derived parameters and the cost per
second of data). Each case is a simulated sequence (streamed to DIR/sequences/NAME, reused when its simulation.json matches) run
by ``ti-cmax slam`` in a child process (so each case's peak memory is its own; in the command's default process
layout: a back-end worker up to 0.5 M pixels on 2+ cores, pipelines/slam.default_backend_process), then evaluated
against ground truth: the front-end alone (integrated omega) and CMax-SLAM, abs / rel RMSE, the parameters the
sensor rules derived, us per input event, wall time per second of data and peak RSS; one row per kernel engine
(``--engines``, default: each one installed; the same sequence, DIR/runs/NAME/ENGINE). Prints a markdown table (and
writes DIR/sensors.md, DIR/sensors.json). This is a benchmark, not a test: it takes minutes (HD: 30 M events/s).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

from ti_cmax.io import read_angular_velocity, read_tum
from ti_cmax.kernels.engine import ENGINES, installed_engines
from ti_cmax.kernels.iwe import IWEWorkspace
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.pipelines.evaluation.suites import SUITES
from ti_cmax.simulate import SimulatorConfig, simulate_to_folder
from ti_cmax.so3 import integrate_angular_velocity
from ti_cmax.trajectory import Trajectory


def simulator_overrides(spec) -> dict:
    """SimulatorConfig fields of a suite sequence (``pipelines.benchmark.SequenceSpec``)."""
    return {"sensor": spec.sensor, "scene": spec.scene, "duration": spec.duration, "seed": spec.seed,
            "trajectory": spec.trajectory, **dict(spec.options)}


def _simulate(case, folder: Path) -> dict:
    """Simulate the case into folder unless a matching simulation is there already; returns simulation.json."""
    info_path = folder / "simulation.json"
    config = SimulatorConfig(**simulator_overrides(case)).resolved()
    wanted = {k: getattr(config, k) for k in simulator_overrides(case)}
    if info_path.exists():
        info = json.loads(info_path.read_text())
        if all(info.get("config", {}).get(k) == v for k, v in wanted.items()):
            return info
    return simulate_to_folder(config, folder, show_progress=False)


def _run_slam(dataset: Path, out: Path, threads: int | None, overrides: list[str], flags: tuple = (),
              engine: str | None = None) -> float:
    """``ti-cmax slam`` (with ``flags``, e.g. --realtime) in a child process, on kernel ``engine`` (default: the
    chosen one, kernels/engine.py); returns its wall time (report.json holds the rest)."""
    cmd = [sys.executable, "-m", "ti_cmax.cli", "slam", str(dataset), "--out", str(out), "--quiet", *flags]
    if threads:
        cmd += ["--threads", str(threads)]
    for item in overrides:
        cmd += ["--set", item]
    tic = time.perf_counter()
    env = {**os.environ, "TI_CMAX_ENGINE": engine} if engine else None
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"slam failed on {dataset}: {proc.stderr.strip().splitlines()[-1:]}")
    return time.perf_counter() - tic


def evaluate_case(case, root: Path, threads: int | None = None, overrides: list[str] = (),
                  engine: str | None = None) -> dict:
    seq = root / "sequences" / case.name
    info = _simulate(case, seq)
    out = root / "runs" / case.name / (engine or "")
    if out.exists():
        import shutil

        shutil.rmtree(out)
    wall = _run_slam(seq, out, threads, list(overrides), engine=engine)
    report = json.loads((out / "report.json").read_text())
    gt = read_tum(seq / "groundtruth.txt")
    t, omega = read_angular_velocity(out / "angular_velocity.txt")
    front = evaluate_rotations(gt, Trajectory(t, integrate_angular_velocity(t, omega)))
    slam = evaluate_rotations(gt, read_tum(out / "trajectory.txt"))
    us = report["us_per_event"]
    return {
        "case": asdict(case), "events": int(info["num_events"]), "event_rate_mev_s": info["event_rate"] / 1e6,
        "camera": info["camera"], "engine": f"{report['engine']['name']} {report['engine']['version']}",
        "status": report["status"],
        "frontend_abs_deg": front.abs_rmse_deg, "frontend_rel_deg_s": front.rel_rmse_deg_per_s,
        "slam_abs_deg": slam.abs_rmse_deg, "slam_rel_deg_s": slam.rel_rmse_deg_per_s,
        "frontend_us_per_event": us["frontend"], "backend_us_per_event": us["backend"],
        "compile_seconds": report["compile_seconds"], "process_wall_seconds": wall,
        "steady_seconds_per_data_second": (us["frontend"] + us["backend"]) * 1e-6 * info["num_events"]
        / case.duration,
        "peak_rss_mb": report.get("peak_rss_mb"), "derived": report.get("derived_parameters", {}),
        "events_used_fraction": report["backend"].get("events_used_fraction"),
        "suspect_packets": report["frontend"].get("suspect_packets"), "packets": report["frontend"]["packets"],
        "loadavg": list(os.getloadavg()),
    }


PROBE_EVENTS = 15_000  # about a DAVIS240C front-end packet at 1 M ev/s after thinning


def speed_probe(evaluations: int = 40, seed: int = 0) -> float:
    """This machine's speed right now: median milliseconds of one front-end contrast evaluation (vote, blur, gather;
    kernels/iwe.py, on the calling thread) of a fixed synthetic packet of PROBE_EVENTS events on a DAVIS240C-sized
    image. Every timing of these benchmarks scales with it, and a shared or virtual machine's speed can vary by
    1.5-2x within an hour, more than most changes measured, so a table row carries the probe taken just before its
    runs (about 50 ms, plus the kernels' preparation once)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    w, h, f = 240, 180, 199.0
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    xy = rng.uniform([0, 0], [w, h], (PROBE_EVENTS, 2))
    bearings = np.column_stack([(xy[:, 0] - w / 2) / f, (xy[:, 1] - h / 2) / f, np.ones(PROBE_EVENTS)])
    ws = IWEWorkspace(w, h, np.float32, capacity=PROBE_EVENTS)
    ws.set_packet(bearings, rng.uniform(-0.02, 0.02, PROBE_EVENTS))
    omega = np.array([0.5, 1.0, 0.3])
    ws.evaluate(omega, K)  # compile or load the kernels, warm the caches
    times = []
    for _ in range(evaluations):
        tic = time.perf_counter()
        ws.evaluate(omega, K)
        times.append(time.perf_counter() - tic)
    return float(np.median(times) * 1e3)


def _f(v, digits=2) -> str:
    return "-" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))


def format_table(rows: list[dict]) -> str:
    lines = [
        "| sensor (case) | engine | events (Mev/s) | front-end abs / rel | CMax-SLAM abs / rel | status "
        "| FE + BE us/ev | s per s of data (steady) | compile s | peak RSS MB | map | packet / cap | BA events used "
        "| load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        d = r["derived"]
        size = f"{2 * d['pano_height']}x{d['pano_height']}" if "pano_height" in d else "user"
        lines.append(" | ".join([
            f"| {r['case']['sensor']} ({r['case']['name']})", r["engine"],
            f"{r['events'] / 1e6:.1f} M ({r['event_rate_mev_s']:.1f})",
            f"{_f(r['frontend_abs_deg'])} / {_f(r['frontend_rel_deg_s'])}",
            f"{_f(r['slam_abs_deg'], 3)} / {_f(r['slam_rel_deg_s'], 3)}", r["status"],
            f"{_f(r['frontend_us_per_event'])} + {_f(r['backend_us_per_event'])}",
            _f(r["steady_seconds_per_data_second"]), _f(r["compile_seconds"], 1), _f(r["peak_rss_mb"], 0), size,
            f"{d.get('num_events_per_packet', 'user')} / {d.get('frontend_max_packet_events', 'user')}",
            _f(r["events_used_fraction"]), _f(r["loadavg"][0], 1)]) + " |")
    lines += ["", "abs deg / rel deg/s against ground truth (aligned at start + 0.1 s); us per input event in steady "
              "state (compilation apart); s per s of data = (FE + BE) us/event x events / duration; load = 1-min "
              "load average after the case. Targets: abs <= 0.3 deg, rel <= 0.3 deg/s on every sensor; "
              "VGA at 12 Mev/s no costlier per input event than DAVIS240C at 1 Mev/s; HD peak < 1.5 GB."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ti_cmax.pipelines.evaluation.bench_sensors", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, metavar="DIR", help="sequences, runs and the tables go here")
    ap.add_argument("--sensors", default="", help="comma-separated case names or sensors (default: all)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="slam override for every case")
    ap.add_argument("--engines", default="", help="comma-separated kernel engines, a row each (default: every "
                    "installed one: taichi, quadrants)")
    args = ap.parse_args(argv)

    engines = [e.strip().lower() for e in args.engines.split(",") if e.strip()] or installed_engines()
    if set(engines) - set(ENGINES):
        ap.error(f"--engines: expected some of {', '.join(ENGINES)}, got {args.engines}")

    wanted = {s.strip().lower() for s in args.sensors.split(",") if s.strip()}
    cases = [c for c in SUITES["sensors"].values() if not wanted or c.name in wanted or c.sensor.lower() in wanted]
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in cases:
        for engine in engines:
            rows.append(evaluate_case(case, root, args.threads, args.overrides, engine))
            print(f"{case.name} ({rows[-1]['engine']}): {rows[-1]['events']} events, CMax-SLAM abs "
                  f"{rows[-1]['slam_abs_deg']:.3f} deg", flush=True)
            (root / "sensors.json").write_text(json.dumps(rows, indent=2, default=float))
    table = format_table(rows)
    (root / "sensors.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

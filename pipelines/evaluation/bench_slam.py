"""Benchmark of CMax-SLAM on simulated sequences (a command, not a test).

    python -m ti_cmax.pipelines.evaluation.bench_slam [--duration 5] [--sensors DAVIS240C,DVS128,DAVIS346]
        [--scenes bay,city] [--set key=value ...] [--threads N] [--refine-degree 1] [--json OUT.json] [--quick]

For each simulated sequence (every sensor x scene) it prints a markdown table with one row per method:
front-end alone (CMax-omega, integrated), CMax-SLAM with a linear and a cubic spline, IMU dead reckoning
(the simulated gyro, which carries a constant bias) and that dead reckoning refined by the offline BA
(``refine``). Columns: absolute / relative rotation RMSE (ti_cmax.metrics.evaluate_rotations, default t0
policy, each estimate at its own timestamps), event area EA% and gradient magnitude GM of the final
panoramic map (the back-end's I_G for SLAM/refine, else the events rendered with the method's trajectory at
the same map size), us/event of front-end and back-end in steady state (compile time in its own column), wall
time, and the process's peak resident memory so far (ru_maxrss). The 1-minute load average is printed with
every table because timings are only comparable on an idle machine, and so is a speed probe taken before and
after the runs (bench_sensors.speed_probe: ms per front-end evaluation of a fixed packet; a shared or virtual
machine's speed drifts). Paper anchors and our targets follow.
``--quick`` lowers the map size and CG iteration caps (smoke runs; figures are not comparable).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

from ti_cmax import progress
from ti_cmax.config import SlamConfig, parse_overrides, update_config
from ti_cmax.kernels import runtime
from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude
from ti_cmax.outputs import peak_rss_mb
from ti_cmax.pipelines.baselines.imu import dead_reckoning
from ti_cmax.pipelines.evaluation.bench_sensors import speed_probe
from ti_cmax.pipelines.panorama import render_panorama
from ti_cmax.pipelines.sensor_defaults import pano_size
from ti_cmax.pipelines.slam import refine, run_slam
from ti_cmax.simulate import SimulatorConfig, simulate_sequence

METHODS = ("front-end (CMax-omega)", "SLAM linear", "SLAM cubic", "IMU dead reckoning", "IMU + offline BA")
ROW_KEYS = ("method", "abs_rmse_deg", "rel_rmse_deg_per_s", "ea_percent", "gm", "map_events",
            "frontend_us_per_event", "backend_us_per_event", "compile_seconds", "wall_seconds", "peak_rss_mb")
QUICK_OVERRIDES = {"pano_height": 256, "frontend_cg_max_iters": 20, "backend_cg_max_iters": 10}

# Paper anchors and our targets
PAPER_TAB2 = {"abs_rmse_deg": (0.33, 0.80), "rel_rmse_deg_per_s": (0.41, 0.72)}  # synthetic CMax-SLAM
PAPER_TAB6 = {"linear": (4.6, 11.2), "cubic": (7.6, 20.4)}  # back-end us/event
TARGETS = {"abs_rmse_deg": 0.3, "rel_rmse_deg_per_s": 0.3, "backend_linear": 1.0, "backend_cubic": 1.5}


def _map_figures(image: np.ndarray, lambda0: float) -> tuple[float, float]:
    return event_area_percent(image, lambda0), gradient_magnitude(image)


def _row(method: str, gt, trajectory, image: np.ndarray, map_events: int, lambda0: float, *,
         fe_us: float | None = None, be_us: float | None = None, compile_s: float | None = None,
         wall_s: float | None = None, extra: dict | None = None) -> dict:
    err = evaluate_rotations(gt, trajectory)
    ea, gm = _map_figures(image, lambda0)
    row = {
        "method": method, "abs_rmse_deg": err.abs_rmse_deg, "rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
        "ea_percent": ea, "gm": gm, "map_events": int(map_events),
        "frontend_us_per_event": fe_us, "backend_us_per_event": be_us, "compile_seconds": compile_s,
        "wall_seconds": wall_s, "peak_rss_mb": peak_rss_mb(),
        "abs_max_deg": err.abs_max_deg, "num_rel": err.num_rel, "t0": err.t0,
    }
    row.update(extra or {})
    return row


def loop_counts(report: dict) -> tuple[int, int, int]:
    """The loop closer's (applied, accepted, candidates) from a report's "loops" (zeros without loop closure)."""
    loops = report.get("loops") or []
    return (sum(bool(e.get("applied")) for e in loops), sum(bool(e.get("accepted")) for e in loops), len(loops))


def _slam_extra(report: dict) -> dict:
    be = report["backend"]
    applied, accepted, candidates = loop_counts(report)
    return {"windows": be["windows"], "windows_optimized": be["windows_optimized"],
            "backend_mean_iterations": be["mean_iterations"], "events_settled": be["events_settled"],
            "backend_seconds": be["wall_seconds"], "loops_applied": applied, "loops_accepted": accepted,
            "loops_candidates": candidates, "windows_rejected": be["windows_rejected"],
            "windows_refitted": be["windows_refitted"], "windows_confirmed_by_refit": be["windows_confirmed_by_refit"]}


def bench_sequence(sensor: str, scene: str, duration: float, overrides: dict | None = None, seed: int = 0,
                   quick: bool = False, refine_degree: int = 1) -> dict:
    """Simulate one sequence, run every method of METHODS on it and return its rows plus metadata."""
    load_start = os.getloadavg()
    probe_start = speed_probe()
    tic = time.perf_counter()
    seq = simulate_sequence(SimulatorConfig(scene=scene, duration=duration, sensor=sensor, seed=seed))
    sim_s = time.perf_counter() - tic
    values = {**(QUICK_OVERRIDES if quick else {}), **(overrides or {})}
    base = update_config(SlamConfig(), values, source="--set")
    linear = update_config(base, {"spline_degree": 1})
    cubic = update_config(base, {"spline_degree": 3})
    refine_cfg = update_config(base, {"spline_degree": int(refine_degree)})
    width, height = pano_size(base.backend, seq.camera)
    lam, batch = base.backend.lambda0, base.backend.event_batch_size
    gt = seq.groundtruth

    def render(traj):
        return render_panorama([seq.events], seq.camera, traj, width, height, batch_size=batch)

    rows = []
    res_lin = run_slam(seq.events, seq.camera, linear)
    res_cub = run_slam(seq.events, seq.camera, cubic)
    # front-end alone: the linear run's front-end output (same packets, same code path)
    # (us per input event as in the SLAM rows; the front-end's own us_per_event counts packet overlaps)
    fe = res_lin.frontend
    pano = render(fe.trajectory())
    rows.append(_row(METHODS[0], gt, fe.trajectory(), pano.image, pano.events_used, lam,
                     fe_us=res_lin.report["us_per_event"]["frontend"], compile_s=fe.timing["compile_seconds"],
                     wall_s=fe.timing["wall_seconds"], extra={"packets": len(fe), "still": int(fe.sparse.sum())}))
    for name, res in ((METHODS[1], res_lin), (METHODS[2], res_cub)):
        rep = res.report
        rows.append(_row(name, gt, res.trajectory, res.map, rep["backend"]["events_settled"], lam,
                         fe_us=rep["us_per_event"]["frontend"], be_us=rep["us_per_event"]["backend"],
                         compile_s=rep["compile_seconds"], wall_s=rep["wall_seconds"], extra=_slam_extra(rep)))
    del res_lin, res_cub
    tic = time.perf_counter()
    dr = dead_reckoning(seq.imu.t, seq.imu.gyro)
    dr_s = time.perf_counter() - tic
    pano = render(dr)
    rows.append(_row(METHODS[3], gt, dr, pano.image, pano.events_used, lam, wall_s=dr_s))
    res_ref = refine(seq.events, seq.camera, dr, refine_cfg)
    rep = res_ref.report
    rows.append(_row(METHODS[4], gt, res_ref.trajectory, res_ref.map, rep["backend"]["events_settled"], lam,
                     be_us=rep["us_per_event"]["backend"], compile_s=rep["compile_seconds"],
                     wall_s=rep["wall_seconds"], extra={**_slam_extra(rep), "spline_degree": int(refine_degree)}))
    return {
        "sensor": sensor, "scene": scene, "duration_s": duration, "seed": seed, "quick": quick,
        "events": int(len(seq.events)), "event_rate_mev_s": len(seq.events) / duration / 1e6,
        "simulate_seconds": sim_s, "gyro_bias_deg_s": np.degrees(seq.gyro_bias).tolist(),
        "map_size": [int(width), int(height)], "overrides": values, "refine_degree": int(refine_degree),
        "loadavg_start": list(load_start), "loadavg_end": list(os.getloadavg()),
        "probe_ms": [probe_start, speed_probe()], "peak_rss_mb": peak_rss_mb(), "rows": rows,
    }


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.{digits}f}"
    return str(v)


def format_table(result: dict) -> str:
    """Markdown table of one sequence, with its header line and the target check."""
    bias = ", ".join(f"{b:.3f}" for b in result["gyro_bias_deg_s"])
    w, h = result["map_size"]
    lines = [
        f"### {result['sensor']} / {result['scene']}, {result['duration_s']:g} s, {result['events']} events "
        f"({result['event_rate_mev_s']:.2f} Mev/s), map {w}x{h}, gyro bias ({bias}) deg/s"
        + (" [quick]" if result["quick"] else ""),
        f"load avg (1/5/15 min) start {', '.join(f'{x:.2f}' for x in result['loadavg_start'])}; "
        f"end {', '.join(f'{x:.2f}' for x in result['loadavg_end'])}; simulate {result['simulate_seconds']:.1f} s"
        + ("; speed probe start / end " + " / ".join(f"{x:.2f}" for x in result["probe_ms"]) + " ms"
           if result.get("probe_ms") else ""),
        "",
        "| method | abs RMSE (deg) | rel RMSE (deg/s) | EA% | GM | map events | FE us/ev | BE us/ev "
        "| compile s | wall s | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append("| " + " | ".join([
            r["method"], _fmt(r["abs_rmse_deg"]), _fmt(r["rel_rmse_deg_per_s"]), _fmt(r["ea_percent"], 2),
            _fmt(r["gm"], 4), str(r["map_events"]), _fmt(r["frontend_us_per_event"], 2),
            _fmt(r["backend_us_per_event"], 2), _fmt(r["compile_seconds"], 1), _fmt(r["wall_seconds"], 1),
            _fmt(r["peak_rss_mb"], 0)]) + " |")
    lines.append("")
    lines.append(target_check(result))
    return "\n".join(lines)


def target_check(result: dict) -> str:
    """One line: SLAM rows against our targets (abs, rel, back-end us/event)."""
    by = {r["method"]: r for r in result["rows"]}
    parts = []
    for name, key in ((METHODS[1], "backend_linear"), (METHODS[2], "backend_cubic")):
        r = by.get(name)
        if r is None:
            continue
        ok = (r["abs_rmse_deg"] <= TARGETS["abs_rmse_deg"],
              (r["rel_rmse_deg_per_s"] <= TARGETS["rel_rmse_deg_per_s"]) if math.isfinite(r["rel_rmse_deg_per_s"])
              else None,
              r["backend_us_per_event"] <= TARGETS[key])
        parts.append(f"{name}: abs {_ok(ok[0])}, rel {_ok(ok[1])}, back-end us/ev {_ok(ok[2])}")
    return "targets: " + "; ".join(parts)


def _ok(v) -> str:
    return "n/a" if v is None else ("PASS" if v else "FAIL")


def anchors_text() -> str:
    return "\n".join([
        "Paper anchors: Tab. II (synthetic) CMax-SLAM abs RMSE "
        f"{PAPER_TAB2['abs_rmse_deg'][0]}-{PAPER_TAB2['abs_rmse_deg'][1]} deg, rel RMSE "
        f"{PAPER_TAB2['rel_rmse_deg_per_s'][0]}-{PAPER_TAB2['rel_rmse_deg_per_s'][1]} deg/s; "
        f"Tab. VI back-end {PAPER_TAB6['linear'][0]}-{PAPER_TAB6['linear'][1]} us/event linear, "
        f"{PAPER_TAB6['cubic'][0]}-{PAPER_TAB6['cubic'][1]} cubic.",
        f"Our targets: abs <= {TARGETS['abs_rmse_deg']} deg, rel <= {TARGETS['rel_rmse_deg_per_s']} deg/s, "
        f"back-end <= {TARGETS['backend_linear']} us/event linear, <= {TARGETS['backend_cubic']} cubic "
        "(1024x512 map, pano_height=512).",
        "Notes: rel RMSE uses 1 s pairs (nan if the sequence is shorter); FE/BE us/ev are per input event as "
        "reported by run_slam/refine, compilation apart; "
        "SLAM wall includes compilation; peak RSS is the process peak so far (monotone across rows).",
    ])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ti_cmax.pipelines.evaluation.bench_slam", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--sensors", default="DAVIS240C")
    ap.add_argument("--scenes", default="bay,city")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--refine-degree", type=int, default=1, choices=(1, 3),
                    help="spline degree of the offline BA of the IMU trajectory")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="SlamConfig override (any section), e.g. pano_height=256")
    ap.add_argument("--quick", action="store_true", help=f"smoke settings {QUICK_OVERRIDES}")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)
    if args.threads:
        runtime.set_num_threads(args.threads)

    progress.set_quiet(True)
    overrides = parse_overrides(args.overrides)
    results = []
    for sensor in [s.strip() for s in args.sensors.split(",") if s.strip()]:
        for scene in [s.strip() for s in args.scenes.split(",") if s.strip()]:
            res = bench_sequence(sensor, scene, args.duration, overrides, args.seed, args.quick, args.refine_degree)
            results.append(res)
            print(format_table(res) + "\n", flush=True)
            if args.json:  # rewrite after each sequence so a long run leaves partial results
                with open(args.json, "w") as fh:
                    json.dump(results, fh, indent=2)
    print(anchors_text())
    print(f"threads {runtime.num_threads()}, cpu count {os.cpu_count()}, peak RSS {peak_rss_mb():.0f} MB")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

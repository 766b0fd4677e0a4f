"""Benchmark of loop closure (issue 15; a command, not a test): CMax-SLAM with loop_closure=false and =true.

    python -m ti_cmax.pipelines.bench_loops --cache DIR [--sequences SPEC,...] [--set key=value ...] [--threads N]

A SPEC is sensor:scene:duration:trajectory[:turns[:wobble]][:key=value...] (e.g. DAVIS240C:bay:12:pan:2.2:0.5, or
DAVIS240C:city:5:random for a sequence without revisits; key=value: any simulator field, e.g. seed=1,
contrast_threshold=0.4, noise_rate=0.5). Each sequence is simulated once into DIR (reused
later). One markdown table row per sequence and mode: abs / rel rotation RMSE (ti_cmax.metrics.evaluate_rotations),
the largest and the median error of the 0.1 s relative rotations (a jump at a loop shows in the largest),
event area EA% and gradient magnitude GM of all events rendered along the trajectory (the same map size for both
modes: the loop closer's rebuilt map holds only subsamples), loops applied / candidates, back-end us per input event
and the loop closer's share of it. The 1-minute load average is printed: timings are only comparable on an idle
machine.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

# Declared before any result was seen (session 5). Revisits (2-3 turns): the issue's DAVIS240C bay pan, other
# scenes and seeds, VGA, and the hard cases where drift is large: long pans, lower event rates (higher contrast
# threshold), background noise, the 128x128 DVS128. Without revisits: random motion and a pan that stops short
# of a full turn (must stay within 2 % of loop_closure=false). Cheapest first; the VGA pan (15 Mev/s, 122 M
# events) is last (a second VGA pan, VGA:city:12:pan:3:0.3, was dropped: its simulation ran at 0.02x real time).
REVISIT_SEQUENCES = (
    "DAVIS240C:bay:14:pan:2.2:0.3",
    "DVS128:city:12:pan:2.2:0.5",
    "DVS128:street:24:pan:3:0.3:seed=3:noise_rate=1",
    "DAVIS240C:town:20:pan:3:0.3:seed=2:contrast_threshold=0.4:noise_rate=0.5",
    "DAVIS240C:city:10:pan:2:0.5:seed=1",
    "VGA:bay:8:pan:2:0.5",
)
NO_REVISIT_SEQUENCES = (
    "DAVIS240C:bay:5:random",
    "DAVIS240C:city:8:pan:0.9:0.5",
    "VGA:city:2:random:seed=1",
)
DEFAULT_SEQUENCES = REVISIT_SEQUENCES + NO_REVISIT_SEQUENCES


def _dataset(cache: Path, spec: str) -> Path:
    from ti_cmax.config import update_config
    from ti_cmax.simulate import SimulatorConfig, simulate_to_folder

    parts = [p for p in spec.split(":") if "=" not in p]
    extra = dict(p.split("=", 1) for p in spec.split(":") if "=" in p)
    if len(parts) < 4:
        raise SystemExit(f"bench_loops: bad sequence {spec!r} (sensor:scene:duration:trajectory[:turns[:wobble]])")
    values = {"sensor": parts[0], "scene": parts[1], "duration": float(parts[2]), "trajectory": parts[3]}
    if len(parts) > 4:
        values["turns"] = float(parts[4])
    if len(parts) > 5:
        values["pan_wobble"] = float(parts[5])
    import yaml

    values.update({k: yaml.safe_load(v) for k, v in extra.items()})
    out = cache / spec.replace(":", "_")
    if not (out / "groundtruth.txt").exists():
        simulate_to_folder(update_config(SimulatorConfig(), values), out)
    return out


def _short_relative_errors(gt, est, delta: float = 0.1) -> np.ndarray:
    """Angle (deg) between estimated and true rotation over every delta-s step of the estimate's time range."""
    from ti_cmax import so3

    t = np.arange(max(est.t_start, gt.t_start) + 0.1, min(est.t_end, gt.t_end) - delta, delta)
    d_est = np.swapaxes(est.at(t), 1, 2) @ est.at(t + delta)
    d_gt = np.swapaxes(gt.at(t), 1, 2) @ gt.at(t + delta)
    return np.degrees(so3.geodesic_angle(d_est, d_gt))


def bench(dataset: Path, overrides: list[str], out: Path | None = None, modes=(False, True)) -> list[dict]:
    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.io import open_dataset, read_tum
    from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude

    from .panorama import render_panorama
    from .sensor_defaults import resolve_config
    from .slam import run_slam

    ds = open_dataset(dataset)
    gt = read_tum(dataset / "groundtruth.txt")
    rows = []
    for on in modes:
        cfg = load_config(SlamConfig, None, list(overrides) + [f"loop_closure={str(on).lower()}"])
        res = run_slam(ds.iter_events(cfg.dataset.chunk_size), ds.camera, cfg)
        if out is not None:  # for plots of the error over time (the trajectory and the report of each mode)
            import json

            from ti_cmax.io import write_tum

            out.mkdir(parents=True, exist_ok=True)
            mode = "on" if on else "off"
            write_tum(out / f"trajectory_{mode}.txt", res.trajectory)
            (out / f"report_{mode}.json").write_text(json.dumps(res.report, indent=1, default=float))
        err = evaluate_rotations(gt, res.trajectory)
        short = _short_relative_errors(gt, res.trajectory)
        w, h = resolve_config(cfg, ds.camera).backend.pano_size  # the map size the run used
        pano = render_panorama(ds.iter_events(cfg.dataset.chunk_size), ds.camera, res.trajectory, w, h,
                               batch_size=cfg.backend.event_batch_size)
        n = res.report["events_processed"]
        lc = res.report["backend"].get("loop_closure", {})
        loops = res.report.get("loops", [])
        rows.append({
            "sequence": dataset.name, "loop_closure": on, "events": n,
            "abs_rmse_deg": err.abs_rmse_deg, "rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
            "step_max_deg": float(short.max()), "step_median_deg": float(np.median(short)),
            "ea_percent": event_area_percent(pano.image, cfg.backend.lambda0), "gm": gradient_magnitude(pano.image),
            "loops_applied": sum(bool(e.get("applied")) for e in loops), "loops_candidates": len(loops),
            "loops": loops, "backend_us_per_event": res.report["us_per_event"]["backend"],
            "frontend_us_per_event": res.report["us_per_event"]["frontend"],
            "loop_us_per_event": lc.get("seconds", 0.0) * 1e6 / max(n, 1), "load_1min": os.getloadavg()[0],
        })
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| sequence | loop closure | abs RMSE deg | rel RMSE deg/s | 0.1 s step err max / median deg | EA% | GM "
             "| loops applied / candidates | BE us/ev (loop part) | FE us/ev | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['sequence']} | {'on' if r['loop_closure'] else 'off'} | {r['abs_rmse_deg']:.3f} | "
            f"{r['rel_rmse_deg_per_s']:.3f} | {r['step_max_deg']:.3f} / {r['step_median_deg']:.3f} | "
            f"{r['ea_percent']:.3f} | {r['gm']:.4f} | {r['loops_applied']} / {r['loops_candidates']} | "
            f"{r['backend_us_per_event']:.2f} ({r['loop_us_per_event']:.2f}) | {r['frontend_us_per_event']:.2f} | "
            f"{r['load_1min']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", required=True, type=Path, help="folder of the simulated sequences (reused)")
    ap.add_argument("--sequences", default=",".join(DEFAULT_SEQUENCES))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="key=value")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--modes", default="off,on", help="loop closure modes to run (off, on or off,on)")
    ap.add_argument("--out", type=Path, help="write each mode's trajectory and report.json here (OUT/SEQUENCE/)")
    args = ap.parse_args(argv)
    os.environ.setdefault("TI_CMAX_THREADS", str(args.threads))
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.sequences.split(","):
        tic = time.perf_counter()
        data = _dataset(args.cache, spec)
        modes = [m == "on" for m in args.modes.split(",")]
        rows += bench(data, args.overrides, args.out / data.name if args.out else None, modes)
        print(f"{spec}: {time.perf_counter() - tic:.0f} s", file=sys.stderr)
        print(format_rows(rows), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

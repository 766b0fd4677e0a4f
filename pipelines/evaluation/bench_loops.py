"""Benchmark of loop closure (a command, not a test): CMax-SLAM with loop_closure=false and =true.

    python -m ti_cmax.pipelines.evaluation.bench_loops --cache DIR [--sequences SPEC,...] [--set key=value ...] [--threads N]
        [--modes off,on] [--level L] [--loop-slice S] [--out RUNS [--saved | --summarize] [--trace STEP]]

A SPEC is sensor:scene:duration:trajectory[:turns[:wobble]][:key=value...] (e.g. DAVIS240C:bay:12:pan:2.2:0.5, or
DAVIS240C:city:5:random for a sequence without revisits; key=value: any simulator field, e.g. seed=1,
contrast_threshold=0.4, noise_rate=0.5); the default set is declared below. Each sequence is simulated once into
DIR (reused later). One markdown table row per sequence and mode: abs / rel rotation RMSE
(ti_cmax.metrics.evaluate_rotations); the 0.1 s relative rotation errors: the largest around the start of the
revisit (the jump at the loop, ``jump_at_revisit``), the largest and the median (typical) over the sequence; event
area EA% and gradient magnitude GM of all events rendered along the trajectory (the same map size for both modes:
the loop closer's rebuilt map holds only subsamples); loops applied / accepted / candidates; back-end us per input
event with the loop closer's part, and its share of the run's front-end + back-end time; the run's process CPU
seconds with the loop closer's part and the increase over loop_closure=false (CPU time: load inflates it far less
than wall time, but it still varies by about 10 % between runs on a loaded machine). With --out, each mode's
trajectory, report.json and row are kept (RUNS/SEQUENCE/), for plots of the error over time and for --summarize
(the table of all rows there). The 1-minute load average is printed: timings are only comparable on an idle machine.
``--loop-slice S`` runs each loop verification and map rebuild in slices of at most S wall seconds before each window
(LoopCloser.slice_seconds, as the real-time replay does, here without idle time; 0: one slice per window): what the
slicing costs in accuracy, and the longest the loop closer holds the back-end in one call ("longest call").
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from ti_cmax import so3
from ti_cmax.config import SlamConfig, load_config, update_config
from ti_cmax.io import open_dataset, read_tum, write_tum
from ti_cmax.metrics import evaluate_rotations, event_area_percent, gradient_magnitude
from ti_cmax.pipelines.evaluation.bench_slam import loop_counts
from ti_cmax.pipelines.panorama import render_panorama
from ti_cmax.pipelines.realtime import LEVELS, RealtimeController
from ti_cmax.pipelines.sensor_defaults import resolve_config
from ti_cmax.pipelines.slam import OnlineSlam, run_slam
from ti_cmax.simulate import SimulatorConfig, simulate_to_folder

# Declared before any result was seen, so that no sequence was picked for how loop closure does on it. Revisits
# (2-3 turns): a DAVIS240C bay pan, other scenes and seeds, VGA, and the hard cases where drift is large: long
# pans, lower event rates (higher contrast threshold), background noise, the 128x128 DVS128. Without revisits:
# random motion and a pan that stops short of a full turn (must stay within 2 % of loop_closure=false). Cheapest
# first, the VGA pans last (at VGA's default contrast threshold the 8 s pan has 15 Mev/s, 122 M events, and
# simulates at about 0.02x real time).
REVISIT_SEQUENCES = (
    "DAVIS240C:bay:14:pan:2.2:0.3",
    "DVS128:city:12:pan:2.2:0.5",
    "DVS128:street:24:pan:3:0.3:seed=3:noise_rate=1",
    "DAVIS240C:town:20:pan:3:0.3:seed=2:contrast_threshold=0.4:noise_rate=0.5",  # loses track (abs 114 deg)
    "DAVIS240C:city:10:pan:2:0.5:seed=1",
    "VGA:bay:8:pan:2:0.5",
    # Declared before any run of them: VGA pans whose back-end can drift without loop closure (VGA:bay:8 drifts 0.04 deg
    # at the defaults: nothing to halve), still affordable to simulate. Contrast threshold 0.5 instead of VGA's 0.2:
    # ~2.5x fewer events per turn (cheaper runs, and a sparser map per window: the BA's variance noisier, as at lower
    # event rates); background noise 1 Hz per pixel (0.3 M noise events/s, as the DVS128 street pan's); 2 turns in 6 s
    # (2.1 rad/s mean, 4.2 peak: faster than the 8 s pan, so more motion per window and per spline knot; events and
    # renders per turn stay the same). Same wobble as the DAVIS240C bay pan. The city one is another scene and seed.
    "VGA:bay:6:pan:2:0.3:contrast_threshold=0.5:noise_rate=1",
    "VGA:city:6:pan:2:0.3:seed=1:contrast_threshold=0.5:noise_rate=1",
    # Declared before any run of it: the bay pan above with a third turn (same speed, 9 s). On a 2-turn pan at
    # level 4 half the poses are the first turn's, whose error the loop closer keeps (its map is the reference;
    # error_trace's "first turn's part"); with a third turn that part is a third. The pan ramps up and down, and
    # the front-end's error while nearly still, at the start and the end, is not a drift a revisit can measure.
    "VGA:bay:9:pan:3:0.3:contrast_threshold=0.5:noise_rate=1",
)
NO_REVISIT_SEQUENCES = (
    "DAVIS240C:bay:5:random",
    "DAVIS240C:city:8:pan:0.9:0.5",
    "VGA:city:2:random:seed=1",
)
DEFAULT_SEQUENCES = REVISIT_SEQUENCES + NO_REVISIT_SEQUENCES


def _dataset(cache: Path, spec: str) -> Path:
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
    t = np.arange(max(est.t_start, gt.t_start) + 0.1, min(est.t_end, gt.t_end) - delta, delta)
    d_est = np.swapaxes(est.at(t), 1, 2) @ est.at(t + delta)
    d_gt = np.swapaxes(gt.at(t), 1, 2) @ gt.at(t + delta)
    return np.degrees(so3.geodesic_angle(d_est, d_gt))


def first_revisit_time(gt, min_age: float = 3.0, radius_deg: float = 45.0) -> float | None:
    """First time the true optical axis comes back within radius_deg of where it pointed min_age s earlier or
    more (the start of a revisit; None: no revisit)."""
    t = np.arange(gt.t_start, gt.t_end, 0.05)
    z = gt.at(t)[:, :, 2]
    cos_r = np.cos(np.radians(radius_deg))
    for i in np.flatnonzero(t >= t[0] + min_age):
        if np.max(z[: int(np.searchsorted(t, t[i] - min_age, side="right"))] @ z[i]) >= cos_r:
            return float(t[i])
    return None


def jump_at_revisit(gt, est, t_revisit: float | None) -> float | None:
    """Largest 0.1 s relative rotation error (deg) from 1 s before to 2 s after the start of the revisit (the
    windows entering the old map snap to it there), None without a revisit."""
    if t_revisit is None:
        return None

    t = np.arange(max(t_revisit - 1.0, est.t_start, gt.t_start), min(t_revisit + 2.0, est.t_end - 0.1), 0.01)
    d_est = np.swapaxes(est.at(t), 1, 2) @ est.at(t + 0.1)
    d_gt = np.swapaxes(gt.at(t), 1, 2) @ gt.at(t + 0.1)
    return float(np.degrees(so3.geodesic_angle(d_est, d_gt)).max()) if len(t) else None


def error_trace(gt, est, step: float = 0.5) -> str:
    """Error over time (text lines), for where the error comes from: time, true pan angle (deg, about the vertical),
    the absolute error after the start alignment of ``evaluate_rotations`` (deg), its world-frame rotation vector
    (R_est R_gt^T, deg: x, y = yaw, z) and the error left once its mean is removed (deg): drift shows as an error
    that grows with time, a start-up offset as a constant one that the mean removes. The header also gives the
    part of the abs RMSE from the poses before the camera completed its first turn (true pan angle 360 deg from
    the start; all poses if it never does): a loop closer takes the first turn's map as the reference, so with
    no error at all after the first turn its abs RMSE would still be about that part."""
    from scipy.spatial.transform import Rotation

    err = evaluate_rotations(gt, est)
    aligned = est.aligned_to(gt, err.t0)
    t = np.arange(max(gt.t_start, est.t_start) + 0.05, min(gt.t_end, est.t_end), step)
    e = Rotation.from_matrix(aligned.at(t) @ np.swapaxes(gt.at(t), 1, 2))
    mean = e.mean()
    left = np.degrees((mean.inv() * e).magnitude())
    z = gt.at(t)[:, :, 2]
    pan = np.degrees(np.unwrap(np.arctan2(z[:, 0], z[:, 2])))
    vec = np.degrees(e.as_rotvec())
    z_abs = gt.at(err.abs_times)[:, :, 2]
    pan_abs = np.unwrap(np.arctan2(z_abs[:, 0], z_abs[:, 2]))
    first = np.abs(pan_abs - pan_abs[0]) < 2 * np.pi
    part = np.sqrt(np.sum(err.abs_errors_deg[first] ** 2) / len(first))
    lines = [f"abs RMSE {err.abs_rmse_deg:.3f} deg; mean removed {np.sqrt(np.mean(left ** 2)):.3f} deg; first turn's "
             f"part {part:.3f} deg (until {err.abs_times[first][-1]:.2f} s)",
             "    t    pan    abs     ex     ey     ez  -mean"]
    lines += [f"{t[i]:5.2f} {pan[i]:6.0f} {np.degrees(e[i].magnitude()):6.3f} {vec[i, 0]:6.3f} {vec[i, 1]:6.3f} "
              f"{vec[i, 2]:6.3f} {left[i]:6.3f}" for i in range(len(t))]
    return "\n".join(lines)


def evaluate_run(dataset: Path, overrides: list[str], on: bool, trajectory, report: dict,
                 cpu_seconds: float | None = None) -> dict:
    """One table row from a run's trajectory and report.json (the map rendered along the trajectory);
    ``cpu_seconds``: the run's process CPU time (None: unknown)."""
    ds = open_dataset(dataset)
    gt = read_tum(dataset / "groundtruth.txt")
    cfg = load_config(SlamConfig, None, list(overrides) + [f"loop_closure={str(on).lower()}"])
    err = evaluate_rotations(gt, trajectory)
    short = _short_relative_errors(gt, trajectory)
    w, h = resolve_config(cfg, ds.camera).backend.pano_size  # the map size the run used
    pano = render_panorama(ds.iter_events(cfg.dataset.chunk_size), ds.camera, trajectory, w, h,
                           batch_size=cfg.backend.event_batch_size)
    n = report["events_processed"]
    lc = report["backend"].get("loop_closure", {})
    loops = report.get("loops", [])
    applied, _accepted, candidates = loop_counts(report)
    return {
        "sequence": dataset.name, "loop_closure": on, "events": n,
        "abs_rmse_deg": err.abs_rmse_deg, "rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
        "step_max_deg": float(short.max()), "step_median_deg": float(np.median(short)),
        "ea_percent": event_area_percent(pano.image, cfg.backend.lambda0), "gm": gradient_magnitude(pano.image),
        "loops_applied": applied, "loops_candidates": candidates,
        "loops": loops, "backend_us_per_event": report["us_per_event"]["backend"],
        "frontend_us_per_event": report["us_per_event"]["frontend"],
        "loop_us_per_event": lc.get("seconds", 0.0) * 1e6 / max(n, 1), "load_1min": os.getloadavg()[0],
        "cpu_seconds": cpu_seconds, "loop_cpu_seconds": lc.get("cpu_seconds", 0.0),
        "loop_seconds_by_part": lc.get("seconds_by_part", {}),
        "loop_longest_call_cpu_seconds": lc.get("longest_call_cpu_seconds"),
        "jump_deg": jump_at_revisit(gt, trajectory, first_revisit_time(gt)),
    }


def run_at_level(dataset: Path, cfg, level: int, loop_slice: float | None = None):
    """CMax-SLAM on dataset with the real-time controller's degradation ``level`` (pipelines/realtime.LEVELS: 1 of
    k front-end packets, BA cap divided, BA on 1 of m windows; 4: BA skipped) held from the first event, offline:
    what ``--realtime`` computes on a machine that cannot keep up at that level, without the wall clock (so without
    the BA's time budget: level 1, the budget alone, computes as level 0 here).
    ``loop_slice``: loop verifications in slices (OnlineSlam's loop_slice_seconds; None: at once)."""
    ds = open_dataset(dataset)
    online = OnlineSlam(ds.camera, cfg, loop_slice_seconds=loop_slice)
    keep, _divisor, every = LEVELS[level]
    online.degrade(keep, RealtimeController(resolve_config(cfg, ds.camera), 1.0).ba_cap(level), every)
    for chunk in ds.iter_events(cfg.dataset.chunk_size):
        online.push(chunk)
    return online.close()


def bench(dataset: Path, overrides: list[str], out: Path | None = None, modes=(False, True),
          saved: bool = False, level: int = 0, loop_slice: float | None = None) -> list[dict]:
    """Rows of CMax-SLAM on dataset in each mode; with out, each mode's trajectory, report and row are written
    to out (``saved``: evaluate the trajectory and report already there instead of running). ``level``: the
    real-time degradation level held throughout (``run_at_level``; 0: the offline computation, ``run_slam``)."""
    import json

    rows = []
    for on in modes:
        mode = "on" if on else "off"
        if saved:
            traj, report = read_tum(out / f"trajectory_{mode}.txt"), json.loads((out / f"report_{mode}.json").read_text())
            cpu = None
        else:
            ds = open_dataset(dataset)
            cfg = load_config(SlamConfig, None, list(overrides) + [f"loop_closure={str(on).lower()}"])
            cpu = time.process_time()
            res = run_at_level(dataset, cfg, level, loop_slice) if level or loop_slice is not None else \
                run_slam(ds.iter_events(cfg.dataset.chunk_size), ds.camera, cfg)
            traj, report, cpu = res.trajectory, res.report, time.process_time() - cpu
            if out is not None:  # for plots of the error over time
                out.mkdir(parents=True, exist_ok=True)
                write_tum(out / f"trajectory_{mode}.txt", traj)
                (out / f"report_{mode}.json").write_text(json.dumps(report, indent=1, default=float))
        rows.append(evaluate_run(dataset, overrides, on, traj, report, cpu))
        if out is not None:
            (out / f"row_{mode}.json").write_text(json.dumps(rows[-1], indent=1, default=float))
    return rows


def format_rows(rows: list[dict]) -> str:
    """Markdown table. jump: the largest 0.1 s step error around the start of the revisit (``jump_at_revisit``),
    against the median one over the sequence (typical); loop share: the loop closer's time over the run's
    front-end + back-end time; CPU: the run's process CPU seconds (a single-threaded run's work, which load does
    not inflate as it does wall time), the loop closer's part, and the increase over the same sequence's off row."""
    lines = ["| sequence | loop closure | abs RMSE deg | rel RMSE deg/s | 0.1 s step err: jump at revisit / max / "
             "median deg | EA% | GM | loops applied / accepted / candidates | BE us/ev (loop part) | FE us/ev "
             "| loop share % | CPU s (loop part) / vs off | longest call CPU s | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    cpu_off = {r["sequence"]: r.get("cpu_seconds") for r in rows if not r["loop_closure"]}
    for r in rows:
        cpu, ref = r.get("cpu_seconds"), cpu_off.get(r["sequence"])
        cpu_text = "-" if cpu is None else f"{cpu:.1f} ({r.get('loop_cpu_seconds', 0.0):.1f})" + (
            f" / {100 * (cpu / ref - 1):+.1f} %" if r["loop_closure"] and ref else "")
        jump = "-" if r.get("jump_deg") is None else f"{r['jump_deg']:.3f}"
        total = r["backend_us_per_event"] + r["frontend_us_per_event"]
        share = 100 * r["loop_us_per_event"] / total if total > 0 else 0.0
        accepted = sum(bool(e.get("accepted")) for e in r.get("loops", []))
        longest = "-" if r.get("loop_longest_call_cpu_seconds") is None else f"{r['loop_longest_call_cpu_seconds']:.3f}"
        lines.append(
            f"| {r['sequence']} | {'on' if r['loop_closure'] else 'off'} | {r['abs_rmse_deg']:.3f} | "
            f"{r['rel_rmse_deg_per_s']:.3f} | {jump} / {r['step_max_deg']:.3f} / {r['step_median_deg']:.3f} | "
            f"{r['ea_percent']:.3f} | {r['gm']:.4f} | {r['loops_applied']} / {accepted} / {r['loops_candidates']} | "
            f"{r['backend_us_per_event']:.2f} ({r['loop_us_per_event']:.2f}) | {r['frontend_us_per_event']:.2f} | "
            f"{share:.1f} | {cpu_text} | {longest} | {r['load_1min']:.1f} |")
    return "\n".join(lines)


def summarize(out: Path) -> str:
    """The table of every row_{off,on}.json under OUT (runs of separate invocations)."""
    import json

    rows = [json.loads(p.read_text()) for p in sorted(out.glob("*/row_*.json"))]
    return format_rows(sorted(rows, key=lambda r: (r["sequence"], r["loop_closure"])))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cache", required=True, type=Path, help="folder of the simulated sequences (reused)")
    ap.add_argument("--sequences", default=",".join(DEFAULT_SEQUENCES))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="key=value")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--level", type=int, default=0, choices=range(5), help="hold the real-time controller's "
                    "degradation level (pipelines/realtime.LEVELS; 4: BA skipped, front-end poses) from the start")
    ap.add_argument("--loop-slice", type=float, default=None, metavar="S", help="loop verifications and map "
                    "rebuilds in slices of at most S wall s before each window, as in real time (0: one slice)")
    ap.add_argument("--modes", default="off,on", help="loop closure modes to run (off, on or off,on)")
    ap.add_argument("--out", type=Path, help="write each mode's trajectory and report.json here (OUT/SEQUENCE/)")
    ap.add_argument("--saved", action="store_true", help="evaluate the trajectories and reports under --out "
                    "instead of running")
    ap.add_argument("--summarize", action="store_true", help="only print the table of the runs under --out")
    ap.add_argument("--trace", type=float, default=0.0, metavar="STEP", help="with --out: also print each mode's "
                    "error over time every STEP s (error_trace) from the trajectories there")
    args = ap.parse_args(argv)
    if args.summarize:
        print(summarize(args.out))
        return 0
    os.environ.setdefault("TI_CMAX_THREADS", str(args.threads))
    args.cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.sequences.split(","):
        tic = time.perf_counter()
        data = _dataset(args.cache, spec)
        modes = [m == "on" for m in args.modes.split(",")]
        rows += bench(data, args.overrides, args.out / data.name if args.out else None, modes, args.saved,
                      args.level, args.loop_slice)
        print(f"{spec}: {time.perf_counter() - tic:.0f} s", file=sys.stderr)
        if args.trace and args.out:
            for m in args.modes.split(","):
                print(f"{data.name} loop closure {m}: " + error_trace(read_tum(data / "groundtruth.txt"),
                      read_tum(args.out / data.name / f"trajectory_{m}.txt"), args.trace), flush=True)
        print(format_rows(rows), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

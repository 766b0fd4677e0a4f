"""Minute-long recordings: ``ti-cmax slam`` on the ``long`` suite (60 s DAVIS240C pans of 3.7 turns with wobble
and sensor defects, ``suites.SUITES["long"]``), one table row per recording.

    python -m ti_cmax.pipelines.evaluation.bench_long --out DIR [--sequences A,B] [--realtime] [--threads N]
        [--set KEY=VALUE ...] [--saved]

Each recording is simulated once into DIR/sequences (the layout of ``ti-cmax benchmark``, reused when its
simulation.json matches) and run by ``ti-cmax slam`` in a child process (DIR/runs/NAME/offline; with --realtime also
``slam --realtime``, DIR/runs/NAME/realtime). Columns: abs RMSE (deg) and rel RMSE (deg/s) aligned at the start
(``evaluate_rotations``); the worst 0.2 s stretch (``metrics.worst_stretch``: the largest RMS of the start-aligned
abs error over any 0.2 s, and when); the abs error per revolution of the pan (``metrics.revolution_errors``: the
swing, the largest max - min of the quarter-turn means within one complete turn, and the mean of each turn);
loops applied / accepted / candidates (report.json "loops"); the child process's wall seconds and peak memory
(report.json peak_rss_mb, both processes); with --realtime the events used and the lag max of the real-time run.
Writes DIR/long.md and DIR/long.json. ``--saved`` evaluates the runs already in DIR instead of running. A benchmark,
not a test: about a minute of CPU per recording and run.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from ti_cmax.errors import InputError
from ti_cmax.io import read_tum
from ti_cmax.metrics import evaluate_rotations, revolution_errors, worst_stretch
from ti_cmax.pipelines.evaluation.bench_sensors import _f, _run_slam
from ti_cmax.pipelines.evaluation.bench_slam import loop_counts
from ti_cmax.pipelines.evaluation.methods import BenchmarkSettings, ensure_sequence
from ti_cmax.pipelines.evaluation.suites import SUITES

SUITE = "long"


def score_run(groundtruth, trajectory, report: dict) -> dict:
    """The accuracy columns of one run: abs / rel RMSE, the worst 0.2 s stretch and the error per revolution
    (start-aligned), and the loop closer's counts."""
    err = evaluate_rotations(groundtruth, trajectory)
    worst, worst_at = worst_stretch(err.abs_times, err.abs_errors_deg)
    turns = revolution_errors(groundtruth, err.abs_times, err.abs_errors_deg)
    applied, accepted, candidates = loop_counts(report)
    return {"abs_rmse_deg": err.abs_rmse_deg, "rel_rmse_deg_per_s": err.rel_rmse_deg_per_s,
            "worst_stretch_deg": worst, "worst_stretch_at_s": worst_at, "revolutions": turns.to_dict(),
            "loops_applied": applied, "loops_accepted": accepted, "loops_candidates": candidates,
            "status": report.get("status")}


def evaluate_case(spec, root: Path, realtime: bool = False, threads: int | None = None, overrides=(),
                  saved: bool = False, log=print) -> dict:
    """One recording: simulated if needed, run offline (and in real time) unless ``saved``, scored."""
    seq, info, sim_s = ensure_sequence(spec, BenchmarkSettings(), root / "sequences")
    if sim_s:
        log(f"{spec.name}: simulated in {sim_s:.0f} s")
    gt = read_tum(seq / "groundtruth.txt")
    row = {"sequence": spec.name, "scene": spec.scene, "events": int(info["num_events"]),
           "event_rate_mev_s": info["event_rate"] / 1e6, "duration_s": float(info["duration"])}
    for mode, flags in (("offline", ()), ("realtime", ("--realtime",)))[: 2 if realtime else 1]:
        out = root / "runs" / spec.name / mode
        if not saved:
            if out.exists():
                shutil.rmtree(out)
            load = os.getloadavg()[0]
            wall = _run_slam(seq, out, threads, list(overrides), flags)
            (root / "runs" / spec.name / f"{mode}.json").write_text(json.dumps(
                {"process_wall_seconds": wall, "load_1min": [load, os.getloadavg()[0]]}))
        if not (out / "report.json").is_file():
            raise InputError(f"--saved: no run in {out}")
        report = json.loads((out / "report.json").read_text())
        proc_path = root / "runs" / spec.name / f"{mode}.json"
        proc = json.loads(proc_path.read_text()) if proc_path.is_file() else {}
        res = {**score_run(gt, read_tum(out / "trajectory.txt"), report),
               "process_wall_seconds": proc.get("process_wall_seconds"), "load_1min": proc.get("load_1min"),
               "peak_rss_mb": report.get("peak_rss_mb")}
        if mode == "realtime":
            rt = report.get("realtime", {})
            res.update(events_used_fraction=rt.get("events_used_fraction"), max_lag_s=rt.get("max_lag_s"))
        row[mode] = res
        log(f"{spec.name} {mode}: abs {res['abs_rmse_deg']:.3f} deg, worst 0.2 s {res['worst_stretch_deg']:.3f} deg")
    return row


def _turns(rev: dict) -> str:
    return " / ".join(_f(v, 3) for v in rev["means_deg"])


def format_table(rows: list[dict]) -> str:
    """Markdown table, one line per recording and run."""
    lines = ["| recording | run | Mev/s | abs deg | rel deg/s | worst 0.2 s deg (at s) | swing in a turn deg | "
             "mean per turn deg | loops applied / accepted / candidates | events used | lag max s | wall s | "
             "peak MB | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for mode in ("offline", "realtime"):
            m = r.get(mode)
            if m is None:
                continue
            rev = m["revolutions"]
            load = "-".join(_f(v, 1) for v in m["load_1min"]) if m.get("load_1min") else "-"
            lines.append(" | ".join([
                f"| {r['sequence']}", mode, _f(r["event_rate_mev_s"], 2), _f(m["abs_rmse_deg"], 3),
                _f(m["rel_rmse_deg_per_s"], 3), f"{_f(m['worst_stretch_deg'], 3)} ({_f(m['worst_stretch_at_s'], 1)})",
                _f(rev["swing_deg"], 3), _turns(rev),
                f"{m['loops_applied']} / {m['loops_accepted']} / {m['loops_candidates']}",
                _f(m.get("events_used_fraction"), 3), _f(m.get("max_lag_s"), 2), _f(m["process_wall_seconds"], 1),
                _f(m["peak_rss_mb"], 0), load]) + " |")
    lines += ["", "abs / rel: rotation RMSE aligned at start + 0.1 s; worst 0.2 s: the largest RMS of that abs error "
              "over any 0.2 s window (and its start); swing in a turn: the largest max - min of the abs error's "
              "quarter-turn means within one complete turn of the pan; mean per turn: the abs error's mean over each "
              "turn (the last one partial); loops: report.json loops applied / accepted / candidates; events used, "
              "lag max: the real-time run's; wall s: the slam process's; peak MB: both processes' peak RSS; load: "
              "1-minute load average before-after the run (timings are only comparable on an idle machine)."]
    return "\n".join(lines)


def run(out: Path, names: list[str] | None = None, realtime: bool = False, threads: int | None = None,
        overrides=(), saved: bool = False, log=print) -> str:
    suite = SUITES[SUITE]
    unknown = [n for n in names or [] if n not in suite]
    if unknown:
        raise InputError(f"--sequences: unknown {', '.join(unknown)} (expected some of {', '.join(suite)})")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in names or list(suite):
        rows.append(evaluate_case(suite[name], out, realtime, threads, overrides, saved, log))
        (out / "long.json").write_text(json.dumps(rows, indent=1, default=float))
    table = format_table(rows)
    (out / "long.md").write_text(table + "\n")
    return table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ti_cmax.pipelines.evaluation.bench_long", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path, metavar="DIR", help="sequences, runs and the table go here")
    ap.add_argument("--sequences", default="", help=f"comma-separated subset of {','.join(SUITES[SUITE])}")
    ap.add_argument("--realtime", action="store_true", help="also run slam --realtime: events used, lag max")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="slam override for every run")
    ap.add_argument("--saved", action="store_true", help="evaluate the runs already in DIR instead of running")
    args = ap.parse_args(argv)
    names = [s.strip() for s in args.sequences.split(",") if s.strip()]
    try:
        print(run(args.out, names, args.realtime, args.threads, args.overrides, args.saved,
                  log=lambda msg: print(msg, file=sys.stderr, flush=True)))
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

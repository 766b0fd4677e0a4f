"""Whole-process benchmark: what a user waits for from typing ``ti-cmax slam`` to its exit, stage by stage.

    python -m ti_cmax.pipelines.evaluation.bench_process --out DIR [--rounds 5] [--threads N] [--sequential]

The case is a simulated DAVIS240C sequence of 3 s and about 2.9 M events (city, steady random motion; simulated
once into DIR/sequences, reused when simulation.json matches) run as the C++ reference was measured: linear spline,
15 000-event packets (``--spline linear --set num_events_per_packet=15000``), otherwise the command's defaults (a
back-end worker process on 2+ cores). Each round runs ``ti-cmax slam`` in a child process, after one warm-up run
that is not counted (it fills Taichi's offline cache after a code change). Per run: the wall time from launch to
exit, the CPU seconds of the process, its worker and its figure process (rusage of the children; the figure
process draws run.png and map.png, ti_cmax/figure_process.py), and the stages lined up from
report.json's ``timeline_seconds`` (ti_cmax/timeline.py) with the launch:

- start-up: the interpreter, the command line, the pipeline's imports, then the dataset, the worker's start and
  the kernels' preparation (Taichi's init, and kernels loaded from the offline cache) up to the first event;
- events: the front-end over the stream while the worker runs the back-end beside it (``steady`` gives the two
  ends' steady-state seconds from the report's us per event); then the wait for the back-end's last windows;
- outputs: map, run.png, trajectory, config, then the report and the process's exit.

The worker's own points (started, kernels ready, done) are given against the launch too. The table shows the median
of the rounds per stage (wall, CPU of the main process, CPU of the worker) with the accuracy (abs / rel RMSE against
ground truth, the same every round at ``--threads 1``) and the 1-minute load average before and after: a machine
shared with other jobs makes the wall times pessimistic (compare CPU seconds there). Writes DIR/process.md and
DIR/process.json. A benchmark, not a test: about 10 s per round.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from ti_cmax.io import read_tum
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.pipelines.evaluation.methods import BenchmarkSettings, ensure_sequence
from ti_cmax.pipelines.evaluation.suites import SequenceSpec

# 2.92 M events over 3 s (0.97 M ev/s): the realtime suite's 1 M ev/s motion (davis240c-1m), 3 s long
CASE = SequenceSpec("davis240c-3s", "DAVIS240C", "city", 3.0, 21,
                    options=(("max_angular_velocity", 1.43), ("random_ramp_start", 1.0)))
SLAM_ARGS = ("--spline", "linear", "--set", "num_events_per_packet=15000")

# (label, from point, to point) of the main process; "launch" and "exit" are the parent's
STAGES = (
    ("interpreter, command line", "launch", "command"),
    ("imports", "command", "imported"),
    ("dataset, worker start, kernel preparation", "imported", "ready"),
    ("events (front-end; back-end beside it)", "ready", "frontend_done"),
    ("waiting for the back-end's last windows", "frontend_done", "closed"),
    ("outputs (map, run.png, trajectory, config)", "closed", "outputs"),
    ("report, exit", "outputs", "exit"),
)
WORKER_POINTS = ("started", "ready", "done")


def run_once(seq: Path, out: Path, threads: int | None, flags: tuple = (), overrides: tuple = (),
             python: str | None = None) -> dict:
    """One ``ti-cmax slam`` in a child process (run by ``python``, default this interpreter): its report, wall
    seconds, CPU seconds (with its worker) and the stages (wall and CPU seconds per STAGES row, the worker's points
    against the launch; none from a version without report.json's timeline)."""
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [python or sys.executable, "-m", "ti_cmax.cli", "slam", str(seq), "--out", str(out), "--quiet",
           *SLAM_ARGS, *flags]
    if threads:
        cmd += ["--threads", str(threads)]
    for item in overrides:
        cmd += ["--set", item]
    load = [os.getloadavg()[0]]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    launch = time.time()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=out.parent)  # no checkout in the cwd
    end = time.time()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    load.append(os.getloadavg()[0])
    if proc.returncode != 0:
        raise RuntimeError(f"slam failed: {proc.stderr.strip().splitlines()[-1:]}")
    report = json.loads((out / "report.json").read_text())
    points = {"launch": [launch, 0.0], **report.get("timeline_seconds", {})}
    total_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    worker = report.get("backend_process", {})
    worker_cpu = worker.get("process_cpu_seconds", 0.0)
    figures_cpu = report.get("figure_process", {}).get("cpu_seconds", 0.0)
    # the main process's CPU: the children's less the worker's and the figure process's
    points["exit"] = [end, total_cpu - worker_cpu - figures_cpu]
    stages = {label: {"wall": points[b][0] - points[a][0], "cpu": points[b][1] - points[a][1]}
              for label, a, b in STAGES if a in points and b in points}
    wpoints = {k: v for k, v in worker.get("timeline_seconds", {}).items() if k in WORKER_POINTS}
    return {"report": report, "wall": end - launch, "cpu": total_cpu, "worker_cpu": worker_cpu,
            "figures_cpu": figures_cpu, "stages": stages,
            "worker": {k: {"at": v[0] - launch, "cpu": v[1]} for k, v in wpoints.items()}, "load": load}


def summarize(runs: list[dict], events: int) -> dict:
    """Medians over the rounds of the whole process's figures, per stage and per worker point."""
    med = statistics.median
    reports = [r["report"] for r in runs]
    us = {k: med(rep["us_per_event"][k] for rep in reports) for k in ("frontend", "backend")}
    return {
        "wall": med(r["wall"] for r in runs), "cpu": med(r["cpu"] for r in runs),
        "worker_cpu": med(r["worker_cpu"] for r in runs),
        "figures_cpu": med(r.get("figures_cpu", 0.0) for r in runs),
        "stages": {label: {k: med(r["stages"][label][k] for r in runs) for k in ("wall", "cpu")}
                   for label, _, _ in STAGES if all(label in r["stages"] for r in runs)},
        "worker": {p: {k: med(r["worker"][p][k] for r in runs) for k in ("at", "cpu")}
                   for p in WORKER_POINTS if all(p in r["worker"] for r in runs)},
        "steady": {k: v * 1e-6 * events for k, v in us.items()},
        "compile": {"main": med(rep["compile_seconds"] for rep in reports),
                    "worker": med(rep.get("backend_process", {}).get("compile_seconds", 0.0) for rep in reports)},
        "start_method": reports[0].get("backend_process", {}).get("start_method"),
        "load": [min(r["load"][0] for r in runs), max(r["load"][1] for r in runs)],
    }


def format_table(s: dict, runs: list[dict], accuracy, events: int) -> str:
    lines = ["| stage | wall s | CPU s (main) |", "|---|---|---|"]
    lines += [f"| {label} | {v['wall']:.2f} | {v['cpu']:.2f} |" for label, v in s["stages"].items()]
    helpers = [f"{name} {s[key]:.2f}" for name, key in (("worker", "worker_cpu"), ("figure process", "figures_cpu"))
               if s.get(key)]
    main = s["cpu"] - s["worker_cpu"] - s.get("figures_cpu", 0.0)
    cpu = f"{main:.2f} (+ {', '.join(helpers)})" if helpers else f"{main:.2f} (with its worker, if any)"
    lines.append(f"| **whole process** | **{s['wall']:.2f}** | {cpu} |")
    if s["worker"]:
        lines += ["", "| back-end worker (" + (s["start_method"] or "-") + ") | at s (from launch) | its CPU s |",
                  "|---|---|---|"]
        labels = {"started": "started (imports done)", "ready": "kernels ready", "done": "last window done"}
        lines += [f"| {labels[p]} | {v['at']:.2f} | {v['cpu']:.2f} |" for p, v in s["worker"].items()]
    walls = ", ".join(f"{r['wall']:.2f}" for r in runs)
    lines += ["", f"{events / 1e6:.2f} M events; medians of {len(runs)} rounds (wall s per round: {walls}); "
              f"CPU of the main process and its helpers together {s['cpu']:.2f} s. Steady state (us per event x "
              f"events): front-end {s['steady']['frontend']:.2f} s, back-end {s['steady']['backend']:.2f} s; "
              f"kernel preparation (wall) main {s['compile']['main']:.2f} s, worker {s['compile']['worker']:.2f} s. "
              f"CMax-SLAM abs {accuracy.abs_rmse_deg:.3f} deg, rel {accuracy.rel_rmse_deg_per_s:.3f} deg/s. "
              f"1-minute load average {s['load'][0]:.1f}-{s['load'][1]:.1f}."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ti_cmax.pipelines.evaluation.bench_process", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, metavar="DIR", help="the sequence, the runs and the table go here")
    ap.add_argument("--rounds", type=int, default=5, help="counted runs (default 5), after one warm-up run")
    ap.add_argument("--threads", type=int, default=None, help="--threads of each run (default: the command's)")
    ap.add_argument("--sequential", action="store_true", help="front-end and back-end in one process")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a further slam override")
    ap.add_argument("--python", default=None, metavar="PATH",
                    help="the interpreter that runs ti-cmax (default this one; another checkout's venv to compare)")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")

    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    seq, info, _ = ensure_sequence(CASE, BenchmarkSettings(), root / "sequences")
    events = int(info["num_events"])
    flags = ("--sequential",) if args.sequential else ()
    run_once(seq, root / "runs" / "warm-up", args.threads, flags, tuple(args.overrides), args.python)
    runs = []
    for i in range(args.rounds):
        runs.append(run_once(seq, root / "runs" / f"round{i + 1}", args.threads, flags, tuple(args.overrides),
                             args.python))
        print(f"round {i + 1}: {runs[-1]['wall']:.2f} s wall, {runs[-1]['cpu']:.2f} s CPU, "
              f"load {runs[-1]['load'][1]:.1f}", file=sys.stderr, flush=True)
    accuracy = evaluate_rotations(read_tum(seq / "groundtruth.txt"),
                                  read_tum(root / "runs" / f"round{args.rounds}" / "trajectory.txt"))
    summary = summarize(runs, events)
    table = format_table(summary, runs, accuracy, events)
    (root / "process.json").write_text(json.dumps(
        {"case": CASE.name, "events": events, "summary": summary, "abs_deg": accuracy.abs_rmse_deg,
         "rel_deg_s": accuracy.rel_rmse_deg_per_s,
         "runs": [{k: v for k, v in r.items() if k != "report"} for r in runs]}, indent=2))
    (root / "process.md").write_text(table + "\n")
    print(table)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

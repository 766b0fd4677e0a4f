"""SHA-256 digests of every output file of a fixed set of ``ti-cmax`` runs, to show that a change of the code's
structure leaves the outputs bitwise the same.

The script drives only the ``ti-cmax`` command line (through subprocess), so the same script runs before and after
modules move. At ``--threads 1`` it simulates two short sequences with fixed seeds (a DAVIS240C city scene, 1 s,
and a star field, 1 s), then runs on them: slam linear, slam cubic, slam cubic with the back-end in a worker process,
the front-end, refine of the front-end's trajectory, every baseline (smt-ekf, smt-pf, rtpt, cmax-gae, imu) and star
tracking. It writes one line per file, ``run/relative_path  sha256``, sorted.

Files are digested as raw bytes, except JSON files (report.json, simulation.json): those hold timings, memory and
paths, which change from run to run, so they are loaded, stripped of every key whose name has a word of
``VOLATILE_WORDS`` (at any depth) and digested as a canonical dump. The simulated sequences are digested too (the
events file included), so a change of the simulator shows as such rather than as a change of every run.

    python examples/output_digests.py --work /tmp/digests --out before.txt
    python examples/output_digests.py --work /tmp/digests --out after.txt --compare before.txt

``--compare OLD`` prints the lines that differ from OLD and exits with 1 if any do. A run takes a few minutes; the
SMT baselines dominate it, more so when their kernels are not in the compile cache yet.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

# words of a JSON key naming a figure that varies between identical runs: durations (``*_seconds``, ``us_per_*``),
# memory (``peak_rss_mb``), paths, versions, dates. The few parameters they also catch are in config.yaml, raw.
VOLATILE_WORDS = {"seconds", "us", "rss", "path", "version", "date"}
COMMON = ["--threads", "1", "--quiet"]
SEQUENCES = {  # name: ti-cmax simulate arguments
    "city": ["--scene", "city", "--sensor", "DAVIS240C", "--duration", "1", "--seed", "1"],
    "stars": ["--scene", "stars", "--sensor", "DAVIS240C", "--duration", "1", "--seed", "1",
              "--max-angular-velocity", "1"],
}
BASELINES = ("smt-ekf", "smt-pf", "rtpt", "cmax-gae", "imu")


def runs(seq: Path, out: Path) -> dict[str, list[str]]:
    """Run name -> ti-cmax arguments, in order (refine reads the front-end's trajectory)."""
    city, stars = str(seq / "city"), str(seq / "stars")
    table = {
        "slam_linear": ["slam", city, "--spline", "linear", "--sequential"],
        "slam_cubic": ["slam", city, "--spline", "cubic", "--sequential"],
        "slam_cubic_parallel": ["slam", city, "--spline", "cubic", "--parallel"],
        "frontend": ["frontend", city],
        "refine": ["refine", city, "--trajectory", str(out / "frontend" / "trajectory.txt")],
        **{f"baseline_{name}": ["baseline", name, city] for name in BASELINES},
        "star_tracking": ["star-tracking", stars],
    }
    return {name: args + ["--out", str(out / name)] for name, args in table.items()}


def stable(obj):
    """``obj`` without the keys named in VOLATILE_WORDS, at any depth."""
    if isinstance(obj, dict):
        return {k: stable(v) for k, v in obj.items() if not VOLATILE_WORDS & set(k.lower().split("_"))}
    if isinstance(obj, list):
        return [stable(v) for v in obj]
    return obj


def digest(path: Path) -> str:
    if path.suffix == ".json":
        data = json.dumps(stable(json.loads(path.read_text())), sort_keys=True, separators=(",", ":")).encode()
    else:
        data = path.read_bytes()
    return hashlib.sha256(data).hexdigest()


def digest_folder(name: str, folder: Path) -> list[str]:
    return [f"{name}/{p.relative_to(folder).as_posix()}  {digest(p)}" for p in folder.rglob("*") if p.is_file()]


def ti_cmax(cli: list[str], args: list[str]) -> None:
    t = time.perf_counter()
    subprocess.run(cli + args + COMMON, check=True, stdout=subprocess.DEVNULL)
    print(f"{time.perf_counter() - t:6.1f} s  ti-cmax {' '.join(args)}", file=sys.stderr, flush=True)


def record(work: Path, cli: list[str]) -> list[str]:
    """Simulate the sequences and run every run afresh under ``work``; the sorted digest lines."""
    seq, out = work / "sequences", work / "runs"
    shutil.rmtree(seq, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    lines = []
    for name, args in SEQUENCES.items():
        ti_cmax(cli, ["simulate", str(seq / name)] + args)
        lines += digest_folder(f"sequence_{name}", seq / name)
    for name, args in runs(seq, out).items():
        ti_cmax(cli, args)
        lines += digest_folder(name, out / name)
    return sorted(lines)


def compare(old: list[str], new: list[str]) -> list[str]:
    """Human-readable differences between two digest listings (changed, missing and new files)."""
    before, after = (dict(line.split("  ", 1) for line in lines) for lines in (old, new))
    return ([f"changed {f}" for f in sorted(before.keys() & after.keys()) if before[f] != after[f]]
            + [f"missing {f}" for f in sorted(before.keys() - after.keys())]
            + [f"new     {f}" for f in sorted(after.keys() - before.keys())])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, type=Path, help="folder for the sequences and the runs' outputs")
    ap.add_argument("--out", required=True, type=Path, help="file to write the digest lines to")
    ap.add_argument("--compare", type=Path, metavar="OLD_FILE", help="digest file to compare against")
    ap.add_argument("--ti-cmax", dest="cli", default=None,
                    help="ti-cmax executable (default: the one beside this Python, else on PATH)")
    args = ap.parse_args()
    beside = Path(sys.executable).with_name("ti-cmax")
    cli = [args.cli or (str(beside) if beside.exists() else shutil.which("ti-cmax") or "ti-cmax")]

    t = time.perf_counter()
    lines = record(args.work, cli)
    args.out.write_text("".join(line + "\n" for line in lines))
    print("\n".join(lines))
    print(f"{len(lines)} files in {time.perf_counter() - t:.0f} s -> {args.out}", file=sys.stderr)
    if args.compare is None:
        return 0
    differences = compare(args.compare.read_text().splitlines(), lines)
    print("\n".join(differences) or f"identical to {args.compare}")
    return 1 if differences else 0


if __name__ == "__main__":
    sys.exit(main())

"""Reader/writer throughput benchmark: ``python -m ti_cmax.io.bench [--events 6000000] [--dir DIR]``.

Generates a random DAVIS240C-like recording, writes it as ECD text and HDF5, then reads both through
``open_dataset(...).iter_events()`` (validation included) and prints M events/s (wall and CPU time; on a
busy machine the CPU figure is the fairer one, and with 2 parser threads wall can beat CPU).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..events import Events
from .dataset import open_dataset
from .events_txt import EventsTxtWriter
from .h5 import EventsH5Writer
from .calib import write_calib_txt


def _timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=6_000_000)
    ap.add_argument("--dir", type=Path, default=None, help="work folder (default: a temporary one)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        d = args.dir or Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        n = args.events
        rng = np.random.default_rng(0)
        cam = Camera(240, 180, 199.1, 198.8, 132.2, 110.7, (-0.37, 0.15, 0.0, 0.0, 0.0))
        write_calib_txt(d / "calib.txt", cam)
        rows = []
        with EventsTxtWriter(d / "events.txt") as wt, EventsH5Writer(d / "events_h5.h5", camera=cam) as wh:
            t0, wall_txt, wall_h5 = 43.0, 0.0, 0.0
            for i in range(0, n, 1_000_000):
                m = min(1_000_000, n - i)
                t = t0 + np.cumsum(rng.exponential(1e-6, m))
                t0 = float(t[-1])
                ev = Events(t, rng.integers(0, 240, m), rng.integers(0, 180, m), rng.integers(0, 2, m))
                _, w, _ = _timed(lambda: wt.append(ev))
                wall_txt += w
                _, w, _ = _timed(lambda: wh.append(ev))
                wall_h5 += w
        rows.append(("write txt", n / wall_txt / 1e6, float("nan")))
        rows.append(("write h5", n / wall_h5 / 1e6, float("nan")))
        for label, path in (("read txt", d), ("read h5", d / "events_h5.h5")):
            ds = open_dataset(path)
            cnt, wall, cpu = _timed(lambda: sum(len(c) for c in ds.iter_events()))
            assert cnt == n
            rows.append((label, n / wall / 1e6, n / cpu / 1e6))
        size_mb = (d / "events.txt").stat().st_size / 1e6
    print(f"{n} events, events.txt {size_mb:.0f} MB")
    print(f"{'':12s} {'M ev/s wall':>12s} {'M ev/s CPU':>12s}")
    for label, wall, cpu in rows:
        print(f"{label:12s} {wall:12.2f} {cpu:12.2f}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""``ti-cmax convert INPUT OUT.h5``: any supported events input to our HDF5 layout (or ECD text for OUT.txt).

Streams in chunks (memory bounded), validates every chunk, writes to a temporary file beside OUT and
renames it at the end: on any error no output file is left. Sensor size and, when known, the intrinsics
are stored as HDF5 attributes, so the result opens on its own.
"""
from __future__ import annotations

import argparse

from . import add_sensor_arguments, dataset_config

HELP = "convert events (ECD txt, HDF5, ROS1 bag, AEDAT4, Prophesee RAW) to HDF5 events/{t,x,y,p} (or ECD text for .txt)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", help="ECD-layout folder or events file (.txt .h5 .bag .aedat4 .raw)")
    parser.add_argument("output", metavar="OUT.h5", help="output file (.h5/.hdf5; .txt writes ECD text)")
    parser.add_argument("--t-start", type=float, default=None, metavar="S", help="keep events with t >= S")
    parser.add_argument("--t-end", type=float, default=None, metavar="S", help="keep events with t < S")
    parser.add_argument("--compression", choices=["none", "gzip", "lzf"], default="none",
                        help="HDF5 compression filter (default none: fastest to read)")
    add_sensor_arguments(parser)


def run(args) -> int:
    import sys
    from pathlib import Path

    from ..errors import InputError
    from ..io.dataset import open_dataset_from_config
    from ..io.events_txt import EventsTxtWriter
    from ..io.h5 import EventsH5Writer
    from ..outputs import atomic_path, check_output_file
    from ..progress import progress

    cfg = dataset_config(args)
    out = Path(args.output)
    suffix = out.suffix.lower()
    if suffix not in (".h5", ".hdf5", ".txt"):
        raise InputError("output must end in .h5, .hdf5 or .txt", source=str(out))
    check_output_file(out)
    ds = open_dataset_from_config(args.input, cfg)
    if out.exists() and out.resolve() == Path(ds.events_path).resolve():
        raise InputError("output would overwrite the input", source=str(out))
    camera = ds.camera if ds.calibration_source is not None else None
    try:
        total = ds.num_events()
    except InputError:
        total = None
    n = 0
    with atomic_path(out) as tmp:
        if suffix == ".txt":
            writer = EventsTxtWriter(tmp)
        else:
            writer = EventsH5Writer(tmp, camera=camera, width=ds.width, height=ds.height,
                                    compression=None if args.compression == "none" else args.compression)
        with writer, progress(total, desc="convert", unit="ev") as bar:
            for chunk in ds.iter_events(cfg.chunk_size, args.t_start, args.t_end):
                writer.append(chunk)
                n += len(chunk)
                bar.update(len(chunk))
        if n == 0:
            raise InputError("no events in the requested time range", source=str(ds.events_path))
    print(f"wrote {n:,} events ({ds.width} x {ds.height}) to {out}", file=sys.stderr)
    return 0

"""``ti-cmax grayscale``: grayscale panorama from events and a trajectory (SMT mapping module + Poisson).

Writes PANO.png (8-bit, log intensity between its 1st and 99th percentiles over the observed area; black where the
camera never looked), PANO.npy (float32 log intensity, NaN outside the solved box) and PANO.json (runtime per
stage, visited fraction, EKF counts, parameters). With ``--sizes`` the events are streamed once into one map per
size and every size gets PANO_<W>x<H>.png / .npy; PANO.json lists all sizes.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..config import DatasetConfig, GrayscaleConfig

HELP = "reconstruct a grayscale panorama from events and a trajectory (EKF gradient map + Poisson)"


@dataclass(frozen=True)
class GrayscaleCommandConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    grayscale: GrayscaleConfig = field(default_factory=GrayscaleConfig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder or events file")
    parser.add_argument("--trajectory", required=True, metavar="TRAJ.txt", help="trajectory (TUM)")
    parser.add_argument("--out", required=True, metavar="PANO.png", help="output image (.npy and .json beside it)")
    parser.add_argument("--size", default=None, metavar="WxH", help="map size (default: 2*pano_height x pano_height)")
    parser.add_argument("--sizes", default=None, metavar="WxH,WxH,...",
                        help="several map sizes from one pass over the events: PANO_<W>x<H>.png per size")
    parser.add_argument("--contrast", type=float, default=None,
                        help="contrast threshold C (default: the simulator's if known, else 0.22)")
    parser.add_argument("--t-start", type=float, default=None, help="first event time to use (s)")
    parser.add_argument("--t-end", type=float, default=None, help="last event time to use (s)")
    from . import add_map_arguments

    add_map_arguments(parser)


def run(args) -> int:
    import imageio.v3 as iio
    import numpy as np

    from ..config import config_to_dict, load_config, parse_map_size, parse_map_sizes
    from ..errors import InputError
    from ..io import open_dataset_from_config, read_tum
    from ..outputs import atomic_files, check_output_file
    from ti_cmax.pipelines.workflows.grayscale import reconstruct_panoramas, resolve_contrast
    from ..pipelines.panorama import map_image
    from ..status import apply_status, status_text
    from .map import events_range

    wall = time.perf_counter()
    cfg = load_config(GrayscaleCommandConfig, args.config, args.overrides)
    gcfg = cfg.grayscale
    if args.size and args.sizes:
        raise InputError("give either --size or --sizes, not both")
    multi = bool(args.sizes)
    sizes = list(dict.fromkeys(parse_map_sizes(args.sizes, "--sizes", GrayscaleConfig))) if multi else \
        [parse_map_size(args.size, "--size", GrayscaleConfig) if args.size else gcfg.pano_size]
    if args.contrast is not None and not args.contrast > 0:
        raise InputError(f"--contrast must be positive, got {args.contrast}")
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise InputError("--out must name a .png file", source=str(out))
    check_output_file(out)
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    trajectory = read_tum(args.trajectory)
    contrast = args.contrast if args.contrast is not None else resolve_contrast(gcfg, args.dataset)
    results = reconstruct_panoramas(dataset.iter_events(cfg.dataset.chunk_size), dataset.camera, trajectory, sizes,
                                    gcfg, contrast, args.t_start, args.t_end)
    if results[0].stats["events"] == 0:
        raise InputError("no events within the trajectory's time range", source=str(args.dataset))

    entries, files = [], []
    for (w, h), res in zip(sizes, results):
        start = time.perf_counter()
        img, shown = map_image(res.to_uint8(gcfg.display_percentile_low, gcfg.display_percentile_high),
                               full_sphere=args.full_sphere, intensity=True)
        res.timings["image"] = time.perf_counter() - start
        stem = out.with_name(f"{out.stem}_{w}x{h}") if multi else out.with_suffix("")
        files.append((stem, img, res.log_intensity))
        entry = res.summary()
        entry["seconds"]["total"] = float(sum(v for k, v in res.timings.items() if k != "compile"))
        entry["png"] = str(stem.with_suffix(".png"))
        entry["png_shows"] = shown
        entries.append(entry)
    report = {
        "maps": entries,
        "contrast_threshold": contrast,
        "events": int(results[0].stats["events"]),
        "unobserved_pixels": "black",
        "wall_seconds": time.perf_counter() - wall,
        "parameters": config_to_dict(cfg),
    }
    apply_status(report, events_range=events_range(dataset, args),
                 trajectory_range=(trajectory.t_start, trajectory.t_end))
    targets = [stem.with_suffix(ext) for stem, _, _ in files for ext in (".png", ".npy")] + [out.with_suffix(".json")]
    with atomic_files(*targets) as tmps:  # every map and the report, or none of them
        for (_, img, log_i), png, npy in zip(files, tmps[0::2], tmps[1::2]):
            iio.imwrite(png, img, extension=".png")
            with open(npy, "wb") as fh:
                np.save(fh, log_i)
        tmps[-1].write_text(json.dumps(report, indent=2))
    for e in entries:
        s = e["seconds"]
        print(f"grayscale {e['width']}x{e['height']}: visited {100 * e['visited_fraction']:.2f} %, "
              f"EKF {s['ekf']:.3f} s, Poisson {s['poisson']:.3f} s, total {s['total']:.3f} s -> {e['png']}")
    if report["reasons"]:
        print(f"grayscale{status_text(report)}")
    print(json.dumps({"maps": [{k: e[k] for k in ("width", "height", "visited_fraction", "seconds")} for e in entries],
                      "events": report["events"]}))
    return 0

"""``ti-cmax super-resolution``: CMax-SLAM at several map sizes (paper Sec. IV-G1, Fig. 15, 16)."""
from __future__ import annotations

import argparse

HELP = ("CMax-SLAM at several panoramic map sizes: map_WxH.png per size, runtime per event per size "
        "(runtime.txt, runtime.png) and map quality in report.json")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (ECD layout, star form) or events file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--sizes", default="512x256,1024x512,2048x1024,4096x2048,8192x4096", metavar="WxH,...",
                        help="map sizes (width = 2 x height), default 512x256 to 8192x4096")
    parser.add_argument("--spline", choices=("linear", "cubic"), default=None,
                        help="trajectory model (default: spline_degree of the config, linear)")
    parser.add_argument("--no-render", action="store_true",
                        help="save the back-end's own global map instead of re-rendering the IWE of the trajectory")
    from . import add_map_arguments

    add_map_arguments(parser)


def plot_runtime(path, rows: list[dict]) -> None:
    """Back-end (and front-end) us/event vs map size, log scale (Fig. 16a)."""
    from ..plots import _figure, _save

    fig = _figure(6.5, 4)
    ax = fig.subplots()
    x = list(range(len(rows)))
    ax.plot(x, [r["us_per_event_backend"] for r in rows], "o-", label="back-end (BA)")
    ax.plot(x, [r["us_per_event_frontend"] for r in rows], "s--", label="front-end")
    ax.set_xticks(x, [r["size"] for r in rows], rotation=20)
    ax.set_yscale("log")
    ax.set_ylabel("runtime [us / event]")
    ax.set_xlabel("map size [px]")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    _save(fig, path)


def run(args) -> int:
    import imageio.v3 as iio
    import numpy as np

    from ..config import SlamConfig, load_config, save_config
    from ..io import write_tum
    from ..outputs import OutputDir, write_report
    from ..pipelines.panorama import map_image
    from ti_cmax.pipelines.workflows.star_tracking import open_star_or_dataset
    from ti_cmax.pipelines.workflows.super_resolution import (iter_super_resolution, parse_sizes, quality_availability,
                                              runtime_table)
    from .slam import spline_override

    sizes = parse_sizes(args.sizes)
    cfg = load_config(SlamConfig, args.config, list(args.overrides) + spline_override(args))
    dataset = open_star_or_dataset(args.dataset, cfg.dataset)
    camera = dataset.camera
    t0, t1 = dataset.time_range()
    gt = dataset.groundtruth

    def source():
        return dataset.iter_events(cfg.dataset.chunk_size)

    rows = []
    with OutputDir(args.out) as out:
        for r in iter_super_resolution(source, camera, sizes, cfg, groundtruth=gt, render=not args.no_render,
                                       progress_total=t1 - t0):
            name = f"{r.width}x{r.height}"
            png, shown = map_image(r.map, cfg.output.gamma, full_sphere=args.full_sphere)
            iio.imwrite(out / f"map_{name}.png", png, extension=".png")
            write_tum(out / f"trajectory_{name}.txt", r.trajectory)
            r.map = None  # free the map before the next (larger) size
            rows.append({**r.row(), "map_png": shown})
            if not args.quiet:
                print(f"{name}: back-end {r.us_per_event_backend:.2f} us/event, peak RSS {r.peak_rss_mb:.0f} MB")
        table = runtime_table(rows)
        (out / "runtime.txt").write_text(table + "\n")
        plot_runtime(out / "runtime.png", rows)
        report = {
            "status": "ok",
            "method": "cmax-slam at several map sizes",
            "dataset": str(args.dataset),
            "events_processed": rows[0]["events_processed"] if rows else 0,
            "sizes": rows,
            "us_per_event": {r["size"]: {"frontend": r["us_per_event_frontend"], "backend": r["us_per_event_backend"]}
                             for r in rows},
            "peak_rss_mb": float(np.max([r["peak_rss_mb"] for r in rows])),
            "image_quality": quality_availability(),
            "camera": camera.to_dict(),
        }
        write_report(out, report)
        save_config(cfg, out / "config.yaml")
    print(table)
    print(f"-> {args.out}")
    return 0

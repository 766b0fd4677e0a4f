"""``ti-cmax map``: render the panoramic IWE of a trajectory and print its event area and gradient magnitude."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from . import add_map_arguments, positive_float

HELP = "render the panoramic image of warped events of a trajectory (PNG + JSON with EA, GM, variance)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder or events file")
    parser.add_argument("--trajectory", required=True, metavar="TRAJ.txt", help="trajectory (TUM)")
    parser.add_argument("--out", required=True, metavar="MAP.png", help="output image; MAP.json is written beside it")
    parser.add_argument("--size", default=None, metavar="WxH", help="map size (default: 2*pano_height x pano_height)")
    parser.add_argument("--gamma", type=positive_float, default=None, help="display gamma (default 0.75)")
    parser.add_argument("--t-start", type=float, default=None, help="first event time to use (s)")
    parser.add_argument("--t-end", type=float, default=None, help="last event time to use (s)")
    add_map_arguments(parser)


def events_range(dataset, args) -> tuple[float, float]:
    """The time range of the events asked for: the dataset's, cut to --t-start/--t-end."""
    t0, t1 = dataset.time_range()
    return (t0 if args.t_start is None else max(t0, args.t_start), t1 if args.t_end is None else min(t1, args.t_end))


def run(args) -> int:
    import imageio.v3 as iio

    from ..config import SlamConfig, load_config, parse_map_size
    from ..io import open_dataset_from_config, read_tum
    from ..outputs import atomic_files, check_output_file
    from ..pipelines.panorama import describe_extent, map_image, render_panorama
    from ..pipelines.sensor_defaults import pano_size
    from ..status import apply_status, status_text

    check_output_file(args.out)
    cfg = load_config(SlamConfig, args.config, args.overrides)
    gamma = cfg.output.gamma if args.gamma is None else args.gamma
    size = parse_map_size(args.size) if args.size else None
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    width, height = size or pano_size(cfg.backend, dataset.camera)
    trajectory = read_tum(args.trajectory)
    result = render_panorama(dataset.iter_events(cfg.dataset.chunk_size), dataset.camera, trajectory, width, height,
                             cfg.backend.event_batch_size, args.t_start, args.t_end)
    if result.events_used == 0:
        from ..errors import InputError

        raise InputError(f"no event falls in the trajectory's time range [{trajectory.t_start:.6f}, "
                         f"{trajectory.t_end:.6f}] s" + (" and --t-start/--t-end" if args.t_start is not None
                                                         or args.t_end is not None else "") + ": nothing to render",
                         source=args.trajectory)
    figures = apply_status(result.figures(cfg.backend.lambda0), events_range=events_range(dataset, args),
                           trajectory_range=(trajectory.t_start, trajectory.t_end))
    image, figures["png"] = map_image(result.image, gamma, full_sphere=args.full_sphere)
    out = Path(args.out)
    with atomic_files(out, out.with_suffix(".json")) as (png, js):  # both or neither
        iio.imwrite(png, image, extension=".png")
        js.write_text(json.dumps(figures, indent=2))
    print(f"map {width}x{height}: {figures['events']} events, EA {figures['event_area_percent']:.3f} %, "
          f"GM {figures['gradient_magnitude']:.4f}, variance {figures['variance']:.5f}; image: "
          f"{describe_extent(figures['png'])}{status_text(figures)}")
    print(json.dumps(figures))
    return 0

"""One module per ``ti-cmax`` subcommand: ``HELP``, ``add_arguments(parser)``, ``run(args) -> int``."""


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0 (argparse reports anything else as one usage error)."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def add_map_arguments(parser) -> None:
    """--full-sphere: the map PNG of the whole sphere instead of the observed region (pipelines/panorama.map_image)."""
    parser.add_argument("--full-sphere", action="store_true",
                        help="map image of the whole sphere (default: cropped to the observed region and contrast-"
                             "stretched; its extent in degrees is in the JSON report)")


def add_sensor_arguments(parser, topic_help: str = "ROS bag event topic") -> None:
    """--width, --height, --topic: what a dataset's files may not say (info, convert)."""
    parser.add_argument("--width", type=int, default=None, help="sensor width (overrides what the files say)")
    parser.add_argument("--height", type=int, default=None, help="sensor height")
    parser.add_argument("--topic", default=None, help=topic_help)


def dataset_config(args):
    """The DatasetConfig of --config / --set, with --width, --height and --topic applied."""
    from dataclasses import replace

    from ..config import load_config
    from ..io.dataset import DatasetConfig

    cfg = load_config(DatasetConfig, args.config, args.overrides)
    if args.width or args.height:
        cfg = replace(cfg, width=args.width or 0, height=args.height or 0)
    if args.topic:
        cfg = replace(cfg, topic=args.topic)
    return cfg

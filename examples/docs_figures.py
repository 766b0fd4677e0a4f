"""Regenerate the documentation's figure (docs/img/demo.png) from a demo run.

Runs ``ti-cmax demo`` into a work folder and puts its CMax-SLAM map (slam/map.png, cropped to the observed region)
above its error-over-time plot (errors_over_time.png, the front-end alone against CMax-SLAM) in one image.

    python examples/docs_figures.py [--work DIR] [--out docs/img/demo.png] [--demo-out DIR]

``--demo-out`` reuses an existing demo folder instead of running the demo.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path


def compose(demo_dir: Path, out: Path) -> None:
    """The map above the error plot, each scaled to one width, with a caption each."""
    import matplotlib

    matplotlib.use("Agg")
    import imageio.v3 as iio
    import matplotlib.pyplot as plt

    panels = [(iio.imread(demo_dir / "slam" / "map.png"), "CMax-SLAM panoramic map (observed region)"),
              (iio.imread(demo_dir / "errors_over_time.png"), "rotation error over time against ground truth")]
    heights = [img.shape[0] / img.shape[1] for img, _ in panels]
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 9 * sum(heights) + 0.6),
                             gridspec_kw={"height_ratios": heights})
    for ax, (img, caption) in zip(axes, panels):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None)
        ax.set_title(caption, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=None, help="folder for the demo run (default: a temporary one)")
    ap.add_argument("--demo-out", type=Path, default=None, help="an existing demo output folder to use")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "img" / "demo.png")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        demo_dir = args.demo_out
        if demo_dir is None:
            demo_dir = (args.work or Path(tmp)) / "demo_out"
            ti_cmax = Path(sys.executable).with_name("ti-cmax")
            subprocess.run([str(ti_cmax), "demo", "--out", str(demo_dir), "--quiet"], check=True)
        compose(demo_dir, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

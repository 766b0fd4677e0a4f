"""Super-resolution workflow: CMax-SLAM at two small map sizes writes both maps and the runtime table."""
import json

import imageio.v3 as iio
import numpy as np
import pytest

from ti_cmax.errors import InputError


def test_parse_sizes():
    from ti_cmax.pipelines.workflows.super_resolution import parse_sizes

    assert parse_sizes("512x256, 1024x512") == [(512, 256), (1024, 512)]
    for bad in ("512x512", "abc", "", "8x4", "65536x32768", "0x0"):
        with pytest.raises(InputError):
            parse_sizes(bad)


def test_central_crop_and_quality_figures():
    from ti_cmax.pipelines.workflows.super_resolution import central_crop, quality_figures

    img = np.zeros((64, 128), np.float32)
    img[16:48, 32:96] = np.random.default_rng(0).poisson(2.0, (32, 64))
    crop = central_crop(img)
    assert crop.shape == (16, 32)
    q = quality_figures(img)
    assert q["gradient_magnitude"] > 0 and 0 < q["event_area_percent"] <= 100
    assert q["niqe"] is None  # no offline NIQE model


@pytest.fixture(scope="module")
def small_dataset(ti_runtime, tmp_path_factory):
    from ti_cmax.simulate import SimulatorConfig, simulate_sequence, write_sequence

    seq = simulate_sequence(SimulatorConfig(scene="bay", duration=0.5, max_angular_velocity=2.0, seed=5))
    out = tmp_path_factory.mktemp("sr") / "seq"
    write_sequence(seq, out)
    return out


@pytest.mark.slow
def test_super_resolution_two_sizes(small_dataset, tmp_path, capsys):
    from ti_cmax.cli import main

    out = tmp_path / "sr"
    assert main(["super-resolution", str(small_dataset), "--out", str(out), "--sizes", "256x128,512x256",
                 "--quiet"]) == 0
    shown = {r["size"]: r["map_png"] for r in json.loads((out / "report.json").read_text())["sizes"]}
    for w, h in ((256, 128), (512, 256)):
        img = iio.imread(out / f"map_{w}x{h}.png")  # cropped to the observed region
        assert img.shape == (shown[f"{w}x{h}"]["height"], shown[f"{w}x{h}"]["width"])
        assert img.shape[0] < h and img.shape[1] < w
        assert img.min() < 128  # events were voted (dark on white)
        assert (out / f"trajectory_{w}x{h}.txt").is_file()
    table = (out / "runtime.txt").read_text().splitlines()
    assert len(table) == 3 and table[1].split()[0] == "256x128" and table[2].split()[0] == "512x256"
    assert (out / "runtime.png").is_file()
    report = json.loads((out / "report.json").read_text())
    rows = report["sizes"]
    assert [r["size"] for r in rows] == ["256x128", "512x256"]
    for r in rows:
        assert r["us_per_event_backend"] > 0 and r["peak_rss_mb"] > 0
        assert r["abs_rmse_deg"] < 5.0  # tracking works at both sizes
    assert set(report["image_quality"]) >= {"piqe", "niqe", "reported"}

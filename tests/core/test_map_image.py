"""Map images: cropped to the observed region (extent in degrees), the full sphere on request, and the right
polarity for both kinds of map (events dark on white; an intensity panorama as it is)."""
import json

import imageio.v3 as iio
import numpy as np
import pytest

from ti_cmax.pipelines.panorama import map_image


def _patch_map(h=90, w=180):
    img = np.zeros((h, w), np.float32)
    img[30:45, 170:180] = 3.0  # a region across the longitude seam (u = 0 is u = w)
    img[35:50, 0:12] = 5.0
    return img


def test_events_map_is_cropped_around_what_was_observed():
    img = _patch_map()
    png, info = map_image(img)
    h, w = img.shape
    r0, r1 = info["crop_px"]["rows"]
    c0, c1 = info["crop_px"]["columns"]
    assert info["shown"] == "observed region" and png.shape == (info["height"], info["width"])
    assert r0 <= 30 and r1 >= 50 and r1 - r0 < 30  # the rows with events, plus a small margin
    assert c0 > c1 and c0 <= 170 and c1 >= 12  # across the seam: west edge > east edge in columns
    assert png.shape[1] < 40 and png.shape[1] == (c1 - c0) % w
    lon0, lon1 = info["extent_deg"]["longitude"]
    assert lon0 == pytest.approx((c0 - w / 2) * 2.0) and lon1 == pytest.approx((c1 - w / 2) * 2.0)
    assert info["size_deg"][0] == pytest.approx(png.shape[1] * 2.0)
    lat0, lat1 = info["extent_deg"]["latitude"]
    assert lat0 == pytest.approx((r0 - 45.0) * 2.0) and lat1 == pytest.approx((r1 - 45.0) * 2.0)
    # contrast-stretched and dark on white: every event pixel is darker than the background, the densest black
    dark = png < 255
    assert dark.sum() == (img > 0).sum() and png.min() == 0 and (png == 255).any()


def test_full_sphere_on_request():
    img = _patch_map()
    png, info = map_image(img, full_sphere=True)
    assert png.shape == img.shape and info["shown"] == "full sphere"
    assert info["extent_deg"] == {"longitude": [-180.0, 180.0], "latitude": [-90.0, 90.0]}
    assert map_image(np.zeros((8, 16)))[0].shape == (8, 16)  # nothing observed: the whole (white) map


def _known_panorama(h=64, w=128):
    """A smooth intensity panorama observed on part of the sphere (8-bit, 0 = unobserved, as SMT's map)."""
    v, u = np.mgrid[0:h, 0:w]
    scene = 128 + 100 * np.sin(u / 5.0) * np.cos(v / 7.0)
    pano = np.zeros((h, w), np.uint8)
    pano[10:40, 20:90] = np.clip(scene[10:40, 20:90], 1, 255).astype(np.uint8)
    return pano


def test_intensity_map_keeps_its_polarity(tmp_path):
    """The SMT baseline's map (an intensity panorama) was drawn through the event renderer, which inverts it
    (correlation -0.88 with the true panorama); as a baseline result of kind "intensity" it is written as is."""
    from ti_cmax.pipelines.baselines import BaselineConfig, BaselineResult
    from ti_cmax.commands.slam import write_result
    from ti_cmax.trajectory import Trajectory

    pano = _known_panorama()
    result = BaselineResult(Trajectory(np.array([0.0, 1.0]), np.stack([np.eye(3)] * 2)), pano, {"status": "ok"},
                            map_kind="intensity")
    write_result(tmp_path, result, BaselineConfig())
    png = iio.imread(tmp_path / "map.png")
    report = json.loads((tmp_path / "report.json").read_text())
    r0, r1 = report["map"]["png"]["crop_px"]["rows"]
    c0, c1 = report["map"]["png"]["crop_px"]["columns"]
    truth = pano[r0:r1, c0:c1].astype(float)
    assert png.shape == truth.shape
    mask = truth > 0
    corr = np.corrcoef(png[mask].astype(float), truth[mask])[0, 1]
    assert corr > 0.99
    # the same panorama through the event renderer is inverted: what the intensity kind avoids
    inverted, _ = map_image(pano.astype(np.float32))
    assert np.corrcoef(inverted[mask].astype(float), truth[mask])[0, 1] < 0

"""Grayscale panorama: Poisson integration (pipelines/workflows/poisson.py), GrayscaleMapper on a simulated sequence,
``ti-cmax grayscale`` CLI."""
import json

import numpy as np
import pytest

from ti_cmax.pipelines.workflows import poisson


def smooth_band(n=40, w=128, seed=0):
    """A smooth image periodic in columns (random low-frequency Fourier terms), plus a vertical ramp."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:n, 0:w].astype(np.float64)
    img = 0.02 * rows
    for _ in range(6):
        k = rng.integers(1, 5)
        img += rng.normal() * np.sin(2 * np.pi * k * cols / w + rng.uniform(0, 6)) * np.cos(rng.uniform(0.02, 0.15)
                                                                                            * rows + rng.uniform(0, 6))
    return img


def test_poisson_periodic_recovers_image_from_forward_differences():
    img = smooth_band() + np.random.default_rng(1).normal(size=(40, 128))  # any image, not only smooth
    gu = np.roll(img, -1, axis=1) - img  # periodic in longitude
    gv = img[1:] - img[:-1]
    rec = poisson.integrate_periodic(gu, gv)
    np.testing.assert_allclose(rec - rec.mean(), img - img.mean(), atol=1e-10)


def test_poisson_neumann_recovers_image():
    img = np.random.default_rng(2).normal(size=(30, 50))
    rec = poisson.integrate_neumann(img[:, 1:] - img[:, :-1], img[1:] - img[:-1])
    np.testing.assert_allclose(rec - rec.mean(), img - img.mean(), atol=1e-10)


def test_integrate_box_from_centred_gradients_on_a_band():
    """Analytic pixel-centred gradient of a smooth panorama band (rows 30..69 of 100): recovered up to a constant,
    periodic in longitude, nothing solved outside the band."""
    h, w = 100, 128
    band = smooth_band(40, w, seed=3)
    rows, cols = np.mgrid[0:40, 0:w].astype(np.float64)
    # analytic derivatives via spectral differentiation along u and a fine central difference along v
    gu = np.real(np.fft.ifft(np.fft.fft(band, axis=1) * 2j * np.pi * np.fft.fftfreq(w), axis=1))
    gv = np.gradient(band, axis=0)
    full_u = np.zeros((h, w))
    full_v = np.zeros((h, w))
    full_u[30:70], full_v[30:70] = gu, gv
    mask = np.zeros((h, w), bool)
    mask[30:70] = True
    m, rr, cc = poisson.integrate_box(full_u, full_v, mask, margin=0)
    assert rr == slice(30, 70) and len(cc) == w
    err = (m - m.mean()) - (band - band.mean())
    assert np.abs(err).max() < 0.02 * np.ptp(band)


def test_integrate_box_uses_cyclic_column_interval():
    h, w = 20, 64
    cols = (np.arange(12) + 58) % w  # columns 58..63, 0..5: wraps around the seam
    gu = np.zeros((h, w))
    gv = np.zeros((h, w))
    mask = np.zeros((h, w), bool)
    mask[5:15][:, cols] = True
    # a ramp M = a * (column offset from the interval start) + b * row: constant gradient on the box
    a, b = 0.3, -0.2
    gu[:, cols] = a
    gv[:, cols] = b
    m, rr, cc = poisson.integrate_box(gu, gv, mask, margin=0)
    assert list(cc) == list(cols) and rr == slice(5, 15)
    expect = a * np.arange(12)[None, :] + b * np.arange(10)[:, None]
    np.testing.assert_allclose(m - m.mean(), expect - expect.mean(), atol=1e-10)
    assert poisson.cyclic_interval(np.isin(np.arange(w), cols)) == (58, 12)


@pytest.fixture(scope="module")
def seq_results(short_sequence):
    from ti_cmax.pipelines.workflows.grayscale import GrayscaleConfig, reconstruct_panoramas

    cfg = GrayscaleConfig(contrast_threshold=short_sequence.config.contrast_threshold)
    return reconstruct_panoramas([short_sequence.events], short_sequence.camera, short_sequence.groundtruth,
                                 [(512, 256)], cfg)


def test_reconstruction_correlates_with_true_panorama(short_sequence, seq_results):
    from ti_cmax.pipelines.workflows.grayscale import normalized_cross_correlation, resample_panorama

    res = seq_results[0]
    truth = resample_panorama(np.log(short_sequence.config.log_eps + short_sequence.panorama), 512, 256)
    ncc_visited = normalized_cross_correlation(res.log_intensity, truth, res.visited)
    ncc_observed = normalized_cross_correlation(res.log_intensity, truth, res.display_mask())
    assert ncc_visited > 0.7, ncc_visited
    assert ncc_observed > 0.7, ncc_observed
    assert 0.01 < res.visited.mean() < 0.5
    assert res.stats["updates"] > 0.5 * len(short_sequence.events)
    assert set(res.timings) >= {"poses", "ekf", "poisson"}
    img = res.to_uint8()
    assert img.dtype == np.uint8 and img[res.display_mask()].min() >= 1 and np.all(img[~res.display_mask()] == 0)


def test_incremental_updates_match_one_shot(short_sequence):
    """Feeding a tracker-style stream in pieces (own poses per batch) gives the same map as one call."""
    from ti_cmax.kernels.pano import batch_mid_times
    from ti_cmax.pipelines.workflows.grayscale import GrayscaleConfig, GrayscaleMapper

    ev = short_sequence.events[:200_000]
    gt = short_sequence.groundtruth
    cfg = GrayscaleConfig(contrast_threshold=0.2, max_updates_per_pixel=2, visit_gap=0.02)
    one = GrayscaleMapper(short_sequence.camera, 256, 128, cfg)
    one.update(ev, gt.at(batch_mid_times(ev.t, 100)), 100)
    parts = GrayscaleMapper(short_sequence.camera, 256, 128, cfg)
    for lo, hi in ((0, 70_000), (70_000, 200_000)):  # boundaries at multiples of the batch size
        piece = ev[lo:hi]
        parts.update(piece, gt.at(batch_mid_times(piece.t, 100)), 100)
    np.testing.assert_array_equal(parts.gradient, one.gradient)
    np.testing.assert_array_equal(parts.visits, one.visits)
    assert parts.stats == one.stats and one.stats["capped"] > 0
    r = parts.reconstruct()
    assert np.isfinite(r.log_intensity[r.visited]).all()


def test_config_loads_with_overrides(tmp_path):
    from ti_cmax.config import load_config
    from ti_cmax.errors import InputError
    from ti_cmax.pipelines.workflows.grayscale import GrayscaleConfig

    cfg = load_config(GrayscaleConfig, None, ["max_updates_per_pixel=0", "pano_height=256", "measurement_noise=0.1"])
    assert cfg.max_updates_per_pixel == 0 and cfg.pano_size == (512, 256) and cfg.measurement_noise == 0.1
    with pytest.raises(InputError):
        load_config(GrayscaleConfig, None, ["measurement_noise=-1"])


@pytest.mark.slow
def test_cli_grayscale_multi_size(short_dataset, tmp_path, capsys):
    from ti_cmax.cli import main

    out = tmp_path / "pano.png"
    gt = short_dataset / "groundtruth.txt"
    rc = main(["grayscale", str(short_dataset), "--trajectory", str(gt), "--out", str(out),
               "--sizes", "256x128,512x256", "--quiet", "--set", "max_updates_per_pixel=3"])
    assert rc == 0
    import imageio.v3 as iio

    report = json.loads((tmp_path / "pano.json").read_text())
    for (w, h), entry in zip(((256, 128), (512, 256)), report["maps"]):
        img = iio.imread(tmp_path / f"pano_{w}x{h}.png")  # cropped to the observed region
        shows = entry["png_shows"]
        assert shows["shown"] == "observed region" and img.shape == (shows["height"], shows["width"])
        assert img.shape[0] < h and img.shape[1] < w and img.max() > 200 and (img == 0).any()
        assert np.load(tmp_path / f"pano_{w}x{h}.npy").shape == (h, w)
    assert [(m["width"], m["height"]) for m in report["maps"]] == [(256, 128), (512, 256)]
    for m in report["maps"]:
        assert m["visited_fraction"] > 0.01 and m["seconds"]["ekf"] > 0 and m["seconds"]["poisson"] > 0
    assert report["contrast_threshold"] == pytest.approx(0.2)  # the simulator's C, read from simulation.json
    assert report["parameters"]["grayscale"]["max_updates_per_pixel"] == 3
    # bad input: one error line, exit 2, nothing written
    bad = tmp_path / "bad.png"
    assert main(["grayscale", str(short_dataset), "--trajectory", str(gt), "--out", str(bad), "--size", "64x32",
                 "--sizes", "64x32", "--quiet"]) == 2
    assert not list(tmp_path.glob("bad*"))
    assert "error" in capsys.readouterr().err

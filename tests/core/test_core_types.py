import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ti_cmax import Camera, Events, InputError, so3
from ti_cmax.camera import UNPROJECT_BLOCK
from ti_cmax.config import SlamConfig, load_config, save_config


def _events(n=100, seed=0):
    rng = np.random.default_rng(seed)
    return Events(np.sort(rng.uniform(0, 1, n)), rng.integers(0, 240, n), rng.integers(0, 180, n),
                  rng.integers(0, 2, n))


def test_events_slicing_and_downsampling():
    ev = _events()
    part = ev.slice_time(0.25, 0.5)
    assert np.all((part.t >= 0.25) & (part.t < 0.5))
    assert len(part) == np.count_nonzero((ev.t >= 0.25) & (ev.t < 0.5))
    assert len(ev.downsample(4)) == 25 and np.array_equal(ev.downsample(4).t, ev.t[::4])
    assert set(np.unique(ev.p)) <= {-1, 1} and ev.p.dtype == np.int8
    assert len(Events.concatenate([ev[:10], ev[10:]])) == 100


@pytest.mark.parametrize("mutate, message", [
    (lambda t, x, y: t.__setitem__(5, np.nan), "non-finite"),
    (lambda t, x, y: t.__setitem__(5, -1.0), "not sorted"),
    (lambda t, x, y: x.__setitem__(5, 240), "outside the sensor"),
])
def test_events_validation_messages(mutate, message):
    ev = _events()
    t, x, y = ev.t.copy(), ev.x.copy(), ev.y.copy()
    mutate(t, x, y)
    with pytest.raises(InputError, match=message):
        Events(t, x, y, ev.p).validate(240, 180)


def test_so3_matches_scipy_and_jacobians():
    rng = np.random.default_rng(1)
    phi = rng.normal(size=(20, 3))
    phi *= (rng.uniform(0.01, 3.0, 20) / np.linalg.norm(phi, axis=1))[:, None]
    assert np.allclose(so3.exp(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    assert np.allclose(so3.log(so3.exp(phi)), phi, atol=1e-9)
    eps = 1e-6
    for p in phi[:5]:
        jr = so3.right_jacobian(p)
        num = np.zeros((3, 3))
        for i in range(3):
            d = np.zeros(3)
            d[i] = eps
            num[:, i] = so3.log(so3.exp(p).T @ so3.exp(p + d)) / eps
        assert np.allclose(jr, num, atol=1e-5)
        assert np.allclose(so3.right_jacobian_inv(p) @ jr, np.eye(3), atol=1e-9)


def test_euler_angles_match_scipy_also_at_gimbal_lock():
    """so3.euler_xyz is scipy's as_euler("xyz") (the run figure's orientation panel, without importing scipy)."""
    import warnings

    rotations = Rotation.random(2000, random_state=3)
    assert np.allclose(so3.euler_xyz(rotations.as_matrix()), rotations.as_euler("xyz"), atol=1e-12)
    locked = Rotation.from_euler("xyz", [[0.3, np.pi / 2, 0.5], [0.3, -np.pi / 2, 0.5], [-2.0, np.pi / 2, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns of the gimbal lock
        expected = locked.as_euler("xyz")
    assert np.allclose(so3.euler_xyz(locked.as_matrix()), expected, atol=1e-9)


def test_camera_roundtrip_with_distortion():
    cam = Camera(240, 180, 199.09, 198.88, 132.19, 110.71, (-0.368, 0.150, -0.0003, -0.0002, 0.0))
    ys, xs = np.mgrid[0:180:7, 0:240:7]
    b = cam.unproject(xs.ravel(), ys.ravel())
    back = cam.project(b)
    assert np.abs(back - np.stack([xs.ravel(), ys.ravel()], 1)).max() < 1e-3
    lut = cam.bearing_lut
    assert lut.shape == (240 * 180, 3) and lut.dtype == np.float32
    assert np.allclose(cam.bearings(np.array([10], np.uint16), np.array([20], np.uint16)), lut[20 * 240 + 10])
    # the table is built in blocks of pixels (UNPROJECT_BLOCK): the numbers of unproject() on every pixel
    ys, xs = np.mgrid[0:180, 0:240]
    assert 240 * 180 > UNPROJECT_BLOCK
    np.testing.assert_array_equal(lut, cam.unproject(xs.ravel(), ys.ravel()).astype(np.float32))
    with pytest.raises(ValueError, match="separable"):
        cam.separable_bearing_lut4


@pytest.mark.parametrize("size", [(240, 180), (128, 128), (180, 240)])
def test_an_undistorted_cameras_separable_table_holds_the_per_pixel_tables_numbers(size):
    w, h = size
    cam = Camera(w, h, 199.1, 198.9, 0.55 * w, 0.45 * h)
    sep, lut = cam.separable_bearing_lut4, cam.bearing_lut4
    assert sep.shape == (max(w, h), 4) and sep.dtype == np.float32 and not sep[:, 3].any()
    ys, xs = np.mgrid[0:h, 0:w]
    rows = np.stack([sep[xs.ravel(), 0], sep[ys.ravel(), 1], sep[ys.ravel(), 2], sep[ys.ravel(), 3]], axis=1)
    np.testing.assert_array_equal(rows, lut)
    np.testing.assert_array_equal(cam.separable_bearing_lut, sep[:, :3])


def test_config_yaml_and_overrides(tmp_path):
    cfg = load_config(SlamConfig, None, ["num_events_per_packet=20000", "backend.spline_degree=3"])
    assert cfg.frontend.num_events_per_packet == 20000 and cfg.backend.spline_degree == 3
    save_config(cfg, tmp_path / "c.yaml")
    again = load_config(SlamConfig, tmp_path / "c.yaml")
    assert again == cfg
    (tmp_path / "flat.yaml").write_text("dt_ang_vel: 0.02\npano_height: 256\n")
    flat = load_config(SlamConfig, tmp_path / "flat.yaml")
    assert flat.frontend.dt_ang_vel == 0.02 and flat.backend.pano_size == (512, 256)
    with pytest.raises(InputError, match="unknown parameter 'nonsense'"):
        load_config(SlamConfig, None, ["nonsense=1"])
    with pytest.raises(InputError, match="expects int"):
        load_config(SlamConfig, None, ["num_events_per_packet=abc"])


def test_trajectory_interpolation_and_alignment():
    from ti_cmax.trajectory import Trajectory

    t = np.linspace(0, 1, 11)
    traj = Trajectory(t, so3.exp(np.outer(t, [0.0, 1.0, 0.0])))
    mid = traj.at([0.05, 0.55])
    assert np.allclose(mid, so3.exp(np.outer([0.05, 0.55], [0, 1.0, 0])), atol=1e-12)
    shifted = traj.left_multiplied(so3.exp(np.array([0.3, 0, 0])))
    assert np.allclose(shifted.aligned_to(traj, 0.5).R, traj.R, atol=1e-12)
    with pytest.raises(InputError, match="increase strictly"):
        Trajectory(np.array([0.0, 0.0]), np.stack([np.eye(3)] * 2))


def test_signed_polarity_from_every_stored_form():
    from ti_cmax.events import signed_polarity

    for stored in (np.array([0, 1, 1, 0], np.uint8), np.array([-1, 1, 1, -1], np.int16),
                   np.array([False, True, True, False]), np.array([0.0, 1.0, 1.0, 0.0], np.float32)):
        out = signed_polarity(stored)
        assert out.dtype == np.int8
        np.testing.assert_array_equal(out, [-1, 1, 1, -1])

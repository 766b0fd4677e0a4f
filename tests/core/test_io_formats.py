"""Round trips of every reader through its writer or the format's own library (h5py, rosbags), real files."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ti_cmax.camera import Camera
from ti_cmax.events import Events
from ti_cmax.io import (
    EventsH5Writer,
    EventsTxtWriter,
    ImuData,
    open_dataset,
    read_angular_velocity,
    read_calib,
    read_imu_txt,
    read_tum,
    write_angular_velocity,
    write_calib_txt,
    write_camera_info_yaml,
    write_events_h5,
    write_events_txt,
    write_imu_txt,
    write_tum,
)
from ti_cmax.trajectory import Trajectory

CAM = Camera(240, 180, 199.09, 198.83, 132.19, 110.71, (-0.368, 0.151, -0.0003, -0.0008, 0.0))


def random_events(n=5000, w=240, h=180, seed=0, t0=10.0):
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.uniform(0, 1, n))
    return Events(t, rng.integers(0, w, n), rng.integers(0, h, n), rng.choice([-1, 1], n))


def assert_same(a: Events, b: Events, atol=1e-9):
    assert len(a) == len(b)
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=atol)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.p, b.p)


# text ---------------------------------------------------------------------------------------------
def test_txt_round_trip_with_companions(tmp_path):
    ev = random_events()
    write_events_txt(tmp_path / "events.txt", ev)
    write_calib_txt(tmp_path / "calib.txt", CAM)
    gt = Trajectory(np.linspace(10, 11, 30), Rotation.random(30, random_state=2).as_matrix())
    write_tum(tmp_path / "groundtruth.txt", gt)
    rng = np.random.default_rng(3)
    imu = ImuData(np.linspace(10, 11, 50), rng.normal(size=(50, 3)), rng.normal(size=(50, 3)))
    write_imu_txt(tmp_path / "imu.txt", imu)

    ds = open_dataset(tmp_path)
    assert ds.sensor_size == (240, 180)  # snapped from the pixel range to DAVIS240C
    assert ds.camera == CAM
    assert_same(ds.read_events(), ev)
    t0, t1 = ds.time_range()
    assert abs(t0 - ev.t[0]) < 1e-9 and abs(t1 - ev.t[-1]) < 1e-9
    assert ds.num_events() == len(ev)
    np.testing.assert_allclose(ds.groundtruth.t, gt.t, atol=1e-9)
    np.testing.assert_allclose(ds.groundtruth.R, gt.R, atol=1e-9)
    np.testing.assert_allclose(ds.imu.gyro, imu.gyro, rtol=1e-8)
    np.testing.assert_allclose(read_imu_txt(tmp_path / "imu.txt").acc, imu.acc, rtol=1e-8)
    # the first line is exactly the ECD form
    first = (tmp_path / "events.txt").read_text().splitlines()[0].split()
    assert first[0] == f"{ev.t[0]:.9f}" and first[3] in ("0", "1")


def test_txt_accepts_comments_signed_polarity_and_spacing(tmp_path):
    f = tmp_path / "events.txt"
    f.write_text("# t x y p\n\n0.5 3 4 -1\n0.6\t5  6 +1  # note\n0.7 7 8 1\n1e0 9 10 0\n")
    ev = open_dataset(f, 240, 180, allow_default_calibration=True).read_events()
    np.testing.assert_allclose(ev.t, [0.5, 0.6, 0.7, 1.0])
    np.testing.assert_array_equal(ev.x, [3, 5, 7, 9])
    np.testing.assert_array_equal(ev.p, [-1, 1, 1, -1])


def test_txt_streaming_writer_and_chunked_reading(tmp_path):
    ev = random_events(25_000)
    with EventsTxtWriter(tmp_path / "events.txt") as w:
        for i in range(0, len(ev), 7000):
            w.append(ev[i:i + 7000])
    write_calib_txt(tmp_path / "calib.txt", CAM)
    ds = open_dataset(tmp_path)
    from ti_cmax.io import events_txt

    # small byte blocks so the file is parsed in many pieces; chunks are re-sliced exactly
    blocks = list(events_txt.iter_txt_blocks(tmp_path / "events.txt", block_bytes=50_000))
    assert len(blocks) > 5 and max(len(b.events) for b in blocks) < 3000
    sizes = [len(c) for c in ds.iter_events(chunk_size=4000)]
    assert sizes == [4000] * 6 + [1000]
    cut = Events.concatenate(list(ds.iter_events(chunk_size=3000, t_start=10.25, t_end=10.5)))
    assert_same(cut, ev.slice_time(10.25, 10.5))


def test_tum_imu_angular_velocity_round_trip(tmp_path):
    t = np.linspace(0, 2, 41)
    traj = Trajectory(t, Rotation.from_rotvec(np.outer(t, [0.1, -0.4, 0.2])).as_matrix())
    back = read_tum(write_tum(tmp_path / "trajectory.txt", traj))
    np.testing.assert_allclose(back.R, traj.R, atol=1e-10)
    row = (tmp_path / "trajectory.txt").read_text().splitlines()[1].split()
    assert row[1:4] == ["0", "0", "0"] and len(row) == 8
    omega = np.random.default_rng(0).normal(size=(41, 3))
    t2, w2 = read_angular_velocity(write_angular_velocity(tmp_path / "angular_velocity.txt", t, omega))
    np.testing.assert_allclose(t2, t, atol=1e-9)
    np.testing.assert_allclose(w2, omega, rtol=1e-10)


def test_calib_txt_and_yaml(tmp_path):
    assert read_calib(write_calib_txt(tmp_path / "calib.txt", CAM), 240, 180) == CAM
    (tmp_path / "c4.txt").write_text("# fx fy cx cy\n200 201 120 90\n1 2 3\n")
    c = read_calib(tmp_path / "c4.txt", 240, 180)
    assert (c.fx, c.fy, c.cx, c.cy, c.has_distortion) == (200, 201, 120, 90, False)
    (tmp_path / "c8.txt").write_text("200 201 120 90 -0.1 0.01 0.001 0.002\n")
    assert read_calib(tmp_path / "c8.txt", 240, 180).dist == (-0.1, 0.01, 0.001, 0.002, 0.0)
    y = write_camera_info_yaml(tmp_path / "camera_info.yaml", CAM)
    assert read_calib(y) == CAM
    # a folder with the YAML: sensor size comes from it
    write_events_txt(tmp_path / "events.txt", random_events(100, w=30, h=20))
    (tmp_path / "calib.txt").unlink()
    ds = open_dataset(tmp_path)
    assert ds.camera == CAM and ds.size_source == "camera_info.yaml"


# HDF5 ---------------------------------------------------------------------------------------------
def test_h5_round_trip_streaming_writer(tmp_path):
    ev = random_events(30_000)
    with EventsH5Writer(tmp_path / "ev.h5", camera=CAM, chunk_events=4096) as w:
        for i in range(0, len(ev), 9999):
            w.append(ev[i:i + 9999])
    ds = open_dataset(tmp_path / "ev.h5")
    assert ds.camera == CAM and ds.calibration_source == "HDF5 file"
    assert ds.num_events() == len(ev)
    assert ds.time_range() == (ev.t[0], ev.t[-1])
    assert [len(c) for c in ds.iter_events(chunk_size=8000)] == [8000, 8000, 8000, 6000]
    assert_same(ds.read_events(), ev, atol=0)
    assert_same(ds.read_events(10.3, 10.31), ev.slice_time(10.3, 10.31), atol=0)


def test_h5_other_layouts_written_by_h5py(tmp_path):
    import h5py

    ev = random_events(2000, w=640, h=480, t0=0.0)
    us = np.round(ev.t * 1e6).astype(np.int64)
    # DSEC style: int microseconds relative to t_offset, ms_to_idx, Blosc-free gzip compression
    with h5py.File(tmp_path / "dsec.h5", "w") as f:
        off = int(us[0])
        f["events/t"] = (us - off).astype(np.uint32)
        f.create_dataset("events/x", data=ev.x, compression="gzip")
        f["events/y"] = ev.y
        f["events/p"] = (ev.p > 0).astype(np.uint8)
        f["t_offset"] = np.int64(off)
        f["ms_to_idx"] = np.searchsorted(us - off, np.arange(0, 1001) * 1000).astype(np.uint64)
    ds = open_dataset(tmp_path / "dsec.h5", allow_default_calibration=True)
    assert ds.sensor_size == (640, 480)  # inferred: VGA
    got = ds.read_events()
    assert_same(got, ev, atol=6e-7)
    assert_same(ds.read_events(0.4, 0.6), got.slice_time(0.4, 0.6), atol=0)
    # E2VID style: events/{ts,xs,ys,ps}, sensor_resolution = (height, width)
    with h5py.File(tmp_path / "e2vid.h5", "w") as f:
        f["events/ts"], f["events/xs"], f["events/ys"] = ev.t, ev.x.astype(np.int16), ev.y.astype(np.int16)
        f["events/ps"] = ev.p.astype(np.int8)
        f.attrs["sensor_resolution"] = (480, 640)
    ds = open_dataset(tmp_path / "e2vid.h5", allow_default_calibration=True)
    assert ds.size_source == "HDF5 file" and ds.sensor_size == (640, 480)
    assert_same(ds.read_events(), ev, atol=0)
    # int64 microseconds flagged by an attribute
    with h5py.File(tmp_path / "us.h5", "w") as f:
        f["events/t"] = us
        f["events/t"].attrs["units"] = "us"
        f["events/x"], f["events/y"], f["events/p"] = ev.x, ev.y, (ev.p > 0)
        f.attrs["width"], f.attrs["height"] = 640, 480
    assert_same(open_dataset(tmp_path / "us.h5", allow_default_calibration=True).read_events(), ev, atol=6e-7)


def test_h5_float_times_in_another_unit_than_seconds_need_their_attribute(tmp_path):
    """Found by fuzzing: float times without a units attribute are seconds (CONVENTIONS.md), and microseconds stored
    as floats were read as such: a 1 s recording became 11.6 days at a few events per "second", silently; a float
    unit not known (e.g. 'minutes') was taken for seconds too. Refused in one line naming the attribute; with it the
    file reads; dense float seconds without it (E2VID style) read as before."""
    import h5py

    from ti_cmax.errors import InputError

    ev = random_events(2000, w=640, h=480, t0=0.0)

    def write(name, t, units=None):
        with h5py.File(tmp_path / name, "w") as f:
            f["events/t"] = t
            if units is not None:
                f["events/t"].attrs["units"] = units
            f["events/x"], f["events/y"], f["events/p"] = ev.x, ev.y, (ev.p > 0)
            f.attrs["width"], f.attrs["height"] = 640, 480
        return tmp_path / name

    path = write("us_float.h5", ev.t * 1e6)
    with pytest.raises(InputError, match=r"us_float.h5: events/t holds float times without a 'units' attribute.*"
                                         r"Set the attribute units on events/t to their unit: 'us'"):
        open_dataset(path, allow_default_calibration=True)
    for units in ("us", "usec", b"microseconds"):
        got = open_dataset(write("us_float.h5", ev.t * 1e6, units), allow_default_calibration=True).read_events()
        assert_same(got, ev, atol=1e-9)
    with pytest.raises(InputError, match=r"unknown time unit 'minutes' on events/t"):
        open_dataset(write("minutes.h5", ev.t / 60, "minutes"), allow_default_calibration=True)
    got = open_dataset(write("s_float.h5", ev.t), allow_default_calibration=True).read_events()
    assert_same(got, ev, atol=0)
    sparse = write("sparse_s.h5", ev.t * 1e6, "s")  # stated seconds are seconds, however sparse
    assert open_dataset(sparse, allow_default_calibration=True).time_range()[1] == pytest.approx(ev.t[-1] * 1e6)


def test_h5_compressed_with_hdf5plugin(tmp_path):
    hdf5plugin = pytest.importorskip("hdf5plugin")
    import h5py

    ev = random_events(3000)
    with h5py.File(tmp_path / "z.h5", "w") as f:
        for k, v in (("t", ev.t), ("x", ev.x), ("y", ev.y), ("p", (ev.p > 0).astype(np.uint8))):
            f.create_dataset(f"events/{k}", data=v, **hdf5plugin.Zstd())
    assert_same(open_dataset(tmp_path / "z.h5", 240, 180, allow_default_calibration=True).read_events(), ev, atol=0)


def test_h5_filter_plugins_are_imported_only_for_a_file_that_needs_them(tmp_path):
    """hdf5plugin (~0.05 s of start-up) is imported when a file uses a filter HDF5 lacks, not for every file."""
    hdf5plugin = pytest.importorskip("hdf5plugin")
    import subprocess
    import sys

    import h5py

    ev = random_events(300)
    for name, kw in (("plain.h5", {}), ("zstd.h5", hdf5plugin.Zstd())):
        with h5py.File(tmp_path / name, "w") as f:
            for k, v in (("t", ev.t), ("x", ev.x), ("y", ev.y), ("p", (ev.p > 0).astype(np.uint8))):
                f.create_dataset(f"events/{k}", data=v, **kw)
    code = ("import sys\n"
            "from ti_cmax.io import open_dataset\n"
            "n = len(open_dataset(sys.argv[1], 240, 180, allow_default_calibration=True).read_events())\n"
            "print(n, 'hdf5plugin' in sys.modules)\n")
    for name, imported in (("plain.h5", "False"), ("zstd.h5", "True")):
        proc = subprocess.run([sys.executable, "-c", code, str(tmp_path / name)], capture_output=True, text=True,
                              timeout=120)
        assert proc.stdout.split() == [str(len(ev)), imported], proc.stderr


# ROS1 bag -----------------------------------------------------------------------------------------
def test_bag_round_trip(tmp_path, write_ros1_bag):
    ev = random_events(3000)
    path = write_ros1_bag(tmp_path / "seq.bag", ev, CAM)
    ds = open_dataset(path)
    assert ds.sensor_size == (240, 180)
    assert ds.camera.K.tolist() == CAM.K.tolist() and ds.camera.dist == CAM.dist
    assert ds.num_events() == len(ev)
    t0, t1 = ds.time_range()
    assert abs(t0 - ev.t[0]) < 1e-9 and abs(t1 - ev.t[-1]) < 1e-9
    assert_same(ds.read_events(), ev, atol=2e-9)
    from ti_cmax.io.bag import BagSource

    src = BagSource(path, block=1000)  # several messages per block
    assert [len(b.events) for b in src.iter_blocks()] == [1400, 1400, 200]


# AEDAT4 and real recordings -----------------------------------------------------------------------
def test_aedat4_real_file(real_data):
    pytest.importorskip("aedat")
    path = real_data / "aedat4" / "davis346_imu.aedat4"
    if not path.is_file():
        pytest.skip("aedat4 sample absent")
    with pytest.raises(Exception, match="no camera calibration"):
        open_dataset(path).camera
    ds = open_dataset(path, allow_default_calibration=True)
    assert ds.sensor_size == (346, 260) and ds.camera.width == 346
    ev = ds.read_events()
    assert len(ev) == ds.num_events() > 10_000
    assert 0.1 < ev.duration < 0.2
    imu = ds.imu
    assert len(imu) > 100 and np.median(np.diff(imu.t)) == pytest.approx(1e-3, rel=0.01)
    assert np.linalg.norm(imu.acc, axis=1).mean() == pytest.approx(9.81, rel=0.05)  # gravity in m/s^2
    assert np.abs(imu.gyro).max() < 1.0  # slow hand-held motion, rad/s


@pytest.mark.parametrize("name", ["shapes_rotation", "poster_rotation", "boxes_rotation", "dynamic_rotation"])
def test_ecd_slices(real_data, name, tmp_path):
    folder = real_data / "ecd_slices" / name
    if not folder.is_dir():
        pytest.skip(f"{folder} absent")
    ds = open_dataset(folder)
    assert ds.sensor_size == (240, 180)
    assert ds.camera.fx == pytest.approx(199.092366542) and ds.camera.has_distortion
    ev = ds.read_events()
    assert len(ev) == 30_000 == ds.num_events()
    ref = np.loadtxt(folder / "events.txt")
    np.testing.assert_allclose(ev.t, ref[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ev.x, ref[:, 1])
    np.testing.assert_array_equal(ev.p, np.where(ref[:, 3] > 0, 1, -1))
    # the slices have CRLF line ends, which the fast parser takes as they are
    from ti_cmax.io.events_txt import _parse_fast

    assert _parse_fast((folder / "events.txt").read_bytes()) is not None
    # re-written by our writer: the same ECD text (LF line ends)
    write_events_txt(tmp_path / "events.txt", ev)
    assert (tmp_path / "events.txt").read_bytes() == (folder / "events.txt").read_bytes().replace(b"\r\n", b"\n")


def test_ecd_shapes_start_h5_conversion(real_data, tmp_path):
    folder = real_data / "ecd_shapes_rotation_start"
    if not folder.is_dir():
        pytest.skip(f"{folder} absent")
    ds = open_dataset(folder)
    ev = ds.read_events()
    assert len(ev) == 120_000 and ds.time_range() == (ev.t[0], ev.t[-1])
    write_events_h5(tmp_path / "events.h5", ev, camera=ds.camera)
    back = open_dataset(tmp_path / "events.h5")
    assert back.camera == ds.camera
    assert_same(back.read_events(), ev, atol=0)


def test_txt_seek_to_start_time(tmp_path, monkeypatch):
    from ti_cmax.io import events_txt

    ev = random_events(20_000)
    write_events_txt(tmp_path / "events.txt", ev)
    write_calib_txt(tmp_path / "calib.txt", CAM)
    offset, line = events_txt.txt_seek(tmp_path / "events.txt", 10.6, min_skip=10_000)
    data = (tmp_path / "events.txt").read_bytes()
    assert 0 < offset and data[offset - 1:offset] == b"\n" and data[:offset].count(b"\n") + 1 == line
    assert float(data[offset:].split(maxsplit=1)[0]) < 10.6  # starts at or before the cut
    assert ev.index_at(10.6) - (line - 1) < 20_000 // 4  # but skipped most of what precedes it
    monkeypatch.setattr(events_txt, "txt_seek",
                        lambda p, t, min_skip=0, f=events_txt.txt_seek: f(p, t, min_skip=10_000))
    ds = open_dataset(tmp_path)
    assert_same(ds.read_events(10.6, 10.7), ev.slice_time(10.6, 10.7))
    # errors after a seek still name the right line
    lines = data.decode().splitlines(keepends=True)
    k = int(ev.index_at(10.8))
    lines[k] = "oops\n"
    (tmp_path / "events.txt").write_text("".join(lines))
    with pytest.raises(Exception, match=rf"line {k + 1}: expected 't x y p'"):
        ds.read_events(10.6, 10.9)


@pytest.mark.parametrize("fmt", ["{:.6f}", "{:.9f}", "{:.12f}", "{:.0f}", "{:.3f}"])
def test_txt_parser_tiers_agree_with_float(tmp_path, fmt):
    from ti_cmax.io.events_txt import _parse_fast

    ev = random_events(3000, t0=1.6e9 if fmt == "{:.9f}" else 5.0)
    text = "".join(f"{fmt.format(t)} {x} {y} {1 if p > 0 else 0}\n" for t, x, y, p in
                   zip(ev.t.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist()))
    assert _parse_fast(text.encode()) is not None  # the vectorized tier takes it
    (tmp_path / "events.txt").write_text(text)
    got = open_dataset(tmp_path / "events.txt", 240, 180, allow_default_calibration=True).read_events()
    ref = np.array([float(line.split()[0]) for line in text.splitlines()])
    np.testing.assert_array_equal(got.t, ref)  # same doubles as Python's float()
    np.testing.assert_array_equal(got.x, ev.x)


def test_sensor_size_inference():
    from ti_cmax.io._common import infer_sensor_size

    assert infer_sensor_size(100, 100, "e") == (128, 128)
    assert infer_sensor_size(100, 100, "e", principal_point=(132.2, 110.7)) == (240, 180)  # ECD calib
    assert infer_sensor_size(239, 100, "e") == (240, 180)
    assert infer_sensor_size(300, 100, "e") == (346, 260)
    assert infer_sensor_size(600, 400, "e") == (640, 480)  # VGA / DVXplorer
    assert infer_sensor_size(1279, 719, "e") == (1280, 720)  # HD (Prophesee IMX636)
    assert infer_sensor_size(700, 100, "e") == (1280, 720)
    with pytest.raises(Exception, match="cannot infer the sensor size"):
        infer_sensor_size(1280, 719, "e")

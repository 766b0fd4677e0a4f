"""Readers check what they parse: coordinates never wrap, polarities of any common dtype, timestamps with enough
resolution and a plausible unit, intrinsics that fit the sensor. Each bad case is one InputError naming the file, the
line or field, and the value."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from ti_cmax.camera import Camera
from ti_cmax.errors import InputError
from ti_cmax.events import Events, polarity_signs
from ti_cmax.io import open_dataset

GOOD = "".join(f"{0.001 * i:.9f} {i * 37 % 240} {i * 53 % 180} {i % 2}\n" for i in range(1, 201))


def read(path, **kw):
    return open_dataset(path, allow_default_calibration=True, **kw).read_events()


@pytest.mark.parametrize("value", [65536, 65600, 70000, 99999, 123456])
@pytest.mark.parametrize("size", [(240, 180), (None, None)])
def test_text_coordinates_beyond_uint16_are_named_not_wrapped(tmp_path, value, size):
    """65 600 was read as 64 (uint16 wrap) and passed the sensor check; 70 000 was reported as 4 464."""
    path = tmp_path / "ev.txt"
    path.write_text(GOOD + f"0.300000000 {value} 5 1\n")
    with pytest.raises(InputError, match=rf"ev.txt, line 201: x={value} is beyond any sensor"):
        read(path, width=size[0], height=size[1])
    path.write_text(GOOD + f"0.300000000 5 {value} 1\n")
    with pytest.raises(InputError, match=rf"ev.txt, line 201: y={value} is beyond any sensor"):
        read(path, width=size[0], height=size[1])


def write_h5(path, t, x=None, y=None, p=None, units=None, n=None):
    n = len(t) if n is None else n
    x = (np.arange(n) * 37 % 240).astype(np.uint16) if x is None else x
    y = (np.arange(n) * 53 % 180).astype(np.uint16) if y is None else y
    p = (np.arange(n) % 2).astype(np.uint8) if p is None else p
    with h5py.File(path, "w") as f:
        for k, v in zip("txyp", (t, x, y, p)):
            f[f"events/{k}"] = v
        if units is not None:
            f["events/t"].attrs["units"] = units
        f.attrs["width"], f.attrs["height"] = 240, 180
    return path


T_US = np.arange(2000, dtype=np.int64) * 50  # 20 k events/s in microseconds


@pytest.mark.parametrize("p", [
    np.array([b"1", b"0"] * 1000),
    np.array(["+", "-"] * 1000, dtype=h5py.string_dtype()),
    np.array([b"+1", b"-1"] * 1000),
    np.array([b"on", b"off"] * 1000),
    np.array([1.0, -1.0] * 1000),
    np.array([1, 0] * 1000, dtype=np.int64),
    np.array([1, -1] * 1000, dtype=np.int8),
    np.array([True, False] * 1000),
])
def test_h5_polarity_of_any_common_dtype(tmp_path, p):
    """Polarity stored as bytes crashed (a numpy ufunc error); strings, floats and bools read as signs."""
    ev = read(write_h5(tmp_path / "p.h5", T_US, p=p))
    assert ev.p.dtype == np.int8 and list(ev.p[:4]) == [1, -1, 1, -1]


@pytest.mark.parametrize("p, shown", [
    (np.array([1, 7] * 1000, dtype=np.int32), "7"),
    (np.array([1.0, np.nan] * 1000), "nan"),
    (np.array([1.0, 0.5] * 1000), "0.5"),
    (np.array([b"1", b"x"] * 1000), "'x'"),
])
def test_h5_polarity_that_is_no_polarity_is_named(tmp_path, p, shown):
    """A polarity of 7 was read as +1 (p > 0) without a word."""
    with pytest.raises(InputError, match=rf"p.h5: events/p \(events 0\.\.1999\): value {shown} at position 1 "
                                         r"is not a polarity"):
        read(write_h5(tmp_path / "p.h5", T_US, p=p))


def test_polarity_signs_refuses_unsupported_dtypes():
    with pytest.raises(InputError, match="dtype complex128"):
        polarity_signs(np.array([1 + 1j]))
    assert list(Events(np.zeros(2), np.zeros(2, np.uint16), np.zeros(2, np.uint16), np.array(["-", "+"])).p) == [-1, 1]


def test_h5_uint64_times_beyond_int64_are_refused(tmp_path):
    """uint64 times above 2^63 became negative times."""
    t = np.arange(2000, dtype=np.uint64) * np.uint64(50) + np.uint64(2**63 + 5)
    with pytest.raises(InputError, match=r"u64.h5: events/t: event 0 has time 9223372036854775813, beyond any clock"):
        open_dataset(write_h5(tmp_path / "u64.h5", t), allow_default_calibration=True)
    t = np.arange(2000, dtype=np.uint64) * np.uint64(50)  # small uint64 times read as before
    assert read(write_h5(tmp_path / "ok.h5", t)).t[-1] == pytest.approx(1999 * 50e-6)


def test_h5_float_times_too_coarse_are_refused(tmp_path):
    """float16 times were quantised without a word (1 ms steps near 1 s); float32 loses microseconds past ~100 s."""
    with pytest.raises(InputError, match=r"f16.h5: events/t holds float16 times, too coarse"):
        open_dataset(write_h5(tmp_path / "f16.h5", (T_US * 1e-6).astype(np.float16)), allow_default_calibration=True)
    with pytest.raises(InputError, match=r"f32.h5: events/t holds float32 times whose resolution at t=4999.99.* is "
                                         r"0.000488 s"):
        open_dataset(write_h5(tmp_path / "f32.h5", (4990 + T_US * 1e-4).astype(np.float32)),
                     allow_default_calibration=True)
    assert read(write_h5(tmp_path / "f32ok.h5", (T_US * 1e-6).astype(np.float32))).t[-1] == pytest.approx(0.09995)


def test_h5_integer_times_in_an_implausible_unit_are_refused(tmp_path):
    """Integer times without a unit are microseconds: nanoseconds read so gave 50 events/s over hours, seconds an
    instant; both now name the unit assumed and what to set. With the unit given, they read."""
    ns = write_h5(tmp_path / "ns.h5", T_US * 1000 * 20)  # 1 k events/s in nanoseconds
    with pytest.raises(InputError, match=r"ns.h5: events/t holds integer times without a 'units' attribute, read as "
                                         r"microseconds, but its first events are 1 s apart.*attribute units on "
                                         r"events/t.*--set time_unit"):
        open_dataset(ns, allow_default_calibration=True)
    assert read(ns, time_unit="ns").t[-1] == pytest.approx(1999 * 1e-3)
    seconds = write_h5(tmp_path / "s.h5", np.arange(200_000, dtype=np.int64) // 20_000, n=200_000)
    with pytest.raises(InputError, match=r"s.h5: events/t read as microseconds \(integer times without a units "
                                         r"attribute\), 200000 events span 9e-06 s \(2.22e\+10 events/s\): more than "
                                         r"any event camera.*--set time_unit"):
        open_dataset(seconds, allow_default_calibration=True)
    assert open_dataset(seconds, allow_default_calibration=True, time_unit="s").time_range() == (0.0, 9.0)
    stated = write_h5(tmp_path / "stated.h5", T_US, units="ms")  # a stated unit is taken as stated
    assert open_dataset(stated, allow_default_calibration=True).time_range()[1] == pytest.approx(99.95)


def test_text_times_in_microseconds_are_refused_until_the_unit_is_given(tmp_path):
    path = tmp_path / "us.txt"
    path.write_text("".join(f"{1_000_000 + 500 * i} {i % 240} {i % 180} {i % 2}\n" for i in range(400)))
    with pytest.raises(InputError, match=r"us.txt: the times read as seconds \(the text format's unit\), the events "
                                         r"span 1.995e\+05 s.*--set time_unit=ms, us or ns"):
        open_dataset(path, allow_default_calibration=True)
    ev = read(path, time_unit="us")
    assert ev.t[0] == pytest.approx(1.0) and ev.t[-1] == pytest.approx(1.1995)
    assert open_dataset(path, allow_default_calibration=True, time_unit="us").time_range()[1] == pytest.approx(1.1995)
    from ti_cmax.cli import main

    assert main(["info", str(path), "--set", "allow_default_calibration=true", "--set", "time_unit=us"]) == 0
    assert main(["info", str(path), "--set", "allow_default_calibration=true"]) == 2
    (tmp_path / "x.aedat4").write_bytes(b"x")
    with pytest.raises(InputError, match="time_unit applies to text and HDF5 files"):
        open_dataset(tmp_path / "x.aedat4", time_unit="us")


def test_camera_info_yaml_not_utf8_is_one_error(tmp_path):
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text(GOOD)
    (d / "camera_info.yaml").write_bytes("image_width: 240\nimage_height: 180\n# caf\xe9\ncamera_matrix: {data: "
                                         "[200,0,120,0,200,90,0,0,1]}\n".encode("latin-1"))
    with pytest.raises(InputError, match=r"camera_info.yaml: not UTF-8 text \(byte 0xe9 at offset 40\)"):
        open_dataset(d)


@pytest.mark.parametrize("fx, cx, message", [
    (1e-9, 120.0, r"fx=1e-09 px gives a horizontal field of view of 180 deg \(expected 1 to 179 deg\)"),
    (1e12, 120.0, r"fx=1e\+12 px gives a horizontal field of view of 1.375e-08 deg"),
    (200.0, 5000.0, r"principal point cx=5000 px is far off the sensor \(expected -120 to 360\)"),
    (200.0, -200.0, r"principal point cx=-200 px is far off the sensor"),
])
def test_intrinsics_that_do_not_fit_the_sensor_are_one_error(tmp_path, fx, cx, message):
    """Focal lengths of 1e-9 or 1e12 px and a principal point far off the sensor were accepted (omega up to 4e11
    rad/s, status ok)."""
    with pytest.raises(InputError, match=message):
        Camera(240, 180, fx, fx, cx, 90.0)
    d = tmp_path / "seq"
    d.mkdir()
    (d / "events.txt").write_text(GOOD)
    (d / "calib.txt").write_text(f"{fx} {fx} {cx} 90\n")
    with pytest.raises(InputError, match=r"calib.txt: camera intrinsics do not fit the 240x180 sensor: " + message):
        open_dataset(d, 240, 180).camera
    with pytest.raises(InputError, match=message):  # `info` showed such a file as "no calib.txt"
        open_dataset(d, 240, 180).calibration_source
    (d / "calib.txt").unlink()
    assert open_dataset(d, 240, 180).calibration_source is None
    Camera(240, 180, 10.0, 10.0, -100.0, 250.0)  # a wide lens with an off-centre principal point still fits


def test_h5_integer_coordinates_beyond_uint16_are_named(tmp_path):
    x = (np.arange(2000) % 240).astype(np.int32)
    x[1234] = 70000
    with pytest.raises(InputError, match=r"x.h5: events/x: event 1234 has x=70000, outside the pixel range 0..65535"):
        read(write_h5(tmp_path / "x.h5", T_US, x=x))


def star_folder(tmp_path, lines: str):
    d = tmp_path / "star"
    d.mkdir(parents=True)
    (d / "events.txt").write_text(lines)
    (d / "calibration.txt").write_text("0.005 0 -0.6\n0 0.005 -0.45\n0 0 1\n")
    return d


@pytest.mark.parametrize("bad, message", [
    ("0.5 1e6 3.5 1", r"line 3: x=1000000.0 is far outside the 240x180 sensor \(expected -120 to 360\)"),
    ("0.5 4.5 -1e40 0", r"line 3: y=-1e\+40 is far outside"),
    ("0.5 4.5 3.5 2", r"line 3: polarity must be 0/1 or -1/\+1, got 2.0"),
    ("0.5 4.5 nan 1", r"line 3: values must be finite numbers"),
    ("0.05 4.5 3.5 1", r"line 3: timestamps are not sorted: t=0.05 comes after t=0.2"),
])
def test_star_reader_names_the_line_and_value(tmp_path, bad, message):
    from ti_cmax.io.star import open_star_dataset

    d = star_folder(tmp_path, f"0.1 1.5 2.5 1\n0.2 -3.5 182.25 0\n{bad}\n")
    with pytest.raises(InputError, match=r"events.txt, " + message):
        open_star_dataset(d).read_events()
    d = star_folder(tmp_path / "c", f"# comment\n0.1 1.5 2.5 1\n\n0.2 -3.5 182.25 0\n{bad}\n")
    with pytest.raises(InputError, match=r"events.txt, " + message.replace("line 3", "line 5")):
        open_star_dataset(d).read_events()


def test_text_polarity_words(tmp_path):
    """Text polarities as +/-, on/off or numbers equal to 1/0/-1 read as signs; anything else names the line."""
    path = tmp_path / "ev.txt"
    path.write_text("0.1 1 2 +\n0.2 3 4 -\n0.3 5 6 on\n0.4 7 8 1e0\n0.5 9 9 -1.0\n")
    assert list(read(path, width=240, height=180).p) == [1, -1, 1, 1, -1]
    path.write_text("0.1 1 2 +\n0.2 3 4 2\n")
    with pytest.raises(InputError, match=r"ev.txt, line 2: polarity must be 0/1 or -1/\+1 \(or \+/-\), got '2'"):
        read(path, width=240, height=180)

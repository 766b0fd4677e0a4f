"""Property-based tests (hypothesis) of the readers and of OnlineSlam.push: random and adversarial inputs end in a
valid result or one InputError, never another exception. Examples are few and small: the whole file runs in
seconds."""
from __future__ import annotations

import math
import struct

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from ti_cmax.errors import InputError
from ti_cmax.events import Events
from ti_cmax.io import open_dataset

W, H = 240, 180
FAST = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def assert_valid(ev: Events, width=W, height=H):
    """What every reader promises of the events it returns."""
    assert len(ev.t) == len(ev.x) == len(ev.y) == len(ev.p)
    assert ev.t.dtype == np.float64 and np.isfinite(ev.t).all() and (np.diff(ev.t) >= 0).all()
    assert ev.p.dtype == np.int8 and np.isin(ev.p, (-1, 1)).all()
    if ev.has_subpixel_coordinates:
        assert np.isfinite(ev.x).all() and np.isfinite(ev.y).all()
    else:
        assert ev.x.dtype == np.uint16 and (ev.x < width).all() and (ev.y < height).all()


def read_or_input_error(path, **kw):
    """The events of ``path`` checked by assert_valid, or None when the reader refused them with InputError."""
    try:
        ds = open_dataset(path, allow_default_calibration=True, **kw)
        ev = ds.read_events()
    except InputError as exc:
        assert "\n" not in str(exc)
        return None
    assert_valid(ev, ds.width, ds.height)
    return ev


# ------------------------------------------------------------------------------------------------
# text
numbers = st.one_of(
    st.integers(-5, 300).map(str), st.integers(0, 200_000).map(str),
    st.floats(allow_nan=True, allow_infinity=True, width=64).map(repr),
    st.sampled_from(["1e3", "+1", "-1", "0", "1", "2", "nan", "inf", "-0", "0x10", "1,5", "", "abc", "\u00e9"]),
)
good_line = st.builds(lambda t, x, y, p: f"{t:.9f} {x} {y} {p}", st.floats(0, 5), st.integers(0, W - 1),
                      st.integers(0, H - 1), st.sampled_from(["0", "1", "-1"]))
odd_line = st.one_of(
    st.lists(numbers, min_size=0, max_size=6).map(" ".join),
    st.sampled_from(["# comment", "", "   ", "\t1.0\t2\t3\t1", "1.0 2 3 1 # tail"]),
)


@FAST
@given(lines=st.lists(st.one_of(good_line, good_line, odd_line), min_size=1, max_size=12),
       sort=st.booleans(), crlf=st.booleans(), size=st.sampled_from([(W, H), (None, None)]))
def test_text_reader_returns_valid_events_or_one_input_error(tmp_path, lines, sort, crlf, size):
    if sort:
        lines = sorted(lines, key=lambda s: s.split(" ")[0])
    path = tmp_path / "ev.txt"
    path.write_bytes(("\r\n" if crlf else "\n").join(lines).encode("utf-8") + b"\n")
    read_or_input_error(path, width=size[0], height=size[1])


@FAST
@given(n=st.integers(1, 300), x_max=st.sampled_from([W - 1, W, 65535, 65536, 65600, 99999]))
def test_text_reader_never_wraps_coordinates(tmp_path, n, x_max):
    """A pixel beyond the sensor or uint16 is refused, never read as another pixel."""
    x = np.arange(n) % W
    x[-1] = x_max
    path = tmp_path / "ev.txt"
    path.write_text("".join(f"{0.001 * i:.9f} {xi} 5 {i % 2}\n" for i, xi in enumerate(x)))
    ev = read_or_input_error(path, width=W, height=H)
    assert (ev is not None) == (x_max < W)
    if ev is not None:
        assert int(ev.x[-1]) == x_max


# ------------------------------------------------------------------------------------------------
# HDF5
T_DTYPES = ["<i4", "<i8", "<u8", "<f2", "<f4", "<f8"]
XY_DTYPES = ["<u2", "<i4", "<i8", "<u8", "<f4", "<f8"]
P_DTYPES = ["|u1", "|b1", "|i1", "<i4", "<f4", "<f8", "S2", "str"]


@st.composite
def h5_columns(draw):
    n = draw(st.integers(1, 200))
    t_dtype, xy_dtype, p_dtype = (draw(st.sampled_from(d)) for d in (T_DTYPES, XY_DTYPES, P_DTYPES))
    step = draw(st.sampled_from([1, 50, 1000, 10**6, 10**9]))
    t = np.cumsum(np.asarray(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)), np.uint64)) * np.uint64(step)
    t = t + np.uint64(draw(st.sampled_from([0, 1_600_000_000, 2**63 + 1])))
    if not draw(st.booleans()):  # adversarial: unsorted
        t = t[::-1]
    if t_dtype.startswith("<f"):
        t = t.astype(np.float64) * draw(st.sampled_from([1e-6, 1.0]))
    else:
        t = np.minimum(t, np.uint64(np.iinfo(t_dtype).max))
    with np.errstate(all="ignore"):
        t = t.astype(t_dtype)
    big = draw(st.sampled_from([0, 1, 70000, -1]))
    x = (np.arange(n) * 37 % W).astype(np.int64)
    y = (np.arange(n) * 53 % H).astype(np.int64)
    if big:
        x[draw(st.integers(0, n - 1))] = big
    if np.dtype(xy_dtype).kind == "u":
        x = np.abs(x)
    x, y = x.astype(xy_dtype), y.astype(xy_dtype)
    signs = draw(st.lists(st.sampled_from([0, 1, -1, 7]), min_size=n, max_size=n))
    if p_dtype == "S2":
        p = np.array([{0: b"0", 1: b"1", -1: b"-", 7: b"x"}[s] for s in signs], dtype="S2")
    elif p_dtype == "str":
        p = np.array([{0: "off", 1: "on", -1: "-1", 7: "?"}[s] for s in signs], dtype=h5py.string_dtype())
    else:
        p = np.array([max(s, 0) if np.dtype(p_dtype).kind in "ub" else s for s in signs]).astype(p_dtype)
    units = draw(st.sampled_from([None, "us", "s", "ns", b"ms", "minutes"]))
    cut = draw(st.sampled_from([0, 0, 0, 1]))  # 1: the p column one shorter
    return t, x, y, p[:n - cut] if n > cut else p, units


@FAST
@given(cols=h5_columns(), size_attrs=st.booleans())
def test_h5_reader_returns_valid_events_or_one_input_error(tmp_path, cols, size_attrs):
    t, x, y, p, units = cols
    path = tmp_path / "ev.h5"
    with h5py.File(path, "w") as f:
        for k, v in zip("txyp", (t, x, y, p)):
            f[f"events/{k}"] = v
        if units is not None:
            f["events/t"].attrs["units"] = units
        if size_attrs:
            f.attrs["width"], f.attrs["height"] = W, H
    ev = read_or_input_error(path)
    if ev is not None and t.dtype == np.uint64:
        assert (ev.t >= 0).all()  # uint64 times never come back negative


# ------------------------------------------------------------------------------------------------
# the star form (float coordinates)
star_line = st.builds(lambda t, x, y, p: f"{t!r} {x!r} {y!r} {p}", st.floats(0, 5), st.floats(-400, 600),
                      st.floats(-300, 400), st.sampled_from(["0", "1", "-1", "2"]))


@FAST
@given(lines=st.lists(st.one_of(star_line, odd_line), min_size=1, max_size=10))
def test_star_reader_returns_valid_events_or_one_input_error(tmp_path, lines):
    from ti_cmax.io.star import open_star_dataset

    d = tmp_path / "star"
    d.mkdir(exist_ok=True)
    (d / "events.txt").write_text("\n".join(sorted(lines)) + "\n")
    (d / "calibration.txt").write_text("0.005 0 -0.6\n0 0.005 -0.45\n0 0 1\n")
    try:
        ev = open_star_dataset(d).read_events()
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    assert_valid(ev)
    assert ((ev.x >= -W / 2) & (ev.x <= 1.5 * W) & (ev.y >= -H / 2) & (ev.y <= 1.5 * H)).all()


# ------------------------------------------------------------------------------------------------
# OnlineSlam.push
@pytest.fixture(scope="module")
def slam_parts():
    from ti_cmax.camera import Camera
    from ti_cmax.config import SlamConfig, update_config

    camera = Camera(W, H, 200.0, 200.0, 119.5, 89.5)
    cfg = update_config(SlamConfig(), {"loop_closure": False, "pano_height": 256})
    return camera, cfg


@st.composite
def chunks(draw):
    """1-3 chunks of 0-400 events: sorted or not, pauses, pixels on or off the sensor, odd polarities and dtypes."""
    out, t0 = [], draw(st.sampled_from([0.0, 1.6e9, -5.0]))
    for _ in range(draw(st.integers(1, 3))):
        n = draw(st.integers(0, 400))
        span = draw(st.sampled_from([1e-6, 0.01, 0.2, 100.0]))
        t = t0 + np.sort(np.asarray(draw(st.lists(st.floats(0, 1), min_size=n, max_size=n)))) * span
        if n and draw(st.integers(0, 4)) == 0:
            t = t[::-1].copy()
        if n and draw(st.integers(0, 6)) == 0:
            t[draw(st.integers(0, n - 1))] = draw(st.sampled_from([math.nan, math.inf, -1e300]))
        t0 = float(t[-1]) if n and np.isfinite(t[-1]) else t0
        subpixel = draw(st.booleans())
        x = np.asarray(draw(st.lists(st.integers(0, W + 5), min_size=n, max_size=n)), dtype=np.int64)
        y = np.asarray(draw(st.lists(st.integers(0, H - 1), min_size=n, max_size=n)), dtype=np.int64)
        if subpixel:
            x, y = x.astype(np.float32) + 0.25, y.astype(np.float32)
        else:
            x, y = x.astype(np.uint16), y.astype(np.uint16)
        p = np.asarray(draw(st.lists(st.sampled_from([0, 1]), min_size=n, max_size=n)), dtype=np.uint8)
        out.append(Events(t, x, y, p))
    return out


@settings(max_examples=8, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(parts=chunks())
def test_online_slam_push_ends_in_a_result_or_one_input_error(slam_parts, parts):
    from ti_cmax.pipelines.slam import OnlineSlam

    camera, cfg = slam_parts
    slam = OnlineSlam(camera, cfg)
    try:
        for ev in parts:
            slam.push(ev)
        result = slam.close()
    except InputError as exc:
        assert "\n" not in str(exc)
        event("InputError")
        return
    event("result")
    assert len(result.trajectory) >= 1 and np.isfinite(result.trajectory.R).all()
    assert np.isfinite(result.map).all()


# ------------------------------------------------------------------------------------------------
# the message- and packet-based formats: ROS1 bags, AEDAT4, Prophesee RAW
FEW = settings(max_examples=20, deadline=None, derandomize=True,
               suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
T_SEC = [0, 1, 1_600_000_000, 2**32 - 1]  # ROS time seconds: start of the epoch, a real date, the last one
PIXELS = st.one_of(st.integers(0, W - 1), st.sampled_from([W, 2047, 32767, 65535]))


def read_all_or_input_error(path, time_range=True, **kw):
    """read_or_input_error, then the reader's event count and time range (the info command's figures): InputError
    or the figures of the events read."""
    ev = read_or_input_error(path, **kw)
    try:
        ds = open_dataset(path, allow_default_calibration=True, **kw)
        n, (t0, t1) = ds.num_events(), ds.time_range()
    except InputError as exc:
        assert "\n" not in str(exc)
        return ev
    if ev is not None:
        assert n == len(ev)
        if time_range and len(ev):
            assert (t0, t1) == pytest.approx((ev.t[0], ev.t[-1]), abs=1e-9, rel=1e-12)
    return ev


@st.composite
def damage(draw):
    """A cut (fraction of the length kept, None: whole) and up to 4 (fraction of the position, new byte) flips."""
    cut = draw(st.one_of(st.none(), st.floats(0, 1)))
    flips = draw(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)), max_size=4))
    return cut, flips


def damaged(data: bytes, cut, flips, start: int = 0) -> bytes:
    """``data`` with bytes at or after ``start`` replaced, then cut."""
    b = bytearray(data)
    for where, value in flips:
        b[start + int(where * (len(b) - start))] = value
    return bytes(b if cut is None else b[:int(cut * len(b))])


# ROS1 bags: EventArray messages serialized by hand (so any field value, or a malformed message, can be written)
@st.composite
def event_array_messages(draw):
    """1-3 raw dvs_msgs/EventArray messages: times sorted or not, nanoseconds beyond 1e9, pixels beyond the sensor,
    polarity bytes other than 0/1, odd sizes in the message; sometimes a message cut short or with a count or a
    frame_id length that overruns it."""
    out, sec = [], draw(st.sampled_from(T_SEC))
    for k in range(draw(st.integers(1, 3))):
        n = draw(st.integers(0, 30))
        rec = np.zeros(n, dtype=[("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("p", "u1")])
        rec["x"] = draw(st.lists(PIXELS, min_size=n, max_size=n))
        rec["y"] = draw(st.lists(st.integers(0, H - 1), min_size=n, max_size=n))
        secs = sec + np.cumsum(draw(st.lists(st.integers(0, 1), min_size=n, max_size=n)), dtype=np.int64)
        rec["sec"] = np.minimum(secs if draw(st.booleans()) else secs[::-1], 2**32 - 1)
        rec["nsec"] = draw(st.lists(st.one_of(st.integers(0, 10**9 - 1), st.sampled_from([10**9, 2**32 - 1])),
                                    min_size=n, max_size=n))
        rec["p"] = draw(st.lists(st.sampled_from([0, 1, 1, 2, 255]), min_size=n, max_size=n))
        h, w = draw(st.sampled_from([(H, W), (H, W), (0, 0), (1, 1), (65535, 65535)]))
        frame_id = b"dvs" * (k % 2)
        count, flen, cut = n, len(frame_id), 0
        fault = draw(st.sampled_from([None] * 6 + ["count", "frame_id", "cut"]))
        if fault == "count":
            count = draw(st.sampled_from([n + 1, 2**32 - 1]))
        elif fault == "frame_id":
            flen = draw(st.sampled_from([len(frame_id) + 100, 2**32 - 1]))
        raw = (struct.pack("<IIII", k, int(sec), 0, flen) + frame_id + struct.pack("<III", h, w, count)
               + rec.tobytes())
        if fault == "cut":
            cut = draw(st.integers(1, len(raw)))
        out.append(raw[:len(raw) - cut])
        sec = int(rec["sec"].max()) if n else sec
    return out


def write_raw_bag(path, store, messages, log_times, camera_info=None):
    """A ROS1 bag of raw EventArray messages on /dvs/events (and an optional CameraInfo on /dvs/camera_info)."""
    from rosbags import rosbag1

    path.unlink(missing_ok=True)  # the writer refuses to overwrite (hypothesis reuses tmp_path)
    with rosbag1.Writer(path) as w:
        conn = w.add_connection("/dvs/events", "dvs_msgs/msg/EventArray", typestore=store)
        for raw, t in zip(messages, log_times):
            w.write(conn, t, raw)
        if camera_info is not None:
            c2 = w.add_connection("/dvs/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
            w.write(c2, log_times[0], store.serialize_ros1(camera_info, "sensor_msgs/msg/CameraInfo"))
    return path


def camera_info_message(store, fx, width, height):
    T = store.types
    K = np.array([fx, 0, 119.5, 0, fx, 89.5, 0, 0, 1], float)
    return T["sensor_msgs/msg/CameraInfo"](
        header=T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="dvs"),
        height=height, width=width, distortion_model="plumb_bob", D=np.zeros(5), K=K, R=np.eye(3).ravel(),
        P=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


@FEW
@given(messages=event_array_messages(), log_order=st.sampled_from(["sorted", "reversed", "same"]),
       fx=st.sampled_from([None, 200.0, 0.0, -1.0, math.nan, math.inf, 1e300]),
       ci_size=st.sampled_from([(W, H), (0, 0), (2 * W, H)]))
def test_bag_reader_returns_valid_events_or_one_input_error(tmp_path, ros1_store, messages, log_order, fx, ci_size):
    log_times = [10**9 * (k + 1) for k in range(len(messages))]
    log_times = {"sorted": log_times, "reversed": log_times[::-1], "same": [10**9] * len(messages)}[log_order]
    ci = None if fx is None else camera_info_message(ros1_store, fx, *ci_size)
    path = write_raw_bag(tmp_path / "ev.bag", ros1_store, messages, log_times, ci)
    read_all_or_input_error(path, time_range=False)  # a bag's time range comes from its log times
    try:
        cam = open_dataset(path, allow_default_calibration=True).camera
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    assert np.isfinite(cam.K).all() and cam.fx > 0 and cam.fy > 0


@pytest.fixture(scope="module")
def valid_bag(tmp_path_factory, write_ros1_bag):
    from ti_cmax.camera import Camera

    n = 300
    ev = Events(10.0 + 1e-3 * np.arange(n), np.arange(n) % W, np.arange(n) % H, np.arange(n) % 2)
    path = write_ros1_bag(tmp_path_factory.mktemp("bag") / "ok.bag", ev, Camera(W, H, 200, 200, 119.5, 89.5),
                          per_msg=100)
    return path.read_bytes()


@FEW
@given(dmg=damage())
@example(dmg=(None, [(0.53125, 0)]))  # a record header without 'op': rosbags' ReaderError while reading messages
@example(dmg=(None, [(0.53125, 255)]))  # a UnicodeDecodeError while reading messages
@example(dmg=(None, [(0.875, 255)]))  # "Header could not be read from file" in the index
@example(dmg=(None, [(0.890625, 0)]))  # a damaged message definition: rosbags' error quotes it over many lines
def test_damaged_bag_gives_valid_events_or_one_input_error(tmp_path, valid_bag, dmg):
    path = tmp_path / "ev.bag"
    path.write_bytes(damaged(valid_bag, *dmg))
    read_all_or_input_error(path, time_range=False)


# AEDAT4: header and EventPacket flatbuffers written by hand, uncompressed (the layout of iniVation's schemas)
def _pad(b: bytes, align: int) -> bytes:
    return b + b"\0" * (-len(b) % align)


def aedat4_bytes(packets, width=W, height=H) -> bytes:
    """An AEDAT4 file: magic line, IOHeader (compression none, no data table, the XML description of one event
    stream of ``width`` x ``height``), then each EventPacket (records t i64, x i16, y i16, on u8) on stream 0."""
    desc = (f'<dv version="2.0"><node name="outInfo" path="/"><node name="0" path="/0/">'
            f'<attr key="typeIdentifier" type="string">EVTS</attr><node name="info" path="/0/info/">'
            f'<attr key="sizeX" type="int">{width}</attr><attr key="sizeY" type="int">{height}</attr>'
            f'</node></node></node></dv>').encode()
    # root offset, identifier, vtable (3 fields), table at 24: vtable offset, compression, position, string offset
    hdr = _pad(struct.pack("<I", 24) + b"IOHE" + struct.pack("<5H", 10, 20, 4, 8, 16), 8)
    hdr = _pad(hdr + struct.pack("<iiqI", 16, 0, -1, 4) + struct.pack("<I", len(desc)) + desc + b"\0", 4)
    out = b"#!AER-DAT4.0\r\n" + struct.pack("<I", len(hdr)) + hdr
    for t, x, y, on in packets:
        rec = np.zeros(len(t), dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("on", "u1"), ("pad", "V3")])
        rec["t"], rec["x"], rec["y"], rec["on"] = t, x, y, on
        # root offset, identifier, vtable (1 field), table at 16: vtable offset, vector offset; vector at 28
        fb = struct.pack("<I", 16) + b"EVTS" + struct.pack("<3H", 6, 8, 4) + b"\0\0" + struct.pack("<iI", 8, 8)
        fb += struct.pack("<I", len(rec)) + rec.tobytes()
        out += struct.pack("<II", 0, len(fb) + 4) + struct.pack("<I", len(fb)) + fb
    return out


@st.composite
def aedat4_packets(draw):
    """1-3 event packets: times (us, int64) sorted or not, negative or huge; pixels negative or beyond the sensor;
    'on' bytes other than 0/1."""
    out, t0 = [], draw(st.sampled_from([0, 1_633_953_629_213_182, -5, 2**63 - 100]))
    for _ in range(draw(st.integers(1, 3))):
        n = draw(st.integers(0, 30))
        t = t0 + np.cumsum(draw(st.lists(st.integers(0, 1000), min_size=n, max_size=n)), dtype=np.int64)
        if draw(st.integers(0, 3)) == 0:
            t = t[::-1]
        x = draw(st.lists(st.one_of(st.integers(0, W - 1), st.sampled_from([W, -1, 32767])), min_size=n, max_size=n))
        y = draw(st.lists(st.one_of(st.integers(0, H - 1), st.sampled_from([H, -32768])), min_size=n, max_size=n))
        on = draw(st.lists(st.sampled_from([0, 1, 1, 2, 255]), min_size=n, max_size=n))
        out.append((t, x, y, on))
        t0 = int(t.max()) if n else t0
    return out


def _read_aedat4(path):
    ev = read_all_or_input_error(path)
    if ev is not None:  # AEDAT4 times are microseconds since the epoch, never negative
        assert (ev.t >= 0).all()


@FEW
@given(packets=aedat4_packets(), size=st.sampled_from([(W, H), (W, H), (0, 0), (1, 65535)]))
def test_aedat4_reader_returns_valid_events_or_one_input_error(tmp_path, packets, size):
    pytest.importorskip("aedat")
    path = tmp_path / "ev.aedat4"
    path.write_bytes(aedat4_bytes(packets, *size))
    _read_aedat4(path)


@FEW
@given(dmg=damage(), in_header=st.booleans())
@example(dmg=(None, [(0.0, 0x38)]), in_header=True)  # header size 4 short: a packet shorter than a flatbuffer
def test_damaged_aedat4_gives_valid_events_or_one_input_error(tmp_path, dmg, in_header):
    """Damage anywhere, or in the IOHeader only (whose flatbuffer and XML aedat parses without checks: a damaged
    one must be refused before aedat sees it, or its panic aborts the process)."""
    pytest.importorskip("aedat")
    n = 40
    good = aedat4_bytes([(np.arange(n) * 100 + 5, np.arange(n), np.arange(n), np.arange(n) % 2)] * 2)
    path = tmp_path / "ev.aedat4"
    header_end = 18 + struct.unpack_from("<I", good, 14)[0]
    cut, flips = dmg
    if in_header:
        flips = [(where * (header_end - 14) / (len(good) - 14), v) for where, v in flips]
    path.write_bytes(damaged(good, cut, flips, start=14))
    _read_aedat4(path)


def test_aedat4_header_not_utf8_is_refused_before_aedat_reads_it(tmp_path):
    """aedat reads the XML description as UTF-8 without checking it, and a byte such as 0xd5 inside makes its XML
    parser panic and abort the process: the reader refuses the header first. Run in a child process, so a
    regression fails this test instead of ending the test session."""
    pytest.importorskip("aedat")
    import subprocess
    import sys

    good = aedat4_bytes([(np.arange(5), np.arange(5), np.arange(5), np.arange(5) % 2)])
    bad = bytearray(good)
    bad[good.index(b"typeIdentifier") + 2] = 0xD5
    path = tmp_path / "ev.aedat4"
    path.write_bytes(bytes(bad))
    code = ("import sys\nfrom ti_cmax.errors import InputError\nfrom ti_cmax.io.aedat4 import Aedat4Source\n"
            "try:\n    Aedat4Source(sys.argv[1])\nexcept InputError as exc:\n    print(exc)\n")
    run = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "corrupt header" in run.stdout and "not well-formed XML" in run.stdout


# Prophesee RAW EVT 2.0 / 3.0, encoded as in test_io_prophesee
@st.composite
def raw_recordings(draw):
    """(version, width, height, t, x, y, p, trailing words): times sorted or not and beyond the 24-bit EVT 3.0 and
    34-bit EVT 2.0 clocks, pixels beyond the header's size, random words after the events."""
    version = draw(st.sampled_from(["2.0", "3.0"]))
    width, height = draw(st.sampled_from([(W, H), (W, H), (1, 1), (2048, 2048), (0, 0)]))
    n = draw(st.integers(0, 40))
    t = draw(st.sampled_from([0, 16_777_000, 2**34 - 50])) + np.cumsum(
        draw(st.lists(st.integers(0, 5000), min_size=n, max_size=n)), dtype=np.int64)
    if draw(st.integers(0, 3)) == 0:
        t = t[::-1]
    x = np.array(draw(st.lists(st.one_of(st.integers(0, W - 1), st.sampled_from([W, 2047])), min_size=n,
                               max_size=n)), np.uint16)
    y = np.array(draw(st.lists(st.one_of(st.integers(0, H - 1), st.sampled_from([H, 2047])), min_size=n,
                               max_size=n)), np.uint16)
    p = np.array(draw(st.lists(st.integers(0, 1), min_size=n, max_size=n)), np.uint16)
    words = draw(st.lists(st.integers(0, 2**32 - 1), max_size=6))
    return version, width, height, t.astype(np.uint64) & np.uint64(2**34 - 1), x, y, p, words


@FEW
@given(rec=raw_recordings())
def test_raw_reader_returns_valid_events_or_one_input_error(tmp_path, rec):
    pytest.importorskip("faery")
    from test_io_prophesee import encode_evt2, encode_evt3, header

    version, width, height, t, x, y, p, words = rec
    encode, word = (encode_evt2, "<u4") if version == "2.0" else (encode_evt3, "<u2")
    data = encode(t, x, y, p) if len(t) else b""
    path = tmp_path / "ev.raw"
    path.write_bytes(header(version, width, height) + data + np.array(words).astype(word).tobytes())
    read_all_or_input_error(path)


@FEW
@given(dmg=damage(), version=st.sampled_from(["2.0", "3.0"]))
def test_damaged_raw_gives_valid_events_or_one_input_error(tmp_path, dmg, version):
    pytest.importorskip("faery")
    from test_io_prophesee import encode_evt2, encode_evt3, header

    n = 60
    t, x, y, p = (np.arange(n, dtype=np.uint64) * 977, np.arange(n) % W, np.arange(n) % H, np.arange(n) % 2)
    good = header(version, W, H) + (encode_evt2 if version == "2.0" else encode_evt3)(t, x, y, p)
    path = tmp_path / "ev.raw"
    path.write_bytes(damaged(good, *dmg))
    read_all_or_input_error(path)


# ------------------------------------------------------------------------------------------------
# calibration (calib.txt, camera_info YAML) and the small tables (TUM, imu.txt, angular velocity)
yaml_value = st.one_of(numbers, st.sampled_from([".inf", "-.inf", ".nan", "1.0e+400", "[]", "{}", "null", "~", "[1, 2]",
                                                 "'200'", "!!binary AA==", "&a 1", "*a", "[1, 2, 3, 4, 5, 6, 7, 8, 9]",
                                                 "{data: 3}", "- 1"]))
yaml_line = st.one_of(
    st.builds(lambda k, v: f"{k}: {v}", st.sampled_from(["image_width", "image_height", "distortion_model",
                                                        "camera_name", "rows", "other"]), yaml_value),
    st.builds(lambda k, v: f"{k}:\n  data: {v}", st.sampled_from(["camera_matrix", "distortion_coefficients"]),
              st.one_of(yaml_value, st.lists(numbers, max_size=10).map(lambda v: "[" + ", ".join(v) + "]"))),
    st.sampled_from(["distortion_model: rational_polynomial", "distortion_model: equidistant", "\t: x", "key: [1, 2",
                     "'unclosed", "%YAML 1.1", "---", "...", "? a", "\xff\xfe", "a: b: c"]),
)
def check_calib(path, size):
    """read_calib gives a camera with a positive size and finite, positive focal lengths, or one InputError line
    naming the file."""
    from ti_cmax.io import read_calib

    try:
        cam = read_calib(path, *size)
    except InputError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert cam.width > 0 and cam.height > 0 and np.isfinite(cam.K).all() and cam.fx > 0 and cam.fy > 0


GOOD_YAML = ["image_width: 240", "image_height: 180", "camera_matrix:\n  data: [200, 0, 119.5, 0, 200, 89.5, 0, 0, 1]",
             "distortion_model: plumb_bob", "distortion_coefficients:\n  data: [0, 0, 0, 0, 0]"]


@FEW
@given(lines=st.lists(st.one_of(yaml_line, st.sampled_from(GOOD_YAML)), min_size=0, max_size=8),
       raw_bytes=st.binary(max_size=8), size=st.sampled_from([(None, None), (W, H), (0, 0)]))
@example(lines=["image_width: .inf", GOOD_YAML[2]], raw_bytes=b"", size=(None, None))  # int(inf): OverflowError
def test_camera_info_yaml_gives_a_camera_or_one_input_error(tmp_path, lines, raw_bytes, size):
    path = tmp_path / "camera.yaml"
    path.write_bytes("\n".join(lines).encode("utf-8", "surrogatepass") + b"\n" + raw_bytes)
    check_calib(path, size)


@FEW
@given(lines=st.lists(st.one_of(st.lists(numbers, min_size=0, max_size=9).map(" ".join), odd_line), max_size=4),
       size=st.sampled_from([(None, None), (W, H)]))
@example(lines=["2 1 0 271"], size=(W, H))  # intrinsics that do not fit the sensor: the error names the file
def test_calib_txt_gives_a_camera_or_one_input_error(tmp_path, lines, size):
    path = tmp_path / "calib.txt"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    check_calib(path, size)


@FEW
@given(kind=st.sampled_from(["tum", "imu", "angular_velocity"]),
       rows=st.lists(st.one_of(st.lists(numbers, min_size=3, max_size=9).map(" ".join), odd_line), max_size=6),
       sort=st.booleans())
def test_tables_give_sorted_finite_values_or_one_input_error(tmp_path, kind, rows, sort):
    from ti_cmax.io import read_angular_velocity, read_imu_txt, read_tum

    path = tmp_path / f"{kind}.txt"
    path.write_text("\n".join(sorted(rows) if sort else rows) + "\n", encoding="utf-8")
    try:
        if kind == "tum":
            traj = read_tum(path)
            t, values = traj.t, traj.R
            assert np.allclose(traj.R @ np.swapaxes(traj.R, 1, 2), np.eye(3), atol=1e-9)
        elif kind == "imu":
            imu = read_imu_txt(path)
            t, values = imu.t, np.column_stack([imu.acc, imu.gyro])
        else:
            t, values = read_angular_velocity(path)
    except InputError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    assert len(t) == len(values) >= 1 and np.isfinite(t).all() and (np.diff(t) >= 0).all()
    assert np.isfinite(values).all()

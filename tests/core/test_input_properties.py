"""Property-based tests (hypothesis) of the readers and of OnlineSlam.push: random and adversarial inputs end in a
valid result or one InputError, never another exception. Examples are few and small: the whole file runs in
seconds."""
from __future__ import annotations

import math

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
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

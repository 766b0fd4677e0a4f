"""Prophesee RAW (EVT 2.0 / 3.0, decoded by faery) and Metavision HDF5 (CD/events) readers.

The RAW files are written by tiny encoders here, from Prophesee's published word layouts (so the decoder is
checked against the format, not only against itself), and by faery's own encoder.
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from ti_cmax.cli import main
from ti_cmax.errors import InputError
from ti_cmax.io import open_dataset

faery = pytest.importorskip("faery")


def random_events(n, width, height, t_end_us, seed=0):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, t_end_us, n)).astype(np.uint64)
    return t, rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n)


def header(version: str, width: int, height: int) -> bytes:
    fmt = {"2.0": "EVT2", "3.0": "EVT3"}[version]
    return (f"% camera_integrator_name Prophesee\n% evt {version}\n% format {fmt};height={height};width={width}\n"
            f"% geometry {width}x{height}\n% end\n").encode()


def encode_evt2(t, x, y, p) -> bytes:
    """EVT 2.0: 32-bit words, type in bits 31-28; CD_OFF 0 / CD_ON 1 carry t[5:0] (27-22), x (21-11), y (10-0);
    EVT_TIME_HIGH 8 carries t[33:6], written before the first event of each new value."""
    t = t.astype(np.uint64)
    th = t >> np.uint64(6)
    new = np.r_[True, th[1:] != th[:-1]]
    cd = (p.astype(np.uint64) << 28) | ((t & np.uint64(63)) << 22) | (x.astype(np.uint64) << 11) | y.astype(np.uint64)
    pos = np.arange(len(t)) + np.cumsum(new)
    words = np.empty(len(t) + int(new.sum()), np.uint32)
    words[pos] = cd
    words[pos[new] - 1] = (np.uint64(8) << 28) | (th[new] & np.uint64(0x0FFFFFFF))
    return words.astype("<u4").tobytes()


def encode_evt3(t, x, y, p) -> bytes:
    """EVT 3.0: 16-bit words, type in bits 15-12: EVT_TIME_HIGH 8 (t[23:12]), EVT_TIME_LOW 6 (t[11:0]),
    EVT_ADDR_Y 0 (y), EVT_ADDR_X 2 (polarity bit 11, x): one group of four words per event. The 24-bit time
    wraps; the decoder counts the wraps."""
    t = t.astype(np.uint64)
    words = np.empty((len(t), 4), np.uint16)
    words[:, 0] = (8 << 12) | ((t >> np.uint64(12)) & np.uint64(0xFFF))
    words[:, 1] = (6 << 12) | (t & np.uint64(0xFFF))
    words[:, 2] = y
    words[:, 3] = (2 << 12) | (p.astype(np.uint16) << 11) | x
    return words.astype("<u2").tobytes()


def check_events(ds, t, x, y, p, chunk=1000):
    chunks = list(ds.iter_events(chunk))
    assert len(chunks) == -(-len(t) // chunk) and all(len(c) == chunk for c in chunks[:-1])
    ev = ds.read_events()
    np.testing.assert_array_equal(np.round(ev.t * 1e6).astype(np.uint64), t)
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.p, np.where(p > 0, 1, -1))


@pytest.mark.parametrize("version, encode", [("2.0", encode_evt2), ("3.0", encode_evt3)])
def test_raw_from_the_published_layout(tmp_path, version, encode):
    # 640x480 in the header, though the pixels would also fit the smaller DAVIS346: the header wins
    t, x, y, p = random_events(5000, 340, 250, 20_000_000)  # 20 s: crosses the 24-bit (16.8 s) wrap of EVT 3.0
    path = tmp_path / "rec.raw"
    path.write_bytes(header(version, 640, 480) + encode(t, x, y, p))
    ds = open_dataset(path)
    assert (ds.width, ds.height, ds.size_source, ds.format) == (640, 480, "Prophesee RAW file", "Prophesee RAW")
    assert ds.num_events() == 5000
    assert ds.time_range() == pytest.approx((t[0] * 1e-6, t[-1] * 1e-6))
    check_events(ds, t, x, y, p)


def test_evt3_vectorized_events(tmp_path):
    """EVT 3.0 vectors: VECT_BASE_X (type 3: polarity bit 11, x base) then VECT_12 (type 4) and VECT_8 (type 5)
    masks; bit i of a mask is an event at x = base + i, and the base advances by the mask's width."""
    m12, m8 = 0b101000000011, 0b10010001
    words = [(8 << 12) | 0x001, (6 << 12) | 0x234, 37, (3 << 12) | (1 << 11) | 100, (4 << 12) | m12, (5 << 12) | m8,
             (3 << 12) | 500, (5 << 12) | 0b1]  # then an OFF vector at x = 500
    path = tmp_path / "vec.raw"
    path.write_bytes(header("3.0", 640, 480) + np.array(words, "<u2").tobytes())
    ev = open_dataset(path).read_events()
    xs = [100 + i for i in range(12) if m12 >> i & 1] + [112 + i for i in range(8) if m8 >> i & 1] + [500]
    np.testing.assert_array_equal(ev.x, xs)
    np.testing.assert_array_equal(ev.y, 37)
    np.testing.assert_array_equal(ev.p, [1] * (len(xs) - 1) + [-1])
    np.testing.assert_allclose(ev.t, 0x001234 * 1e-6)


@pytest.mark.parametrize("version", ["evt2", "evt3"])
def test_raw_round_trip_through_faery(tmp_path, version):
    t, x, y, p = random_events(20000, 1280, 720, 3_000_000, seed=1)
    rec = np.zeros(len(t), dtype=faery.EVENTS_DTYPE)
    rec["t"], rec["x"], rec["y"], rec["on"] = t, x, y, p.astype(bool)
    path = tmp_path / f"{version}.raw"
    with faery.evt.Encoder(str(path), version, False, (1280, 720), True) as enc:
        enc.write({"events": rec})
    ds = open_dataset(path)
    assert ds.sensor_size == (1280, 720)
    check_events(ds, t, x, y, p, chunk=3000)
    sliced = ds.read_events(1.0, 2.0)
    assert len(sliced) == int(((t >= 1e6) & (t < 2e6)).sum())


def test_raw_folder_and_convert(tmp_path, capsys):
    t, x, y, p = random_events(3000, 1280, 720, 1_000_000, seed=2)
    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "recording.raw").write_bytes(header("3.0", 1280, 720) + encode_evt3(t, x, y, p))
    assert main(["info", str(folder), "--json"]) == 0
    assert '"width": 1280' in capsys.readouterr().out
    out = tmp_path / "out.h5"
    assert main(["convert", str(folder), str(out)]) == 0
    ds = open_dataset(out)
    assert ds.sensor_size == (1280, 720) and ds.num_events() == 3000


@pytest.mark.parametrize("damage, message", [
    (lambda data: data[:-1], "truncated EVT3 data: the file ends 1 byte"),  # cut inside a 2-byte word
    (lambda data: data[data.index(b"% end\n") + 6:], "no '% ...' header"),  # header stripped
    (lambda data: data[:20], "RAW header is cut"),  # cut inside the header
    (lambda data: b"", "no '% ...' header"),
])
def test_bad_raw_gives_one_error_and_no_output(tmp_path, capsys, damage, message):
    t, x, y, p = random_events(500, 1280, 720, 100_000, seed=3)
    path = tmp_path / "bad.raw"
    path.write_bytes(damage(header("3.0", 1280, 720) + encode_evt3(t, x, y, p)))
    with pytest.raises(InputError, match=message):
        open_dataset(path)
    out = tmp_path / "out" / "bad.h5"
    for cmd in (["info", str(path)], ["convert", str(path), str(out)]):
        assert main(cmd) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"ti-cmax {cmd[0]}: error: ") and message in err[0]
    assert not out.exists() and (not out.parent.exists() or list(out.parent.iterdir()) == [])


def test_raw_truncated_evt2(tmp_path):
    t, x, y, p = random_events(500, 1280, 720, 100_000, seed=4)
    path = tmp_path / "bad.raw"
    path.write_bytes((header("2.0", 1280, 720) + encode_evt2(t, x, y, p))[:-3])
    with pytest.raises(InputError, match="truncated EVT2 data: the file ends 1 byte"):
        open_dataset(path)


def _metavision_h5(path, t, x, y, p, **kw):
    rec = np.zeros(len(t), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    rec["x"], rec["y"], rec["p"], rec["t"] = x, y, p, t
    with h5py.File(path, "w") as f:
        f.attrs["geometry"] = "1280x720"
        f.create_dataset("CD/events", data=rec, chunks=(1000,), maxshape=(None,), **kw)


def test_metavision_hdf5_layout(tmp_path):
    t, x, y, p = random_events(4500, 1280, 720, 2_000_000, seed=5)
    path = tmp_path / "rec.hdf5"
    _metavision_h5(path, t.astype(np.int64), x, y, p, compression="gzip")
    ds = open_dataset(path)
    assert ds.sensor_size == (1280, 720) and ds.format == "Metavision HDF5"
    check_events(ds, t, x, y, p)
    assert len(ds.read_events(0.5, 1.0)) == int(((t >= 5e5) & (t < 1e6)).sum())


def test_metavision_hdf5_without_ecf_codec(tmp_path, capsys):
    from ti_cmax.io.h5 import ECF_FILTER

    if h5py.h5z.filter_avail(ECF_FILTER):
        pytest.skip("the ECF plugin is installed here")
    path = tmp_path / "ecf.hdf5"
    rec = np.zeros(10, dtype=[("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    with h5py.File(path, "w") as f:  # the filter is optional, so HDF5 stores the data raw but records the filter
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk((10,))
        dcpl.set_filter(ECF_FILTER, h5py.h5z.FLAG_OPTIONAL)
        space = h5py.h5s.create_simple((10,), (h5py.h5s.UNLIMITED,))
        f.create_group("CD")
        h5py.h5d.create(f["CD"].id, b"events", h5py.h5t.py_create(rec.dtype), space, dcpl=dcpl)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ECF codec" in err[0] and "HDF5_PLUGIN_PATH" in err[0]

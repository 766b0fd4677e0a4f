"""Re-chunking of the readers' blocks (io._common.validated_chunks): chunks of exactly chunk_size events in stream
order, and only the chunks that straddle two blocks are copies (a reader's blocks are large; copying each one whole
at every border would add a copy per event to reading, a real-time cost at VGA rates)."""
from __future__ import annotations

import weakref

import h5py
import numpy as np
import pytest

from ti_cmax.errors import InputError
from ti_cmax.events import EventBuffer, Events
from ti_cmax.io import open_dataset, write_events_h5
from ti_cmax.io._common import Block, validated_chunks
from ti_cmax.io.h5 import EventsH5Writer, H5Events


def test_chunks_are_exact_ordered_and_views_inside_a_block():
    sizes = [7, 25, 3, 40, 10, 1]
    t = np.arange(sum(sizes), dtype=float) * 1e-6
    blocks, start = [], 0
    for n in sizes:
        sl = slice(start, start + n)
        blocks.append(Block(Events(t[sl].copy(), np.full(n, 1, np.uint16), np.full(n, 2, np.uint16),
                                   np.ones(n, np.int8)), None, start))
        start += n
    chunks = list(validated_chunks(iter(blocks), "test", 4, 4, chunk_size=10))
    assert [len(c) for c in chunks] == [10] * 8 + [6]
    np.testing.assert_array_equal(np.concatenate([c.t for c in chunks]), t)
    # chunk 1 holds events 10..19, inside the second block (7..31): a view of it; chunk 0 straddles two blocks
    assert np.shares_memory(chunks[1].t, blocks[1].events.t)
    assert not np.shares_memory(chunks[0].t, blocks[0].events.t)
    assert np.shares_memory(chunks[4].t, blocks[3].events.t)  # events 40..49 of the block 35..74


@pytest.mark.parametrize("bad, message", [
    (lambda t, x: t.__setitem__(20, np.nan), "event 20: timestamp is not a finite number"),
    (lambda t, x: t.__setitem__(39, np.inf), "event 39: timestamp is not a finite number"),
    (lambda t, x: t.__setitem__(17, t[16] - 1e-6), "event 17: timestamps are not sorted"),
    (lambda t, x: x.__setitem__(33, 4), "event 33: x=4 is outside the sensor"),
])
def test_one_bad_event_inside_a_block_is_named(bad, message):
    """Good blocks pass with one comparison per column (finite ends and non-decreasing steps: every time is finite);
    a NaN or an infinity inside, a step back or a pixel off the sensor is still found and named."""
    n = 40
    t, x = np.arange(n, dtype=float) * 1e-6, np.full(n, 1, np.uint16)
    bad(t, x)
    block = Block(Events(t, x, np.full(n, 2, np.uint16), np.ones(n, np.int8)), None, 0)
    with pytest.raises(InputError, match=message):
        list(validated_chunks(iter([block]), "test", 4, 4, chunk_size=10))


def test_hdf5_chunks_are_read_only_views_that_a_buffer_borrows(tmp_path):
    """The HDF5 reader's chunks are read-only views of its blocks (nothing else holds them): an ``EventBuffer`` fed
    with them in order is a range of the block, not a copy."""
    n = 5000
    t = np.arange(n, dtype=float) * 1e-5
    write_events_h5(tmp_path / "ev.h5", Events(t, np.arange(n) % 8, np.arange(n) % 6, np.ones(n, np.int8)),
                    width=8, height=6)
    chunks = list(open_dataset(tmp_path / "ev.h5", allow_default_calibration=True).iter_events(1000))
    assert all(not getattr(c, f).flags.writeable for c in chunks for f in "txyp")
    buf = EventBuffer()
    for c in chunks:
        buf.push(c)
        buf.drop(300)
    view = buf.view()
    np.testing.assert_array_equal(view.t, t[5 * 300:])
    assert all(getattr(view, f).base is getattr(chunks[0], f).base is not None for f in "txyp")  # one block


def test_hdf5_blocks_reuse_their_arrays_once_nothing_looks_at_them(tmp_path):
    """Block after block the HDF5 reader fills the same arrays again (no fresh memory per block) when the previous
    blocks' events are no longer looked at; a block still looked at keeps its events."""
    n = 5000
    t = np.arange(n, dtype=float) * 1e-5
    p = np.where(np.arange(n) % 3 == 0, 1, -1).astype(np.int8)
    write_events_h5(tmp_path / "ev.h5", Events(t, np.arange(n) % 8, np.arange(n) % 6, p), width=8, height=6)
    reader = H5Events(tmp_path / "ev.h5")
    arrays, kept, k = [], None, -1
    for block in reader.iter_blocks(block=1000):  # (enumerate would hold the last block while reading the next)
        k += 1
        ev = block.events
        np.testing.assert_array_equal(ev.t, t[1000 * k:1000 * (k + 1)])
        np.testing.assert_array_equal(ev.p, p[1000 * k:1000 * (k + 1)])
        arrays.append(weakref.ref(ev.t if ev.t.base is None else ev.t.base))
        if k == 1:
            kept = ev  # looked at until the end
        del block, ev
        if k == 4:  # the reader still runs
            alive = [a for a in (ref() for ref in arrays) if a is not None]
            assert len({id(a) for a in alive}) < len(alive)  # one set of arrays held several blocks
    np.testing.assert_array_equal(kept.t, t[1000:2000])


@pytest.mark.parametrize("compression", [None, "gzip"])
def test_hdf5_blocks_read_chunk_by_chunk_equal_the_stored_events(tmp_path, monkeypatch, compression):
    """Unfiltered chunks are read as stored (whole chunks straight into the block, those cut by a block's border
    through a staging array), not through HDF5's selections; compressed ones through HDF5's filters: the same
    events either way."""
    n = 5000
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 1, n))
    ev = Events(t, rng.integers(0, 8, n), rng.integers(0, 6, n), rng.choice([-1, 1], n).astype(np.int8))
    with EventsH5Writer(tmp_path / "ev.h5", width=8, height=6, chunk_events=64, compression=compression) as w:
        w.append(ev)
    selections = []
    read_direct = h5py.Dataset.read_direct
    monkeypatch.setattr(h5py.Dataset, "read_direct", lambda *a, **k: selections.append(a[2]) or read_direct(*a, **k))
    blocks = list(H5Events(tmp_path / "ev.h5").iter_blocks(block=1000))
    assert (len(selections) > 0) == (compression is not None)
    got = Events.concatenate([Events(*(getattr(b.events, f).copy() for f in "txyp")) for b in blocks])
    for f in "txyp":
        np.testing.assert_array_equal(getattr(got, f), getattr(ev, f))

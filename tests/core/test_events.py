"""EventBuffer (ti_cmax.events): a growing run of events whose views stay valid."""
from __future__ import annotations

import numpy as np

from ti_cmax.events import ArrayPool, EventBuffer, Events, read_only_columns


def _events(t0: int, n: int, subpixel: bool = False) -> Events:
    t = np.arange(t0, t0 + n, dtype=float)
    xy = t.astype(np.float32) if subpixel else (t % 100).astype(np.uint16)
    return Events(t, xy, xy, np.where(t % 2 == 0, 1, -1).astype(np.int8))


def test_pushes_drops_and_views_keep_the_stream_and_earlier_views():
    """Pushes of many sizes with drops between them: the view is always the stream from the last drop on, and a view
    taken earlier still holds what it held (the buffer writes past the end or into new arrays only)."""
    buf, first, views = EventBuffer(), 0, []
    t0 = 0
    for k, n in enumerate([5, 1000, 3, 2500, 7, 40, 3000, 1]):
        buf.push(_events(t0, n))
        t0 += n
        buf.drop(n // 2)
        first += n // 2
        view = buf.view()
        np.testing.assert_array_equal(view.t, np.arange(first, t0))
        assert view.x.dtype == np.uint16 and view.p.dtype == np.int8
        views.append((view, view.t.copy()))
    for view, held in views:
        np.testing.assert_array_equal(view.t, held)
    buf.drop(10**9)
    assert len(buf) == 0 and len(buf.view()) == 0
    buf.push(_events(t0, 3, subpixel=True))  # sub-pixel coordinates after integer ones: the columns widen
    assert buf.view().x.dtype == np.float32 and len(buf) == 3


def test_without_views_the_buffer_reuses_its_arrays():
    """A steady stream (push, drop the head, no view kept) moves its live events to the front of the same arrays
    instead of allocating new ones; the events stay the stream's."""
    buf, t0 = EventBuffer(), 0
    buf.push(_events(t0, 4000))
    t0 += 4000
    arrays = buf._cols
    for _ in range(50):
        buf.push(_events(t0, 300))
        t0 += 300
        buf.drop(300)
    assert buf._cols is arrays
    np.testing.assert_array_equal(buf.view().t, np.arange(t0 - 4000, t0))


def test_with_the_last_view_kept_the_buffer_alternates_between_two_sets_of_arrays():
    """A consumer that still holds the previous view when the room runs out (a slicer's last packet): the live
    events go to the spare arrays, whose views are gone, instead of new ones; every view keeps what it held."""
    buf, t0 = EventBuffer(), 0
    buf.push(_events(t0, 4000))
    t0 += 4000
    seen, last = set(), None
    for _ in range(200):
        buf.push(_events(t0, 300))
        t0 += 300
        buf.drop(300)
        if last is not None:
            np.testing.assert_array_equal(last[0].t, last[1])
        view = buf.view()
        last = (view, view.t.copy())
        seen.add(id(buf._cols))
        np.testing.assert_array_equal(view.t, np.arange(t0 - 4000, t0))
    assert len(seen) == 2


def _block(t0: int, n: int) -> Events:
    """A reader's block: fresh arrays, read-only."""
    return read_only_columns(_events(t0, n))


def test_read_only_blocks_are_borrowed_not_copied_and_borrowed_again_after_a_border():
    """Pushes that follow each other in a read-only block make the buffer a range of the block (no copy); a push
    from the next block is copied with the live events, until the drops leave only events of that block: then the
    buffer borrows it. The view is always the stream from the last drop on, and earlier views keep what they held."""
    buf, first, t0, views = EventBuffer(), 0, 0, []
    blocks = [_block(0, 3000), _block(3000, 3000)]
    for block in blocks:
        for i in range(0, 3000, 250):
            buf.push(block[i:i + 250])
            t0 += 250
            buf.drop(len(buf) - 400)  # a slicer keeps the events a next packet may use
            first = t0 - len(buf)
            view = buf.view()
            np.testing.assert_array_equal(view.t, np.arange(first, t0))
            views.append((view, view.t.copy()))
            if block is blocks[0] or i >= 500:  # the second block's events alone are live again
                assert buf._borrowed and all(c is getattr(block, f) for c, f in zip(buf._cols, "txyp"))
    for view, held in views:
        np.testing.assert_array_equal(view.t, held)


def test_writeable_columns_are_copied():
    """Events the caller may still change (writeable, or read-only views of a writeable array) are copied."""
    buf, ev = EventBuffer(), _events(0, 100)
    buf.push(ev[:50])
    ev.t[:50] = -1.0
    np.testing.assert_array_equal(buf.view().t, np.arange(50))
    owner = _events(100, 100)
    shown = Events(*(getattr(owner, f)[:] for f in "txyp"))
    read_only_columns(shown)  # the views only: their owner stays writeable
    buf.push(shown)
    owner.t[:] = -1.0
    np.testing.assert_array_equal(buf.view().t, np.r_[0:50, 100:200])
    assert not buf._borrowed


def test_array_pool_reuses_a_set_once_nothing_looks_at_it():
    """A set still looked at (a view, a caller's reference) is not handed out again: a new set is made, and the pool
    keeps the last ``keep`` sets; a set nothing holds comes back writeable. Sealed sets are read-only."""
    pool = ArrayPool((np.float64, np.int8), 100, keep=2)
    a = pool.take()
    ArrayPool.seal(a)
    assert not a[0].flags.writeable and not a[1].flags.writeable
    view = a[0][10:20]
    del a
    b = pool.take()  # the first set is looked at through ``view``
    assert not np.shares_memory(b[0], view)
    ids = {id(c) for c in b}
    del b
    c = pool.take()  # the second set: nothing holds it
    assert {id(x) for x in c} == ids and c[0].flags.writeable
    del view
    d = pool.take()  # c is held by the caller; the first set is free again
    assert not any(np.shares_memory(x, y) for x, y in zip(c, d))

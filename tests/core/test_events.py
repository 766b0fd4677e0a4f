"""EventBuffer (ti_cmax.events): a growing run of events whose views stay valid."""
from __future__ import annotations

import numpy as np

from ti_cmax.events import EventBuffer, Events


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

"""The hand-over of events to the back-end worker through shared memory (pipelines/worker.py: EventRing,
RingWriter): every event arrives once, in order, whatever the chunking, the wrap-around of the ring or a reader
slower than the writer."""
from __future__ import annotations

import ctypes
import multiprocessing as mp
import time

import numpy as np
import pytest

from ti_cmax.events import Events
from ti_cmax.pipelines.worker import EventRing, RingWriter


def _events(n: int, t0: float = 0.0, subpixel: bool = False, seed: int = 0) -> Events:
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.uniform(0, 1e-6, n))
    xy = (lambda hi: rng.uniform(0, hi, n).astype(np.float32)) if subpixel else \
        (lambda hi: rng.integers(0, hi, n).astype(np.uint16))
    return Events(t, xy(640), xy(480), rng.choice(np.array([-1, 1], np.int8), n))


def _same(a: Events, b: Events) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) and getattr(a, f).dtype == getattr(b, f).dtype
               for f in "txyp")


def _ring(capacity: int, ctx=None) -> tuple:
    buffer = (ctx or mp).RawArray(ctypes.c_uint8, EventRing.nbytes(capacity))
    return buffer, EventRing(buffer, capacity)


def test_the_ring_returns_every_event_in_order_across_its_wrap_around():
    """Chunks of several sizes and both pixel types, through a ring of 1000 events many times over: each comes out
    equal to what went in, the room is freed as events are taken, and reading out of order is refused."""
    _, ring = _ring(1000)
    sent = []
    for k, n in enumerate([300, 600, 999, 1, 450, 1000, 7] * 3):
        ev = _events(n, k, subpixel=k % 2 == 1, seed=k)
        position = ring.put(ev)
        assert ring.free() == 1000 - n
        with pytest.raises(ValueError):
            ring.put(_events(ring.free() + 1))
        if k % 3:
            back = ring.take(position, n, ev.has_subpixel_coordinates)
        else:  # borrowed: the room is held until the block ends
            with ring.borrow(position, n, ev.has_subpixel_coordinates) as back:
                assert _same(back, ev) and ring.free() == 1000 - n
        assert _same(back, ev) and ring.free() == 1000
        sent.append(n)
    assert ring.written == sum(sent)
    a = ring.put(_events(10))
    ring.put(_events(10, 1.0))
    with pytest.raises(RuntimeError, match="out of order"):
        ring.take(a + 10, 10, False)


def _reader(buffer, capacity, inbox, outbox, delay):
    """A slow reader in another process: takes the announced events and sends them back."""
    ring = EventRing(buffer, capacity)
    while True:
        message = inbox.get()
        if message is None:
            outbox.put(None)
            return
        time.sleep(delay)
        outbox.put(ring.take(*message[1:]))


@pytest.mark.parametrize("delay", [0.0, 0.002])
def test_the_writer_hands_over_every_event_in_order_to_a_slower_process(delay):
    """A stream of 60 000 events in chunks of 1 to 9 000 through a ring of 4 096 events to a reader process (forked
    or spawned) that sleeps before each message: the writer waits for room instead of overwriting, announces what it
    wrote before it waits, and the events come back complete, in order, with their pixel types."""
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    buffer, ring = _ring(4096, ctx)
    inbox, outbox = ctx.Queue(), ctx.Queue()
    proc = ctx.Process(target=_reader, args=(buffer, 4096, inbox, outbox, delay), daemon=True)
    proc.start()
    try:
        writer = RingWriter(ring, inbox.put, lambda: None)
        stream = _events(60_000, seed=3)
        rng = np.random.default_rng(4)
        i, pushes = 0, 0
        while i < len(stream):
            n = int(rng.integers(1, 9000))
            writer.write(stream[i:i + n])
            i += n
            pushes += 1
            if pushes % 3 == 0:
                writer.flush()
        subpixel = _events(500, 1.0, subpixel=True, seed=5)
        writer.write(subpixel)  # another pixel type: its own message
        writer.flush()
        inbox.put(None)
        received = []
        while (chunk := outbox.get(timeout=60)) is not None:
            received.append(chunk)
    finally:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.terminate()
    assert _same(received[-1], subpixel)
    assert _same(Events.concatenate(received[:-1]), stream)
    assert writer.blocked_seconds > 0 or delay == 0.0


def test_a_writer_waiting_on_a_reader_that_ended_raises():
    _, ring = _ring(100)
    writer = RingWriter(ring, lambda message: None, lambda: (_ for _ in ()).throw(RuntimeError("reader ended")))
    writer.write(_events(80))
    with pytest.raises(RuntimeError, match="reader ended"):
        writer.write(_events(80))


@pytest.mark.slow
def test_a_small_ring_changes_nothing_in_slam(short_sequence, monkeypatch):
    """The back-end worker fed through a ring of 8 192 events (it wraps around hundreds of times, and the writer waits
    for the worker's windows): every event reaches the map, and the result is the one-process run's."""
    from ti_cmax import so3
    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.pipelines import worker
    from ti_cmax.pipelines.slam import OnlineSlam, run_slam

    ev = short_sequence.events.slice_time(short_sequence.events.t[0], short_sequence.events.t[0] + 0.35)
    cfg = load_config(SlamConfig, None, ["pano_height=256"])
    reference = run_slam(ev, short_sequence.camera, cfg)
    monkeypatch.setattr(worker, "ring_capacity", lambda camera: 8192)
    online = OnlineSlam(short_sequence.camera, cfg, backend_process=True)
    for i in range(0, len(ev), 15_000):
        online.push(ev[i:i + 15_000])
    result = online.close()
    assert result.report["backend"]["events_settled"] == reference.report["backend"]["events_settled"] == len(ev)
    np.testing.assert_allclose(result.map, reference.map, rtol=1e-4, atol=1e-4)
    assert np.max(so3.geodesic_angle(result.trajectory.R, reference.trajectory.R)) < 1e-5
    process = result.report["backend_process"]
    assert process["push_blocked_seconds"] >= process["ring_wait_seconds"] > 0 and process["ring_events"] == 8192


@pytest.mark.parametrize("q", [1, 3])
@pytest.mark.parametrize("distorted", [False, True])
def test_the_backend_reads_the_ring_in_place_as_it_would_read_copies(ti_runtime, q, distorted):
    """Events pushed from the ring (read in place, across its wrap-around, integer or sub-pixel) or as chunks reach
    the back-end's buffer as every q-th event of the stream (backend_event_sample_rate) with its float32 bearing,
    bit for bit as Camera.bearings of the downsampled stream, and the ring's room is freed after each."""
    from ti_cmax import Camera
    from ti_cmax.config import SlamConfig, load_config
    from ti_cmax.pipelines.online_backend import BackendRunner
    from ti_cmax.pipelines.sensor_defaults import resolve_config

    cam = Camera(640, 480, 400.0, 401.0, 319.2, 240.7, (-0.1, 0.02, 0.001, -0.002, 0.0) if distorted else (0.0,))
    config = resolve_config(load_config(SlamConfig, None, [f"backend_event_sample_rate={q}"]), cam)
    _, ring = _ring(1000)
    runner, stream, t0 = BackendRunner(cam, config), [], 0.0
    for k, n in enumerate([300, 600, 999, 1, 450, 1000, 7, 2, 640]):
        ev = _events(n, t0, subpixel=k == 4, seed=k)
        t0 = float(ev.t[-1]) + 1e-6
        stream.append(ev)
        if k == 6:  # a chunk handed over directly (the back-end in the main process)
            runner.push_events(ev)
            continue
        position = ring.put(ev)
        runner.push_ring(ring, position, n, ev.has_subpixel_coordinates)
        assert ring.free() == 1000
    every = Events.concatenate(stream)[::q]
    buffer = runner.backend.events
    assert np.array_equal(buffer.t, every.t)
    assert buffer.b.dtype == np.float32 and np.array_equal(buffer.b, cam.bearings(every.x, every.y).T)
    assert runner.backend.events_until == stream[-1].t[-1] and runner.events_read == sum(len(e) for e in stream)

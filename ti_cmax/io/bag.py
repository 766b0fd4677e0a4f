"""ROS1 bags: ``dvs_msgs/EventArray`` events (plus CameraInfo, Imu and PoseStamped topics when present).

Read with rosbags' AnyReader (no ROS install; message definitions come from the bag, the ROS1 noetic store
is the default). Event arrays are decoded straight from the raw ROS1 message bytes with numpy: header
(seq u32, stamp 2 x u32, frame_id: u32 length + bytes), height u32, width u32, event count u32, then 13 packed
bytes per event (x u16, y u16, ts.sec u32, ts.nsec u32, polarity u8).
"""
from __future__ import annotations

import contextlib

from pathlib import Path
from typing import Iterator

import numpy as np

from ..camera import Camera
from ..errors import InputError, exception_line, missing_extra
from ..events import Events, signed_polarity
from ..trajectory import Trajectory
from ._common import Block, grouped_blocks
from .text import ImuData

EVENT_ARRAY = "dvs_msgs/msg/EventArray"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
POSE = "geometry_msgs/msg/PoseStamped"
_EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("p", "u1")])
assert _EVENT_DTYPE.itemsize == 13


@contextlib.contextmanager
def _reader(path: Path):
    """An open AnyReader (ROS1 noetic default store); opening errors become InputError."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover
        raise InputError(missing_extra("reading ROS bags", "rosbags", "rosbags"),
                         source=str(path)) from None
    try:
        r = AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC))
        r.open()
    except Exception as exc:  # rosbags raises its own error types for corrupt or unknown files
        raise InputError(f"cannot open ROS bag: {exception_line(exc)}", source=str(path)) from None
    try:
        yield r
    finally:
        r.close()


def _messages(r, source: str, connections, **kw):
    """(connection, log time, raw bytes) of ``r.messages(connections, **kw)``; the errors rosbags raises while
    reading a damaged bag (its ReaderError, KeyError on a record header without a field, decompression errors)
    become one InputError."""
    try:
        yield from r.messages(connections=connections, **kw)
    except Exception as exc:
        raise InputError(f"cannot read the ROS bag (truncated or corrupt?): {type(exc).__name__}: "
                         f"{exception_line(exc)}", source=source) from None


def _deserialize(r, source: str, raw, msgtype: str):
    """A message of a bag deserialized, or one InputError when its bytes do not hold a ``msgtype``."""
    try:
        return r.deserialize(raw, msgtype)
    except Exception as exc:
        raise InputError(f"malformed {msgtype} message ({type(exc).__name__}: {exception_line(exc)})",
                         source=source) from None


def decode_event_array(raw: bytes | memoryview) -> tuple[int, int, np.ndarray]:
    """(height, width, structured events) of one ROS1-serialized dvs_msgs/EventArray, without copies per event."""
    raw = memoryview(raw).cast("B")
    (flen,) = np.frombuffer(raw, "<u4", 1, 12)
    off = 16 + int(flen)
    height, width, count = (int(v) for v in np.frombuffer(raw, "<u4", 3, off))
    off += 12
    if len(raw) < off + 13 * count:
        raise ValueError(f"message holds {len(raw) - off} bytes for {count} events")
    return height, width, np.frombuffer(raw, _EVENT_DTYPE, count, off)


def _stamp(msg) -> float:
    st = msg.header.stamp
    return st.sec + 1e-9 * getattr(st, "nanosec", getattr(st, "nsec", 0))


class BagSource:
    kind = "ROS1 bag"

    def __init__(self, path: Path, topic: str | None = None, block: int = 1 << 20):
        self.path = Path(path)
        self.source = str(self.path)
        self.block = block
        with _reader(self.path) as r:
            by_type: dict[str, list] = {}
            for c in r.connections:
                by_type.setdefault(c.msgtype, []).append(c)
            ev = by_type.get(EVENT_ARRAY, [])
            topics = sorted({c.topic for c in ev})
            if topic is not None:
                if topic not in topics:
                    raise InputError(f"topic {topic!r} holds no {EVENT_ARRAY} (event topics: {topics})",
                                     source=self.source)
            elif len(topics) == 1:
                topic = topics[0]
            elif not topics:
                raise InputError(f"no {EVENT_ARRAY} topic in the bag", source=self.source)
            else:
                raise InputError(f"several event topics {topics}: choose one (topic=...)", source=self.source)
            self.topic = topic
            self._types = {k: sorted({c.topic for c in v}) for k, v in by_type.items()}
            self.sensor_size = None
            for c, _, raw in _messages(r, self.source, [c for c in ev if c.topic == topic]):
                h, w, _ = self._decode(raw, 0)
                if w > 0 and h > 0:
                    self.sensor_size = (w, h)
                break

    def _decode(self, raw, index: int | None = None):
        try:
            return decode_event_array(raw)
        except (ValueError, TypeError) as exc:
            which = "an event message" if index is None else f"event message {index}"
            raise InputError(f"{which}: malformed EventArray ({exception_line(exc)})", source=self.source) from None

    def _connections(self, r, msgtype, topic=None):
        return [c for c in r.connections if c.msgtype == msgtype and (topic is None or c.topic == topic)]

    def iter_blocks(self, t_start=None) -> Iterator[Block]:
        with _reader(self.path) as r:
            messages = _messages(r, self.source, self._connections(r, EVENT_ARRAY, self.topic))
            yield from grouped_blocks((self._decode(raw, k)[2] for k, (_, _, raw) in enumerate(messages)),
                                      self.block, self._events)

    @staticmethod
    def _events(a) -> Events:
        t = a["sec"].astype(np.float64) + 1e-9 * a["nsec"].astype(np.float64)
        return Events(t, a["x"], a["y"], signed_polarity(a["p"]))

    def time_range(self):
        first = last = None
        with _reader(self.path) as r:
            conns = self._connections(r, EVENT_ARRAY, self.topic)
            for k, (_, _, raw) in enumerate(_messages(r, self.source, conns)):
                a = self._decode(raw, k)[2]
                if len(a):
                    first = float(a["sec"][0]) + 1e-9 * float(a["nsec"][0])
                    break
            for start in (max(r.start_time, r.end_time - 2_000_000_000), None):
                for _, _, raw in _messages(r, self.source, conns, start=start):
                    a = self._decode(raw)[2]
                    if len(a):
                        last = float(a["sec"][-1]) + 1e-9 * float(a["nsec"][-1])
                if last is not None:
                    break
        if first is None or last is None:
            raise InputError("the bag holds no events", source=self.source)
        return first, last

    def num_events(self) -> int:
        n = 0
        with _reader(self.path) as r:
            for k, (_, _, raw) in enumerate(_messages(r, self.source, self._connections(r, EVENT_ARRAY, self.topic))):
                n += len(self._decode(raw, k)[2])
        return n

    def _first_of(self, msgtype):
        topics = self._types.get(msgtype, [])
        return topics[0] if topics else None

    def camera(self) -> Camera | None:
        topic = self._first_of(CAMERA_INFO)
        if topic is None:
            return None
        with _reader(self.path) as r:
            for c, _, raw in _messages(r, self.source, self._connections(r, CAMERA_INFO, topic)):
                m = _deserialize(r, self.source, raw, c.msgtype)
                K = np.asarray(getattr(m, "K", getattr(m, "k", None)), dtype=float).reshape(3, 3)
                D = [float(v) for v in getattr(m, "D", getattr(m, "d", []))]
                if K[0, 0] <= 0:
                    return None
                return Camera(int(m.width), int(m.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(D[:5]))
        return None

    def imu(self) -> ImuData | None:
        topic = self._first_of(IMU)
        if topic is None:
            return None
        t, acc, gyro = [], [], []
        with _reader(self.path) as r:
            for c, _, raw in _messages(r, self.source, self._connections(r, IMU, topic)):
                m = _deserialize(r, self.source, raw, c.msgtype)
                t.append(_stamp(m))
                a, g = m.linear_acceleration, m.angular_velocity
                acc.append((a.x, a.y, a.z))
                gyro.append((g.x, g.y, g.z))
        return ImuData(np.array(t), np.array(acc), np.array(gyro)) if t else None

    def groundtruth(self) -> Trajectory | None:
        topic = self._first_of(POSE)
        if topic is None:
            return None
        t, q = [], []
        with _reader(self.path) as r:
            for c, _, raw in _messages(r, self.source, self._connections(r, POSE, topic)):
                m = _deserialize(r, self.source, raw, c.msgtype)
                o = m.pose.orientation
                t.append(_stamp(m))
                q.append((o.x, o.y, o.z, o.w))
        return Trajectory.from_quaternions(np.array(t), np.array(q)) if t else None

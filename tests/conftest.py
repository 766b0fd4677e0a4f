"""Shared fixtures: real recordings under ../shared/data/real (skipped when absent), quiet progress."""
import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("TI_CMAX_NO_PROGRESS", "1")

PROJECT_ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = Path(os.environ.get("TI_CMAX_REAL_DATA", PROJECT_ROOT.parent / "shared" / "data" / "real"))


@pytest.fixture(scope="session")
def real_data() -> Path:
    """Folder of real event recordings; tests using it skip cleanly when it is absent."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real data folder not found: {REAL_DATA}")
    return REAL_DATA


@pytest.fixture(scope="session")
def ti_runtime():
    """Initialize Taichi once for kernel tests."""
    from ti_cmax.kernels import runtime

    runtime.ensure_init()
    return runtime.ti


_EVENT_MSG = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
_EVENT_ARRAY_MSG = "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n"


def ros1_event_typestore():
    """The ROS1 noetic typestore of rosbags with dvs_msgs/Event and dvs_msgs/EventArray registered."""
    pytest.importorskip("rosbags.rosbag1")
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = get_types_from_msg(_EVENT_MSG, "dvs_msgs/msg/Event")
    types.update(get_types_from_msg(_EVENT_ARRAY_MSG, "dvs_msgs/msg/EventArray"))
    store.register(types)
    return store


def _write_ros1_bag(path, events, camera, per_msg=700, with_camera_info=True):
    """A ROS1 bag as the reference's driver records it: dvs_msgs/EventArray on /dvs/events (frame_id varying) and,
    optionally, a sensor_msgs/CameraInfo of ``camera`` on /dvs/camera_info; written with rosbags."""
    from rosbags import rosbag1

    store = ros1_event_typestore()
    Event, EventArray = store.types["dvs_msgs/msg/Event"], store.types["dvs_msgs/msg/EventArray"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]

    def stamp(t):
        s = int(np.floor(t))
        return Time(sec=s, nanosec=int(round((t - s) * 1e9)))

    w_px, h_px = camera.width, camera.height
    with rosbag1.Writer(path) as w:
        conn = w.add_connection("/dvs/events", "dvs_msgs/msg/EventArray", typestore=store)
        for k, i in enumerate(range(0, len(events), per_msg)):
            part = events[i:i + per_msg]
            msg = EventArray(
                header=Header(seq=k, stamp=stamp(part.t[-1]), frame_id="dvs" * (k % 3)),
                height=h_px, width=w_px,
                events=[Event(x=int(x), y=int(y), ts=stamp(t), polarity=bool(p > 0))
                        for t, x, y, p in zip(part.t, part.x, part.y, part.p)],
            )
            w.write(conn, int(part.t[-1] * 1e9), store.serialize_ros1(msg, "dvs_msgs/msg/EventArray"))
        if with_camera_info:
            CameraInfo = store.types["sensor_msgs/msg/CameraInfo"]
            RegionOfInterest = store.types["sensor_msgs/msg/RegionOfInterest"]
            ci = CameraInfo(header=Header(seq=0, stamp=stamp(events.t[0]), frame_id="dvs"), height=h_px, width=w_px,
                            distortion_model="plumb_bob", D=np.array(camera.dist, float), K=camera.K.ravel(),
                            R=np.eye(3).ravel(), P=np.hstack([camera.K, np.zeros((3, 1))]).ravel(),
                            binning_x=0, binning_y=0,
                            roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            c2 = w.add_connection("/dvs/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
            w.write(c2, int(events.t[0] * 1e9), store.serialize_ros1(ci, "sensor_msgs/msg/CameraInfo"))
    return path


@pytest.fixture(scope="session")
def ros1_store():
    """``ros1_event_typestore()`` once per session: the typestore that serializes dvs_msgs for a bag."""
    return ros1_event_typestore()


@pytest.fixture(scope="session")
def write_ros1_bag():
    """``write_ros1_bag(path, events, camera, per_msg=700, with_camera_info=True)``: see :func:`_write_ros1_bag`."""
    return _write_ros1_bag

"""``open_dataset``: one entry point for every supported input.

A DATASET is either a folder in ECD layout (events.h5/.hdf5 or events.txt, the HDF5 preferred when both exist
as it reads faster; calib.txt or a camera_info YAML; optional groundtruth.txt and imu.txt; a folder holding a
single .bag, .aedat4, .raw or .h5 file also works) or a single
events file (.txt, .h5/.hdf5, .bag, .aedat4, .raw). A single file named ``events.*`` is read with the calibration,
groundtruth.txt and imu.txt beside it (it is the events file of an ECD folder); any other single file only with
what it carries itself (so an unrelated calib.txt in the same folder is never picked up by accident).

Sensor size, first match wins: the ``width``/``height`` arguments; the calibration YAML; a second line
'width height' in calib.txt; the events file (HDF5 attributes, bag message width/height, AEDAT4 stream, Prophesee
RAW header); otherwise it is inferred from the largest x, y of
the first chunk, snapped to the smallest sensor of ``ti_cmax.camera.SENSORS`` containing them (by pixel count:
DVS128, DAVIS240C, DAVIS346, VGA / DVXplorer, HD) whose central half holds calib.txt's principal point. A recording whose
first chunk never reaches the far border of a bigger sensor could still be mis-sized: give width and height
(or a camera_info YAML) then.

Intrinsics: calib.txt / YAML; otherwise the events file when it carries them (our HDF5 attributes, a bag's
sensor_msgs/CameraInfo); otherwise ``Camera.ideal(width, height)`` only when ``allow_default_calibration``,
else ``Dataset.camera`` raises InputError.
"""
from __future__ import annotations

from functools import cached_property
from pathlib import Path
from typing import Iterator

from ..camera import Camera
from ..config import DatasetConfig
from ..errors import InputError
from ..events import Events
from ..trajectory import Trajectory
from ._common import NoCompanions, check_time_span, infer_sensor_size, validated_chunks
from .calib import read_calib_txt_params, read_calib_txt_size, read_camera_info_yaml
from .text import ImuData, read_imu_txt, read_tum

def open_dataset_from_config(path, cfg: DatasetConfig) -> "Dataset":
    return open_dataset(path, cfg.width or None, cfg.height or None,
                        allow_default_calibration=cfg.allow_default_calibration, topic=cfg.topic or None,
                        time_unit=None if cfg.time_unit == "auto" else cfg.time_unit)


EVENT_FILE_SUFFIXES = (".txt", ".h5", ".hdf5", ".bag", ".aedat4", ".raw")
_EVENT_NAMES = ("events.h5", "events.hdf5", "events.txt")
_CALIB_NAMES = ("calib.txt", "camera_info.yaml", "camera_info.yml", "calib.yaml", "calib.yml")
DEFAULT_FOV_DEG = 60.0


_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}


class TxtSource(NoCompanions):
    """ECD events.txt (times in seconds, or in ``time_unit``)."""

    kind = "ECD text"

    def __init__(self, path: Path, time_unit: str | None = None):
        from . import events_txt

        self.path = path
        self.source = str(path)
        self.sensor_size = None
        self._txt = events_txt
        self.time_unit = time_unit
        self._scale = _TIME_UNITS[time_unit] if time_unit else 1.0

    def iter_blocks(self, t_start=None):
        offset, first_line = (self._txt.txt_seek(self.path, t_start / self._scale) if t_start is not None
                              else (0, 1))
        blocks = self._txt.iter_txt_blocks(self.path, offset=offset, first_line=first_line)
        return blocks if self._scale == 1.0 else map(self._scaled, blocks)

    def _scaled(self, block):
        ev = block.events
        block.events = Events(ev.t * self._scale, ev.x, ev.y, ev.p)
        return block

    def time_range(self):
        first, last = self._txt.txt_time_range(self.path)
        return first * self._scale, last * self._scale

    def check_time_range(self):
        """Fail early on an empty or unreadable file, or on times that are not seconds (no recording spans days)."""
        first, last = self.time_range()
        if not self.time_unit:
            check_time_span(first, last, None, self.source, "the times read as seconds (the text format's unit)",
                            "give their unit with --set time_unit=ms, us or ns")

    def num_events(self):
        return self._txt.txt_count_lines(self.path)


class H5Source:
    kind = "HDF5"

    def __init__(self, path: Path, time_unit: str | None = None):
        from .h5 import H5Events

        self.path = path
        self.source = str(path)
        self._h5 = H5Events(path, time_unit)
        self.sensor_size = self._h5.sensor_size
        if self._h5.compound:
            self.kind = "Metavision HDF5"

    def iter_blocks(self, t_start=None):
        return self._h5.iter_blocks(t_start=t_start)

    def time_range(self):
        return self._h5.time_range()

    def check_time_range(self):
        """Fail early on an empty or unreadable file (H5Events checked the times' unit when it opened)."""
        self.time_range()

    def num_events(self):
        return self._h5.num_events()

    def camera(self):
        return self._h5.camera()

    def imu(self):
        return None

    def groundtruth(self):
        return None


def _make_source(path: Path, topic: str | None, time_unit: str | None = None):
    suffix = path.suffix.lower()
    if suffix == ".txt":
        return TxtSource(path, time_unit)
    if suffix in (".h5", ".hdf5"):
        return H5Source(path, time_unit)
    if time_unit:
        raise InputError(f"time_unit applies to text and HDF5 files; {suffix} files state their own time unit",
                         source=str(path))
    if suffix == ".bag":
        from .bag import BagSource

        return BagSource(path, topic=topic)
    if suffix == ".aedat4":
        from .aedat4 import Aedat4Source

        return Aedat4Source(path)
    if suffix == ".raw":
        from .prophesee import RawSource

        return RawSource(path)
    raise InputError(f"unsupported events file type {suffix!r} (supported: {', '.join(EVENT_FILE_SUFFIXES)})",
                     source=str(path))


def _find_events_file(folder: Path) -> Path:
    for name in _EVENT_NAMES:
        if (folder / name).is_file():
            return folder / name
    others = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".bag", ".aedat4", ".raw", ".h5", ".hdf5"))
    if len(others) == 1:
        return others[0]
    if others:
        raise InputError(f"several event files, choose one: {', '.join(p.name for p in others)}", source=str(folder))
    raise InputError("no events found: expected events.txt or events.h5 (or one .bag / .aedat4 / .raw file)",
                     source=str(folder))


def _find_calib(folder: Path) -> Path | None:
    for name in _CALIB_NAMES:
        if (folder / name).is_file():
            return folder / name
    for p in sorted(folder.glob("*.y*ml")):
        try:
            head = p.read_text(encoding="utf-8", errors="replace")[:4096]
        except OSError:
            continue
        if "camera_matrix" in head and "image_width" in head:
            return p
    return None


class _NoCalibration(InputError):
    """No intrinsics found (as opposed to intrinsics that are wrong)."""


class Dataset:
    """An opened dataset: camera, optional ground truth and IMU, and streamed events."""

    def __init__(self, path, width: int | None = None, height: int | None = None, *,
                 allow_default_calibration: bool = False, topic: str | None = None, time_unit: str | None = None):
        path = Path(path)
        if time_unit and time_unit not in _TIME_UNITS:
            raise InputError(f"time_unit must be one of {', '.join(_TIME_UNITS)}, got {time_unit!r}")
        if not path.exists():
            raise InputError("no such file or folder", source=str(path))
        self.path = path
        if path.is_dir():
            self.events_path = _find_events_file(path)
            folder, companions = path, True
        else:
            self.events_path = path
            folder, companions = path.parent, path.stem == "events"
        self.name = path.name if path.is_dir() else (path.parent.name if path.stem == "events" else path.stem)
        self.calib_path = _find_calib(folder) if companions else None
        gt, imu = folder / "groundtruth.txt", folder / "imu.txt"
        self.groundtruth_path = gt if companions and gt.is_file() else None
        self.imu_path = imu if companions and imu.is_file() else None
        self.allow_default_calibration = allow_default_calibration
        self._source = _make_source(self.events_path, topic, time_unit)
        self.format = self._source.kind
        self._user_size = (int(width), int(height)) if width and height else None
        if (width is None) != (height is None):
            raise InputError("give both width and height, or neither")
        self._yaml_camera = None
        self._txt_calib = None
        self._txt_size = None
        if self.calib_path is not None:
            if self.calib_path.suffix.lower() in (".yaml", ".yml"):
                self._yaml_camera = read_camera_info_yaml(self.calib_path)
            else:
                self._txt_calib = read_calib_txt_params(self.calib_path)
                self._txt_size = read_calib_txt_size(self.calib_path)
        if isinstance(self._source, (TxtSource, H5Source)):
            self._source.check_time_range()  # cheap here
        self.width, self.height = self._sensor_size()

    # sensor size and camera ----------------------------------------------------------------------
    def _sensor_size(self) -> tuple[int, int]:
        if self._user_size is not None:
            self.size_source = "given"
            return self._user_size
        if self._yaml_camera is not None:
            self.size_source = self.calib_path.name
            return self._yaml_camera.width, self._yaml_camera.height
        if self._txt_size is not None:
            self.size_source = f"{self.calib_path.name}, line {self._txt_size[2]}"
            return self._txt_size[:2]
        if self._source.sensor_size is not None:
            self.size_source = f"{self.format} file"
            return tuple(int(v) for v in self._source.sensor_size)
        blocks = iter(self._source.iter_blocks())
        try:
            first = next(blocks, None)
        finally:
            if hasattr(blocks, "close"):
                blocks.close()
        if first is None or len(first.events) == 0:
            raise InputError("the file holds no events", source=self._source.source)
        ev = first.events
        self.size_source = "inferred from pixel coordinates"
        pp = (self._txt_calib[0][2], self._txt_calib[0][3]) if self._txt_calib is not None else None
        return infer_sensor_size(float(ev.x.max()), float(ev.y.max()), self._source.source, pp)

    @property
    def sensor_size(self) -> tuple[int, int]:
        return self.width, self.height

    @cached_property
    def _camera_and_source(self) -> tuple[Camera, str]:
        try:
            return self._find_camera()
        except InputError as exc:  # intrinsics that do not fit the sensor: name the file they come from
            if exc.source is not None or isinstance(exc, _NoCalibration):
                raise
            raise InputError(str(exc), source=str(self.calib_path or self.events_path)) from None

    def _find_camera(self) -> tuple[Camera, str]:
        w, h = self.width, self.height
        if self._txt_calib is not None:
            (fx, fy, cx, cy), dist = self._txt_calib
            return Camera(w, h, fx, fy, cx, cy, dist), self.calib_path.name
        if self._yaml_camera is not None:
            c = self._yaml_camera
            return Camera(w, h, c.fx, c.fy, c.cx, c.cy, c.dist), self.calib_path.name
        cam = self._source.camera()
        if cam is not None:
            return Camera(w, h, cam.fx, cam.fy, cam.cx, cam.cy, cam.dist), f"{self.format} file"
        if self.allow_default_calibration:
            return Camera.ideal(w, h, DEFAULT_FOV_DEG), f"default (ideal pinhole, {DEFAULT_FOV_DEG:g} deg field of view)"
        raise _NoCalibration("no camera calibration: expected calib.txt or a camera_info YAML beside the events (or "
                         f"use an ideal {DEFAULT_FOV_DEG:g} deg pinhole: --set allow_default_calibration=true)",
                         source=str(self.path))

    @property
    def camera(self) -> Camera:
        return self._camera_and_source[0]

    @property
    def calibration_source(self) -> str | None:
        """Where the intrinsics come from, or None when there are none (intrinsics that do not fit the sensor raise
        their InputError)."""
        try:
            return self._camera_and_source[1]
        except _NoCalibration:
            return None

    # companions ------------------------------------------------------------------------------------
    @cached_property
    def groundtruth(self) -> Trajectory | None:
        if self.groundtruth_path is not None:
            return read_tum(self.groundtruth_path)
        return self._source.groundtruth()

    @cached_property
    def imu(self) -> ImuData | None:
        if self.imu_path is not None:
            return read_imu_txt(self.imu_path)
        return self._source.imu()

    # events ----------------------------------------------------------------------------------------
    def iter_events(self, chunk_size: int = 1_000_000, t_start: float | None = None,
                    t_end: float | None = None) -> Iterator[Events]:
        """Validated chunks of ``chunk_size`` events (last one shorter) with t_start <= t < t_end."""
        return validated_chunks(self._source.iter_blocks(t_start=t_start), self._source.source,
                                self.width, self.height, chunk_size, t_start, t_end)

    def stream(self, chunk_size: int = 1_000_000) -> "EventStream":
        """The validated chunks as an iterable that also knows the time range (progress bars get a total)."""
        return EventStream(self, chunk_size)

    def read_events(self, t_start: float | None = None, t_end: float | None = None) -> Events:
        """All events in [t_start, t_end) at once (convenience for short recordings)."""
        return Events.concatenate(list(self.iter_events(1 << 22, t_start, t_end)))

    def time_range(self) -> tuple[float, float]:
        return self._source.time_range()

    def num_events(self) -> int:
        """Number of events (text files: data lines counted on raw bytes)."""
        return int(self._source.num_events())

    def __repr__(self) -> str:
        return f"Dataset({self.name!r}, {self.format}, {self.width}x{self.height})"


class EventStream:
    """One pass over a dataset's events in chunks (``iter``), with the dataset's ``time_range()``."""

    def __init__(self, dataset: Dataset, chunk_size: int):
        self.dataset, self.chunk_size = dataset, int(chunk_size)

    def time_range(self) -> tuple[float, float]:
        return self.dataset.time_range()

    def __iter__(self) -> Iterator[Events]:
        return iter(self.dataset.iter_events(self.chunk_size))


def open_dataset(path, width: int | None = None, height: int | None = None, *,
                 allow_default_calibration: bool = False, topic: str | None = None,
                 time_unit: str | None = None) -> Dataset:
    """Open a dataset folder or events file (see module doc); reads only what is needed for the metadata.
    ``time_unit`` (s, ms, us, ns): the unit of a text or HDF5 file's times, when not the file's own."""
    return Dataset(path, width, height, allow_default_calibration=allow_default_calibration, topic=topic,
                   time_unit=time_unit)

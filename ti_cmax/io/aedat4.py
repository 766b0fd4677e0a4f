"""AEDAT4 (iniVation DV) files via the ``aedat`` package: events (t us, x, y, on) and IMU samples.

AEDAT4 holds no intrinsics and no index, so time range and count need one pass over the file (cached).
IMU units as DV stores them are converted: accelerometer g -> m/s^2, gyroscope deg/s -> rad/s.
"""
from __future__ import annotations

import struct
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError, exception_line, missing_extra
from ._common import Block, ScannedSource, grouped_blocks, is_decoder_error
from .text import ImuData

G = 9.80665
MAGIC = b"#!AER-DAT4.0\r\n"


def check_header(path: Path) -> None:
    """Raise InputError unless ``path`` starts with a well-formed AEDAT4 header: the magic line, the IOHeader
    flatbuffer (identifier IOHE, vtable and fields inside it) and an XML stream description.

    Why: aedat reads the header without bounds checks and parses the XML with a parser that panics on some
    malformed documents; such a panic aborts the whole process (no Python exception), so a corrupt header must
    never reach it. Packets after the header are checked by aedat itself."""
    source = str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(len(MAGIC) + 4)
            if head[:len(MAGIC)] != MAGIC:
                raise InputError("cannot open AEDAT4 file: it does not start with '#!AER-DAT4.0'", source=source)
            if len(head) < len(MAGIC) + 4:
                raise InputError("cannot open AEDAT4 file: its header is cut", source=source)
            (size,) = struct.unpack_from("<I", head, len(MAGIC))
            buf = f.read(size)
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", source=source) from None

    def bad(why):
        return InputError(f"cannot open AEDAT4 file: corrupt header ({why})", source=source)

    if len(buf) < size:
        raise bad(f"{size} bytes announced, {len(buf)} in the file")
    if size < 8 or buf[4:8] != b"IOHE":
        raise bad("no IOHeader flatbuffer")
    (table,) = struct.unpack_from("<I", buf, 0)
    if table + 4 > size:
        raise bad("table outside the header")
    vtable = table - struct.unpack_from("<i", buf, table)[0]
    if vtable < 0 or vtable + 4 > size:
        raise bad("vtable outside the header")
    vt_size, table_size = struct.unpack_from("<HH", buf, vtable)
    if vt_size < 4 or vt_size % 2 or vtable + vt_size > size or table + table_size > size:
        raise bad("vtable or table outside the header")
    fields = struct.unpack_from(f"<{(vt_size - 4) // 2}H", buf, vtable + 4)
    for k, width in enumerate((4, 8, 4)):  # compression i32, data table position i64, description offset u32
        if k < len(fields) and fields[k] and (fields[k] + width > table_size):
            raise bad(f"field {k} outside its table")
    if len(fields) < 3 or not fields[2]:
        raise bad("no stream description")
    at = table + fields[2]
    at += struct.unpack_from("<I", buf, at)[0]
    if at + 4 > size or at + 4 + struct.unpack_from("<I", buf, at)[0] > size:
        raise bad("stream description outside the header")
    (length,) = struct.unpack_from("<I", buf, at)
    try:
        root = ET.fromstring(buf[at + 4:at + 4 + length].decode("utf-8"))
    except (UnicodeDecodeError, ET.ParseError) as exc:
        raise bad(f"stream description is not well-formed XML: {exception_line(exc)}") from None
    if root.tag != "dv":
        raise bad(f"stream description root is <{root.tag}>, expected <dv>")


def _decoder(path: Path):
    try:
        import aedat
    except ImportError:  # pragma: no cover
        raise InputError(missing_extra("reading AEDAT4", "aedat", "aedat"),
                         source=str(path)) from None
    check_header(path)
    try:
        return aedat.Decoder(str(path))
    except BaseException as exc:  # aedat raises plain RuntimeError/OSError on bad files, panics on some
        if not is_decoder_error(exc):
            raise
        raise InputError(f"cannot open AEDAT4 file: {exception_line(exc)}", source=str(path)) from None


class Aedat4Source(ScannedSource):
    kind = "AEDAT4"

    def __init__(self, path: Path, block: int = 1 << 20):
        self.path = Path(path)
        self.source = str(self.path)
        self.block = block
        streams = _decoder(self.path).id_to_stream()
        ev = [(sid, s) for sid, s in streams.items() if s.get("type") == "events"]
        if not ev:
            raise InputError("no event stream in the AEDAT4 file", source=self.source)
        self.stream_id, s = ev[0]
        self.sensor_size = (int(s["width"]), int(s["height"])) if "width" in s else None

    def _packets(self):
        try:
            yield from _decoder(self.path)
        except InputError:
            raise
        except BaseException as exc:  # a packet shorter than its flatbuffer header makes aedat panic
            if not is_decoder_error(exc):
                raise
            raise InputError(f"cannot decode AEDAT4 data (truncated or corrupt?): {exception_line(exc)}",
                             source=self.source) from None

    def _arrays(self):
        return (pk["events"] for pk in self._packets() if pk.get("stream_id") == self.stream_id and "events" in pk)

    def iter_blocks(self, t_start=None) -> Iterator[Block]:
        return grouped_blocks(self._arrays(), self.block, self._events)

    def imu(self) -> ImuData | None:
        parts = [pk["imus"] for pk in self._packets() if "imus" in pk and len(pk["imus"])]
        if not parts:
            return None
        a = np.concatenate(parts)
        acc = np.column_stack([a[f"accelerometer_{c}"] for c in "xyz"]).astype(np.float64) * G
        gyro = np.radians(np.column_stack([a[f"gyroscope_{c}"] for c in "xyz"]).astype(np.float64))
        return ImuData(a["t"].astype(np.float64) * 1e-6, acc, gyro)

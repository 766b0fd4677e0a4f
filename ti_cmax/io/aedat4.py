"""AEDAT4 (iniVation DV) files via the ``aedat`` package: events (t us, x, y, on) and IMU samples.

AEDAT4 holds no intrinsics and no index, so time range and count need one pass over the file (cached).
IMU units as DV stores them are converted: accelerometer g -> m/s^2, gyroscope deg/s -> rad/s.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError
from ._common import Block, ScannedSource, grouped_blocks
from .text import ImuData

G = 9.80665


def _decoder(path: Path):
    try:
        import aedat
    except ImportError:  # pragma: no cover
        raise InputError("reading AEDAT4 needs the 'aedat' package (pip install ti-cmax[aedat])",
                         source=str(path)) from None
    try:
        return aedat.Decoder(str(path))
    except Exception as exc:  # aedat raises plain RuntimeError/OSError on bad files
        raise InputError(f"cannot open AEDAT4 file: {exc}", source=str(path)) from None


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
        except Exception as exc:
            raise InputError(f"cannot decode AEDAT4 data (truncated or corrupt?): {exc}", source=self.source) from None

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

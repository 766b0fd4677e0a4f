"""Pinhole camera with radial-tangential (OpenCV plumb_bob) distortion and a per-pixel bearing table.

Bearings are points on the unit-depth plane, X = (x_n, y_n, 1), in the camera frame
(x right, y down, z forward). The lookup table is built once per camera by iterative
undistortion, as the reference implementation does.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .errors import InputError


# fields of view (deg, along each sensor axis) a pinhole calibration may give: beyond them it is not a real lens
FOV_RANGE_DEG = (1.0, 179.0)
UNPROJECT_BLOCK = 16384  # pixels per block of the per-pixel bearing table (a few hundred kB of float64 temporaries)


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))  # k1 k2 p1 p2 k3

    def __post_init__(self):
        d = tuple(float(v) for v in self.dist) + (0.0,) * (5 - len(self.dist))
        if len(d) != 5:
            raise InputError(f"distortion needs at most 5 coefficients (k1 k2 p1 p2 k3), got {len(self.dist)}")
        object.__setattr__(self, "dist", d)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"sensor size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not np.all(np.isfinite([self.fx, self.fy, self.cx, self.cy, *d])):
            raise InputError(f"camera intrinsics must be finite numbers, got fx={self.fx}, fy={self.fy}, "
                             f"cx={self.cx}, cy={self.cy}, distortion={d}")
        self._check_against_sensor()

    def _check_against_sensor(self) -> None:
        """Intrinsics that no lens on this sensor has are one error: a field of view outside FOV_RANGE_DEG, or a
        principal point off the sensor extended by half its size on every side (focal lengths of 1e-9 or 1e12 px
        gave omega up to 4e11 rad/s with status ok)."""
        lo, hi = FOV_RANGE_DEG
        for axis, f, size in (("horizontal", self.fx, self.width), ("vertical", self.fy, self.height)):
            fov = float(np.degrees(2 * np.arctan(0.5 * size / f)))
            if not lo <= fov <= hi:
                key = "fx" if axis == "horizontal" else "fy"
                raise InputError(f"camera intrinsics do not fit the {self.width}x{self.height} sensor: {key}={f:g} px "
                                 f"gives a {axis} field of view of {fov:.4g} deg (expected {lo:g} to {hi:g} deg)")
        for key, c, size in (("cx", self.cx, self.width), ("cy", self.cy, self.height)):
            if not -0.5 * size <= c <= 1.5 * size:
                raise InputError(f"camera intrinsics do not fit the {self.width}x{self.height} sensor: principal point "
                                 f"{key}={c:g} px is far off the sensor (expected {-0.5 * size:g} to {1.5 * size:g})")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.dist)

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    # distortion model on normalized coordinates ---------------------------------------------
    def distort_normalized(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2, k3 = self.dist
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd, yd

    def undistort_normalized(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20):
        """Invert the distortion by fixed-point iteration (OpenCV's scheme), float64."""
        xd = np.asarray(xd, dtype=float)
        yd = np.asarray(yd, dtype=float)
        if not self.has_distortion:
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = self.dist
        xn, yn = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = xn * xn + yn * yn
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
            dy = p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
            xn = (xd - dx) / radial
            yn = (yd - dy) / radial
        return xn, yn

    # pixels <-> bearings --------------------------------------------------------------------
    def unproject(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates -> bearings on the unit-depth plane, (N, 3) float64."""
        xd = (np.asarray(x, dtype=float) - self.cx) / self.fx
        yd = (np.asarray(y, dtype=float) - self.cy) / self.fy
        xn, yn = self.undistort_normalized(xd, yd)
        return np.stack([xn, yn, np.ones_like(xn)], axis=-1)

    def project(self, bearings: np.ndarray, distort: bool = True) -> np.ndarray:
        """Bearings (N, 3) in front of the camera -> pixel coordinates (N, 2)."""
        b = np.asarray(bearings, dtype=float)
        xn, yn = b[..., 0] / b[..., 2], b[..., 1] / b[..., 2]
        if distort and self.has_distortion:
            xn, yn = self.distort_normalized(xn, yn)
        return np.stack([self.fx * xn + self.cx, self.fy * yn + self.cy], axis=-1)

    def __getstate__(self):
        """Pickle the intrinsics only, not the bearing tables (rebuilt on first use): a camera sent to a spawned
        worker stays a few hundred bytes instead of 1.2 MB (DAVIS240C) to 44 MB (HD). A payload over a pipe's 64 KB
        also hung the parent for good when the worker died while starting (multiprocessing writes it whole)."""
        return {k: v for k, v in self.__dict__.items()
                if k not in ("bearing_lut", "bearing_lut4", "separable_bearing_lut", "separable_bearing_lut4")}

    @cached_property
    def bearing_lut(self) -> np.ndarray:
        """Per-pixel bearings (height*width, 3) float32, indexed by y*width + x. Built once."""
        return np.ascontiguousarray(self.bearing_lut4[:, :3])

    @cached_property
    def bearing_lut4(self) -> np.ndarray:
        """Per-pixel bearings in the first 3 columns of a (height*width, 4) float32 table (4th column 0)."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        lut = np.zeros((self.height * self.width, 4), np.float32)
        lut[:, :3] = self._checked_unprojection(xs.ravel(), ys.ravel())
        return lut

    @cached_property
    def separable_bearing_lut4(self) -> np.ndarray:
        """An undistorted camera's bearings in separable form, (max(width, height), 4) float32: row i holds the x
        bearing of column i, the y bearing and z (1) of row i, then 0. Without distortion a bearing's x depends on
        its column alone and its y on its row alone, so these few KB hold the per-pixel table's numbers and stay in
        the cache where the per-pixel table (MBs on VGA and HD) is read at random."""
        if self.has_distortion:
            raise ValueError("a distorted camera's bearings have no separable table")
        i = np.arange(max(self.width, self.height))
        lut = np.zeros((len(i), 4), np.float32)
        lut[:, :3] = self.unproject(i, i)
        return lut

    @cached_property
    def separable_bearing_lut(self) -> np.ndarray:
        """``separable_bearing_lut4``'s first 3 columns, (max(width, height), 3) float32."""
        return np.ascontiguousarray(self.separable_bearing_lut4[:, :3])

    def _checked_unprojection(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``unproject`` of every sensor pixel, checked: each bearing must project back onto its pixel (within 0.01
        px; real calibrations come back within 1e-10). Coefficients whose distortion folds over inside the sensor
        have no inverse there, and the fixed-point iteration then returns NaN or directions up to 1e10 px off (a
        trajectory 40 deg off with status ok)."""
        if not self.has_distortion:
            return self.unproject(x, y)
        xd, yd = (np.asarray(x, dtype=float) - self.cx) / self.fx, (np.asarray(y, dtype=float) - self.cy) / self.fy
        bearings = np.ones((len(xd), 3))
        off = np.empty(len(xd))
        with np.errstate(all="ignore"):  # a folding distortion overflows: that is what is checked
            for iterations in (20, 200):  # 20 as OpenCV (bitwise unproject); strong distortion may need more
                # in blocks whose temporaries stay in the cache (elementwise: the same numbers, 2x faster on HD)
                for i in range(0, len(xd), UNPROJECT_BLOCK):
                    j = slice(i, i + UNPROJECT_BLOCK)
                    bearings[j, 0], bearings[j, 1] = self.undistort_normalized(xd[j], yd[j], iterations)
                    back = self.project(bearings[j])
                    off[j] = np.hypot(back[:, 0] - x[j], back[:, 1] - y[j])
                if np.all(off <= 0.01):  # False for NaN too
                    return bearings
        i = int(np.argmax(np.where(np.isfinite(off), off, np.inf)))
        raise InputError(f"the distortion coefficients {self.dist} (k1 k2 p1 p2 k3) cannot be inverted over the "
                         f"sensor: pixel ({int(x[i])}, {int(y[i])}) has no undistorted direction that maps back to it "
                         f"({off[i]:.3g} px off); check the calibration")

    def bearings(self, x: np.ndarray, y: np.ndarray, dtype=np.float32, columns: int = 3) -> np.ndarray:
        """Bearings of event pixels (n, 3): table lookup for integer pixels, direct undistortion otherwise.
        ``columns=4`` returns an (n, 4) array with the bearings in the first 3 columns and a 4th one free for
        the caller (the front-end stores event times there: one copy fewer per packet)."""
        if columns not in (3, 4):
            raise ValueError(f"columns must be 3 or 4, got {columns}")
        x = np.asarray(x)
        if np.issubdtype(x.dtype, np.integer):
            idx = np.asarray(y).astype(np.int32)
            idx *= self.width
            idx += x
            out = (self.bearing_lut4 if columns == 4 else self.bearing_lut).take(idx, axis=0)
            return out if out.dtype == dtype else out.astype(dtype)
        return self._unprojected(x, y, dtype, columns)

    def _unprojected(self, x, y, dtype, columns: int) -> np.ndarray:
        """:meth:`bearings` by direct undistortion (any coordinates)."""
        b = self.unproject(x, y)
        if columns == 3:
            return np.ascontiguousarray(b, dtype=dtype)
        out = np.zeros((len(b), 4), dtype)
        out[:, :3] = b
        return out

    @property
    def undistorted_K(self) -> np.ndarray:
        """Intrinsics used to render front-end IWEs of undistorted bearings (the same K: the
        reference projects with K; we compute bearings and project with the same matrix)."""
        return self.K

    @classmethod
    def ideal(cls, width: int, height: int, fov_deg: float = 60.0) -> "Camera":
        """Distortion-free camera with the given horizontal field of view."""
        f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2)

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
            "cx": self.cx, "cy": self.cy, "dist": list(self.dist),
        }


# Sensors the simulator and the reader know by name (width, height). "DVXplorer" (iniVation) and "VGA" (a
# generic 640x480 camera, kept for existing configs) share a size; "HD" is a Prophesee IMX636 / EVK4 sensor.
SENSORS = {
    "DAVIS240C": (240, 180),
    "DVS128": (128, 128),
    "DAVIS346": (346, 260),
    "VGA": (640, 480),
    "DVXplorer": (640, 480),
    "HD": (1280, 720),
}

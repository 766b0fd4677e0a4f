"""Camera calibration files: ECD calib.txt and ROS camera_info YAML."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import InputError, exception_line

_CALIB_EXPECTED = "expected 'fx fy cx cy [k1 k2 p1 p2 [k3]]' (4, 8 or 9 numbers)"


def _calib_txt_lines(path):
    """(line number, fields) of the data lines of an ECD calib.txt ('#' starts a comment)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("calibration file not found", source=str(path))
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for lineno, raw in enumerate(f, 1):
            parts = raw.split("#", 1)[0].split()
            if parts:
                yield lineno, parts


def read_calib_txt_params(path) -> tuple[tuple[float, float, float, float], tuple]:
    """(fx, fy, cx, cy), dist from the first non-comment line of an ECD calib.txt."""
    source = str(path)
    for lineno, parts in _calib_txt_lines(path):
        if len(parts) not in (4, 8, 9):
            raise InputError(f"{_CALIB_EXPECTED}, got {len(parts)} values", source=source, line=lineno)
        try:
            v = [float(s) for s in parts]
        except ValueError:
            raise InputError(f"{_CALIB_EXPECTED}, got {' '.join(parts)[:80]!r}", source=source, line=lineno) from None
        if not np.isfinite(v).all() or v[0] <= 0 or v[1] <= 0:
            raise InputError(f"focal lengths must be positive finite numbers, got {' '.join(parts)[:80]!r}",
                             source=source, line=lineno)
        return (v[0], v[1], v[2], v[3]), tuple(v[4:])
    raise InputError(f"calibration file is empty ({_CALIB_EXPECTED})", source=source)


def read_calib_txt_size(path) -> tuple[int, int, int] | None:
    """(width, height, line) from the optional second data line 'width height' of a calib.txt (some ECD copies
    have it), or None when the file has one data line."""
    lines = _calib_txt_lines(path)
    next(lines, None)
    second = next(lines, None)
    if second is None:
        return None
    lineno, parts = second
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise InputError(f"expected the sensor size 'width height' (2 positive integers) after the intrinsics, got "
                         f"{' '.join(parts)[:80]!r}", source=str(path), line=lineno)
    return int(parts[0]), int(parts[1]), lineno


def read_camera_info_yaml(path, width: int | None = None, height: int | None = None) -> Camera:
    """ROS camera_info YAML: image_width, image_height, camera_matrix.data, distortion_coefficients.data."""
    import yaml

    path = Path(path)
    source = str(path)
    try:
        d = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML ({exception_line(exc)})", source=source) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): save the "
                         "camera_info YAML as UTF-8", source=source) from None
    if not isinstance(d, dict) or "camera_matrix" not in d:
        raise InputError("not a ROS camera_info YAML (missing camera_matrix)", source=source)
    try:
        K = np.asarray(d["camera_matrix"]["data"], dtype=float).reshape(3, 3)
        w = int(width or d["image_width"])
        h = int(height or d["image_height"])
        model = str(d.get("distortion_model", "plumb_bob"))
        dist = [float(v) for v in (d.get("distortion_coefficients") or {}).get("data", [])]
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise InputError(f"malformed camera_info YAML ({type(exc).__name__}: {exception_line(exc)}); expected "
                         "image_width, "
                         "image_height, camera_matrix.data (9 numbers), distortion_coefficients.data",
                         source=source) from None
    if model not in ("plumb_bob", "rational_polynomial", "radtan", "none", "") :
        raise InputError(f"distortion_model {model!r} is not supported (use plumb_bob)", source=source)
    if model == "rational_polynomial" and any(dist[5:]):
        raise InputError("rational_polynomial with k4..k6 != 0 is not supported", source=source)
    return _camera(source, w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(dist[:5]))


def _camera(source: str, width, height, fx, fy, cx, cy, dist) -> Camera:
    """Camera(...), its InputError (NaN or non-positive intrinsics, intrinsics that do not fit the sensor) naming
    the calibration file."""
    try:
        return Camera(int(width), int(height), fx, fy, cx, cy, dist)
    except InputError as exc:
        raise InputError(str(exc), source=source) from None


def write_camera_info_yaml(path, camera: Camera, camera_name: str = "event_camera") -> Path:
    """Write a ROS camera_info YAML (plumb_bob)."""
    import yaml

    K = camera.K
    P = np.hstack([K, np.zeros((3, 1))])
    d = {
        "image_width": int(camera.width), "image_height": int(camera.height), "camera_name": camera_name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in K.ravel()]},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [float(v) for v in camera.dist]},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in np.eye(3).ravel()]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": [float(v) for v in P.ravel()]},
    }
    path = Path(path)
    path.write_text(yaml.safe_dump(d, sort_keys=False), encoding="utf-8")
    return path


def write_calib_txt(path, camera: Camera) -> Path:
    """ECD calib.txt: one line "fx fy cx cy k1 k2 p1 p2 k3"."""
    vals = [camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist]
    path = Path(path)
    path.write_text(" ".join(repr(float(v)) for v in vals) + "\n", encoding="utf-8")
    return path


def is_camera_info_yaml(path) -> bool:
    return Path(path).suffix.lower() in (".yaml", ".yml")


def read_calib(path, width: int | None = None, height: int | None = None) -> Camera:
    """Camera from an ECD calib.txt (needs width, height: the file has no sensor size) or a camera_info YAML."""
    path = Path(path)
    if is_camera_info_yaml(path):
        return read_camera_info_yaml(path, width, height)
    (fx, fy, cx, cy), dist = read_calib_txt_params(path)
    if width is None or height is None:
        size = read_calib_txt_size(path)
        if size is None:
            raise InputError("calib.txt holds no sensor size: give width and height", source=str(path))
        width, height = size[:2]
    return _camera(str(path), width, height, fx, fy, cx, cy, dist)

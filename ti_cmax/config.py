"""Configuration: frozen dataclasses named after the reference implementation's launch parameters.

A config is loaded from YAML (flat, launch-file style, or nested by section) and from
``--set key=value`` overrides. Flat keys are resolved by their unique field name across sections,
so ``--set num_events_per_packet=20000`` and ``--set frontend.num_events_per_packet=20000`` both work.
The config used is written beside the outputs (:func:`save_config`).
"""
from __future__ import annotations

import dataclasses
import os
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace

import yaml

from .errors import InputError


@dataclass(frozen=True)
class FrontendConfig:
    """CMax-omega front-end (Sec. II-B, III-C1)."""

    contrast_measure: str = "variance"  # "variance" or "mean_square"
    frontend_blur_sigma: float = 1.0
    frontend_event_sample_rate: int = 1  # keep 1 of Q events
    # 0 (or auto): derived from the sensor (pipelines/sensor_defaults.py: 10000 x max(1, pixels / 43200))
    num_events_per_packet: int = 0
    dt_ang_vel: float = 0.01  # 1/f, packet centre spacing (s)
    still_span_factor: float = 10.0  # a packet spanning more than factor*dt_ang_vel means a still camera
    # "bounded" (default): a packet spanning more than W = still_span_factor*dt_ang_vel is shrunk to the
    # events within t_ref +- W/2, and omega = 0 only if fewer than frontend_min_event_rate*W remain.
    # "paper": the reference rule (omega = 0 as soon as the N events span more than W).
    frontend_slicing: str = "bounded"
    frontend_min_event_rate: float = 0.0  # events/s floor of the "bounded" rule; 0: 10000 x pixels / 43200
    # packets take at least every event within t_ref +- span/2 (high event rates: N events would cover too
    # little motion to measure); 0 disables (the reference's fixed N)
    frontend_min_packet_span: float = 0.04
    # packets holding more events than this are thinned uniformly (1 of k, k = ceil(n / max)) before the
    # optimisation: the span (motion) is kept, the cost per packet is bounded at high event rates;
    # 0 (or auto): derived, 20000 x max(1, pixels / 43200); -1 disables
    frontend_max_packet_events: int = 0
    # a packet whose solution moves its events by >= 1 px but raises the contrast by less than this fraction over
    # omega = 0 is "suspect" (report.json counts them; most packets suspect: status "suspect")
    frontend_min_contrast_gain: float = 0.02
    # warm start of packet j: "previous" (omega_{j-1}) or "linear" (2 omega_{j-1} - omega_{j-2}, when both exist)
    frontend_warm_start: str = "linear"
    # Fletcher-Reeves CG
    frontend_cg_init_step: float = 0.1
    # 0.5 with the "secant" step guess (the reference's 0.05 costs ~2.5x the evaluations for no accuracy on
    # this smooth 3-parameter cost; measured with pipelines/bench_frontend.py)
    frontend_cg_line_search_tol: float = 0.5
    frontend_cg_max_iters: int = 50
    frontend_cg_grad_tol: float = 1e-3
    frontend_cg_rel_cost_tol: float = 1e-4
    frontend_cg_max_line_evals: int = 4  # evaluations per line search at most (then its best point is taken)
    # first trial step of each later line search: "decrease" (Nocedal & Wright eq. 3.60) or "secant" (minimum of
    # the quadratic model with the last step's secant curvature; see pipelines/optim.py)
    frontend_cg_step_guess: str = "secant"


@dataclass(frozen=True)
class BackendConfig:
    """Sliding-window CMax bundle adjustment (Sec. III-B, III-C2)."""

    backend_blur_sigma: float = 1.0
    event_batch_size: int = 100
    backend_event_sample_rate: int = 1
    backend_time_window_size: float = 0.2
    backend_sliding_window_stride: float = 0.1
    # 1 linear, 3 cubic. The reference defaults to linear; cubic is measured better at a similar cost on every
    # simulated sequence we ran (rel RMSE 0.12-0.30 vs 0.25-0.36 deg/s, abs 0.07-0.18 vs 0.09-0.21 deg)
    spline_degree: int = 3
    dt_knots: float = 0.05  # control-pose spacing (s)
    # 0 (or auto): derived from the focal length, width = 2 pi f x pano_pixels_per_sensor_pixel rounded up to a
    # multiple of 256 (pipelines/sensor_defaults.py)
    pano_height: int = 0
    pano_width: int = 0  # 0 means 2 * pano_height
    pano_pixels_per_sensor_pixel: float = 1.5  # map pixels per sensor pixel at the image centre (derived size)
    backend_min_ev_rate: float = 0.0  # events/s; below: camera treated as still, no BA; 0: 10000 x pixels / 43200
    # a window with more events is sampled evenly to this many for the BA (all events still go into the map);
    # 0 (or auto): 5 x pixels x backend_time_window_size / 0.2 s; -1: every event
    backend_max_window_events: int = 0
    freeze_pixels: bool = False
    max_update_time: float = 10.0  # s a map pixel stays updatable once observed (if freeze_pixels)
    lambda0: float = 1.0
    # a window whose optimum moves a control pose by more than this (rad) is a false maximum (e.g. a map too
    # coarse for the sensor, or a textureless window): the initialization is kept for that window
    backend_max_correction: float = 0.1
    # Fletcher-Reeves CG
    backend_cg_init_step: float = 0.1
    backend_cg_line_search_tol: float = 0.1
    backend_cg_max_iters: int = 50
    backend_cg_grad_tol: float = 1e-4
    backend_cg_rel_cost_tol: float = 1e-4
    backend_cg_max_line_evals: int = 20  # evaluations per line search at most
    backend_cg_step_guess: str = "decrease"  # first trial step of later line searches (see pipelines/optim.py)

    @property
    def pano_size(self) -> tuple[int, int]:
        """(width, height) of the panoramic map (resolve a derived size with the camera first)."""
        if self.pano_height <= 0:
            raise ValueError("pano_height is derived from the camera: resolve the config first "
                             "(ti_cmax.pipelines.sensor_defaults.resolve_config)")
        return (self.pano_width or 2 * self.pano_height, self.pano_height)


@dataclass(frozen=True)
class LoopClosureConfig:
    """Loop closure on revisits (pipelines/loop_closure.py): the recent events are registered against the map
    regions last observed long ago; an accepted correction is spread over the trajectory since that visit and
    the global map is rebuilt from stored event subsamples."""

    loop_closure: bool = False  # false: no loop closure (the back-end's output is bitwise unchanged)
    loop_min_age: float = 3.0  # s since a map region was last observed for it to count as old (a revisit)
    loop_recent_time: float = 1.0  # s of recent events registered against the old map; at most one check per this
    loop_min_overlap: float = 0.15  # fraction of the recent events that must fall on old observed map regions
    loop_min_confidence: float = 0.3  # correlation of the registered recent map with the old map, at least
    loop_min_peak_ratio: float = 1.5  # that correlation over its best value 4-8 map pixels away, at least (unique)
    loop_max_correction: float = 0.1  # rad; larger registrations are rejected as false loops
    loop_min_correction_px: float = 0.25  # corrections below this many map pixels are not applied (nothing to do)
    loop_min_gain: float = 0.02  # ... nor those raising that correlation by less (not supported by the data)
    loop_registration_events: int = 20000  # recent events used for the registration at most (thinned 1 of k)
    loop_stored_event_rate: float = 200000.0  # events/s kept (1 of k per stride) to rebuild the map after a loop
    loop_max_stored_events: int = 4000000  # all strides are thinned by 2 when the store exceeds this (memory)


@dataclass(frozen=True)
class DatasetConfig:
    """How to open a DATASET (``--set width=346 --set height=260 --set allow_default_calibration=true``)."""

    width: int = 0  # 0: from the calibration YAML, the events file, or inferred
    height: int = 0
    allow_default_calibration: bool = False  # no intrinsics found: use Camera.ideal (60 deg) instead of failing
    topic: str = ""  # ROS bag event topic ("": the only dvs_msgs/EventArray topic)
    chunk_size: int = 1_000_000  # events per streamed chunk


@dataclass(frozen=True)
class OutputConfig:
    gamma: float = 0.75
    trajectory_rate: float = 200.0  # Hz at which continuous trajectories are sampled to TUM
    num_threads: int = 0  # 0: all cores (or TI_CMAX_THREADS)


@dataclass(frozen=True)
class SlamConfig:
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    loop: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


# ------------------------------------------------------------------------------------------
# generic loading of nested frozen dataclasses
# ------------------------------------------------------------------------------------------

def _leaf_paths(cls, prefix=()) -> dict[str, tuple[str, ...]]:
    """Map every leaf field name (and dotted path) to its path in the nested dataclass."""
    out: dict[str, tuple[str, ...]] = {}
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        path = prefix + (f.name,)
        t = hints[f.name]
        if is_dataclass(t):
            out.update(_leaf_paths(t, path))
        else:
            out[".".join(path)] = path
            out.setdefault(f.name, path)
    return out


# keys whose 0 means "derived from the sensor" (pipelines/sensor_defaults.py); "auto" is accepted for them
DERIVED_KEYS = frozenset({"num_events_per_packet", "frontend_max_packet_events", "frontend_min_event_rate",
                          "pano_height", "backend_min_ev_rate", "backend_max_window_events"})


def _convert(value, typ, key: str, source: str):
    origin = typing.get_origin(typ)
    if isinstance(value, str) and value.strip().lower() == "auto" and key.split(".")[-1] in DERIVED_KEYS:
        return typ(0)
    try:
        if typ is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            return bool(value)
        if typ is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(float(value)) if isinstance(value, str) else int(value)
        if typ is float:
            return float(value)
        if typ is str:
            return str(value)
        if origin in (tuple, list):
            if isinstance(value, str):
                value = yaml.safe_load(value)
            return tuple(value)
    except (TypeError, ValueError):
        name = getattr(typ, "__name__", str(typ))
        raise InputError(f"field '{key}' expects {name}, got {value!r}", source=source) from None
    return value


def build_config(cls, values: dict, source: str = "config"):
    """Build a (nested) frozen dataclass from flat or nested key/values; unknown keys are errors."""
    paths = _leaf_paths(cls)
    flat: dict[tuple[str, ...], object] = {}

    def walk(d, prefix=()):
        for k, v in d.items():
            key = ".".join(prefix + (str(k),))
            if isinstance(v, dict) and key not in paths:
                walk(v, prefix + (str(k),))
                continue
            if key not in paths and str(k) in paths and not prefix:
                key = str(k)
            if key not in paths:
                raise InputError(f"unknown parameter '{key}'", source=source)
            flat[paths[key]] = v

    walk(values or {})
    return _apply(cls, flat, (), source)


def _apply(cls, flat, prefix, source):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in fields(cls):
        path = prefix + (f.name,)
        t = hints[f.name]
        if is_dataclass(t):
            kwargs[f.name] = _apply(t, flat, path, source)
        elif path in flat:
            kwargs[f.name] = _convert(flat[path], t, ".".join(path), source)
    return cls(**kwargs)


def parse_overrides(items: list[str] | None) -> dict:
    """['a=1', 'b.c=x'] -> {'a': 1, 'b.c': 'x'} (values parsed as YAML scalars)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise InputError(f"--set expects key=value, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError:
            out[k.strip()] = v
    return out


def load_config(cls, path: str | os.PathLike | None = None, overrides: list[str] | dict | None = None):
    """Defaults <- YAML file <- overrides. Errors name the file and the field."""
    values: dict = {}
    if path:
        try:
            with open(path) as fh:
                loaded = yaml.safe_load(fh)
        except FileNotFoundError:
            raise InputError("config file not found", source=str(path)) from None
        except yaml.YAMLError as exc:
            line = getattr(getattr(exc, "problem_mark", None), "line", None)
            raise InputError("not valid YAML", source=str(path), line=None if line is None else line + 1) from None
        if loaded is not None and not isinstance(loaded, dict):
            raise InputError("expected a mapping of parameter: value", source=str(path))
        values = _flatten(loaded or {})
    ov = overrides if isinstance(overrides, dict) else parse_overrides(overrides)
    cfg = build_config(cls, values, source=str(path) if path else "config")
    if ov:
        cfg = update_config(cfg, ov, source="--set")
    return cfg


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def update_config(cfg, values: dict, source: str = "config"):
    """Return a copy of cfg with flat or dotted keys replaced."""
    base = config_to_dict(cfg)
    merged = _flatten(base)
    paths = _leaf_paths(type(cfg))
    for k, v in values.items():
        if k not in paths:
            raise InputError(f"unknown parameter '{k}'", source=source)
        merged[".".join(paths[k])] = v
    return build_config(type(cfg), merged, source=source)


def config_to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def save_config(cfg, path: str | os.PathLike) -> None:
    """Write the config used beside the outputs (nested YAML, reloadable with --config)."""
    with open(path, "w") as fh:
        yaml.safe_dump(config_to_dict(cfg), fh, sort_keys=False)


__all__ = [
    "DatasetConfig", "FrontendConfig", "BackendConfig", "LoopClosureConfig", "OutputConfig", "SlamConfig",
    "load_config", "update_config", "build_config", "save_config", "config_to_dict", "parse_overrides", "replace",
]

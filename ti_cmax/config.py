"""Configuration: frozen dataclasses named after the reference implementation's launch parameters.

A config is loaded from YAML (flat, launch-file style, or nested by section) and from
``--set key=value`` overrides. Flat keys are resolved by their unique field name across sections,
so ``--set num_events_per_packet=20000`` and ``--set frontend.num_events_per_packet=20000`` both work.
The config used is written beside the outputs (:func:`save_config`).

Every field is declared with :func:`param`: its default, one line of meaning, its unit and its rule (range or
choices; ``zero=`` names what 0 means when 0 is allowed outside the range). The same declaration drives the
check made when a config is built (:class:`Params`, one :class:`InputError` naming the key and the allowed
values) and ``ti-cmax params``. Rules between fields go in a class's ``_relations`` method.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import operator
import os
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace

import yaml

from .errors import InputError

# ------------------------------------------------------------------------------------------
# declaring and checking fields
# ------------------------------------------------------------------------------------------

_BOUNDS = {"ge": operator.ge, "gt": operator.gt, "le": operator.le, "lt": operator.lt}


def param(default=dataclasses.MISSING, help: str = "", *, unit: str = "", ge=None, gt=None, le=None, lt=None,
          choices=None, zero: str | None = None, off: int | None = None, factory=None):
    """A config field: default, one line of help, unit, and its rule (bounds ge/gt/le/lt, or choices; ``zero``:
    0 is also allowed and means this; a ``zero`` starting with "derived" also accepts ``auto``; ``off``: this
    value is also allowed and switches the feature off). ``factory`` builds a mutable or nested default."""
    meta = {"help": help, "unit": unit, "ge": ge, "gt": gt, "le": le, "lt": lt,
            "choices": tuple(choices) if choices is not None else None, "zero": zero, "off": off}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


def rule_text(meta) -> str:
    """The allowed values of a field, as the error message and ``ti-cmax params`` state them."""
    if meta.get("choices") is not None:
        return "one of " + ", ".join(str(c) for c in meta["choices"])
    lo = f">= {meta['ge']:g}" if meta.get("ge") is not None else f"> {meta['gt']:g}" if meta.get("gt") is not None else ""
    hi = f"<= {meta['le']:g}" if meta.get("le") is not None else f"< {meta['lt']:g}" if meta.get("lt") is not None else ""
    text = " and ".join(s for s in (lo, hi) if s)
    if meta.get("zero"):
        text = f"0 ({meta['zero']}) or {text}" if text else f"0 means {meta['zero']}"
    if meta.get("off") is not None:
        text = f"{meta['off']} (off), {text}"
    return text


@functools.lru_cache(maxsize=None)
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _type_ok(value, typ) -> bool:
    if typ is bool:
        return isinstance(value, bool)
    if typ is int:  # numpy integers too
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if typ is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if typ is str:
        return isinstance(value, str)
    if typing.get_origin(typ) in (tuple, list):
        return isinstance(value, (tuple, list))
    return True


def check_field(key: str, value, typ, meta) -> None:
    """Raise InputError naming ``key`` and the allowed values when ``value`` breaks the field's rule."""
    if not _type_ok(value, typ):
        name = getattr(typ, "__name__", str(typ))
        extra = " (finite)" if typ is float else ""
        raise InputError(f"{key} expects {name}{extra}, got {value!r}")
    if (meta.get("zero") and value == 0) or (meta.get("off") is not None and value == meta["off"]):
        return
    if meta.get("choices") is not None:
        ok = value in meta["choices"]
    else:
        ok = all(op(value, meta[k]) for k, op in _BOUNDS.items() if meta.get(k) is not None)
    if not ok:
        unit = f" {meta['unit']}" if meta.get("unit") else ""
        raise InputError(f"{key} must be {rule_text(meta)}{unit}, got {value!r}")


def check_map_size(width: int, height: int, option: str, text: str, cls=None) -> None:
    """A map size given on the command line (``option``, e.g. --size, as ``text``) within the bounds of the
    ``pano_width`` and ``pano_height`` of ``cls`` (default: BackendConfig, the back-end's map): the size its own
    config would refuse is refused in one line naming the option (``map --size 2x1`` rendered a 2x1 panorama)."""
    for value, key, what in ((width, "pano_width", "width"), (height, "pano_height", "height")):
        meta = {**next(f for f in fields(cls or BackendConfig) if f.name == key).metadata, "zero": None, "off": None}
        try:
            check_field(key, value, int, meta)
        except InputError:
            unit = f" {meta['unit']}" if meta.get("unit") else ""
            raise InputError(f"{option} {text}: the map {what} must be {rule_text(meta)}{unit} (as {key}), "
                             f"got {value}") from None


def parse_map_size(text: str, option: str = "--size", cls=None) -> tuple[int, int]:
    """A command line's WIDTHxHEIGHT (``option``) within the map bounds of ``cls`` (:func:`check_map_size`);
    anything else is one error naming ``option``."""
    try:
        w, h = (int(v) for v in str(text).strip().lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise InputError(f"{option} expects WIDTHxHEIGHT, e.g. 1024x512, got {text!r}") from None
    check_map_size(w, h, option, text, cls)
    return w, h


def parse_map_sizes(text: str, option: str = "--sizes", cls=None) -> list[tuple[int, int]]:
    """'512x256,1024x512' -> [(512, 256), (1024, 512)], each as :func:`parse_map_size`; none is an error."""
    sizes = [parse_map_size(item.strip(), option, cls) for item in str(text).split(",") if item.strip()]
    if not sizes:
        raise InputError(f"{option} expects WIDTHxHEIGHT[,WIDTHxHEIGHT...], e.g. 512x256,1024x512, got {text!r}")
    return sizes


class Params:
    """Base of the config dataclasses: checks every field declared with :func:`param` when built (also by
    ``dataclasses.replace``), then the class's ``_relations`` (rules between fields)."""

    def __post_init__(self):
        hints = _hints(type(self))
        for f in fields(self):
            typ = hints[f.name]
            if not is_dataclass(typ):
                value = getattr(self, f.name)
                check_field(f.name, value, typ, f.metadata)
                if typ in (int, float) and type(value) is not typ:  # numpy scalars -> Python (YAML-safe)
                    object.__setattr__(self, f.name, typ(value))
        self._relations()

    def _relations(self) -> None:
        """Rules between fields; raise InputError naming the keys."""


def iter_params(cls, prefix: str = ""):
    """(dotted key, field, type) of every leaf field of a (nested) config dataclass, in declaration order."""
    hints = _hints(cls)
    for f in fields(cls):
        if is_dataclass(hints[f.name]):
            yield from iter_params(hints[f.name], f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, hints[f.name]


def field_default(f):
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


# choices shared with the pipelines (which import them from here)
CONTRAST_MEASURES = ("variance", "mean_square")
SLICING_RULES = ("bounded", "paper")
WARM_STARTS = ("previous", "linear")
STEP_GUESSES = ("decrease", "secant")  # first trial step of later line searches (see pipelines/optim.py)
OPTIMIZERS = ("bfgs", "cg")  # pipelines/optim.py: warm-started BFGS, or the reference's Fletcher-Reeves CG


@dataclass(frozen=True)
class FrontendConfig(Params):
    """CMax-omega front-end (Sec. II-B, III-C1)."""

    contrast_measure: str = param("variance", "contrast of the image of warped events", choices=CONTRAST_MEASURES)
    frontend_blur_sigma: float = param(1.0, "Gaussian blur of the IWE, in sensor pixels (sigma / d IWE pixels)",
                                       unit="px", ge=0, le=50)
    # the IWE has 1/d of the sensor's pixels per axis (the optimiser's pixel tolerances are IWE pixels, d sensor
    # pixels wide); derived from the blur and the sensor's pixel count (pipelines/sensor_defaults.py)
    frontend_iwe_downsample: int = param(0, "IWE pixel = d x d sensor pixels; derived: the largest d <= sqrt(6) x "
                                            "blur sigma keeping >= 43200 IWE pixels", ge=1, le=16, zero="derived")
    frontend_event_sample_rate: int = param(1, "keep 1 of Q events", ge=1)
    num_events_per_packet: int = param(0, "events per packet N (Sec. III-C1); derived: 10000 x max(1, IWE pixels / "
                                          "43200)",
                                       unit="events", ge=2, le=10_000_000, zero="derived")
    dt_ang_vel: float = param(0.01, "spacing of the packet centres, 1/f", unit="s", gt=0)
    still_span_factor: float = param(10.0, "a packet spanning more than this x dt_ang_vel means a still camera",
                                     gt=0)
    # a longer pause is taken for a stray event or a jump of the clock (a lone event at t = 0 before Unix-time
    # stamps: 1.7e9 s), which would cost ~0.04 s of packets and windows per second of pause: one clear error instead
    max_event_gap: float = param(60.0, "longest pause between two events the pipelines accept", unit="s", gt=0)
    # "bounded" (default): a packet spanning more than W = still_span_factor*dt_ang_vel is shrunk to the
    # events within t_ref +- W/2, and omega = 0 only if fewer than frontend_min_event_rate*W remain.
    # "paper": the reference rule (omega = 0 as soon as the N events span more than W).
    frontend_slicing: str = param("bounded", "still-camera rule: bounded (shrink long packets) or paper (omega = 0)",
                                  choices=SLICING_RULES)
    frontend_min_event_rate: float = param(0.0, "event-rate floor of the bounded rule; derived: 10000 x pixels / 43200",
                                           unit="events/s", gt=0, zero="derived")
    # packets take at least every event within t_ref +- span/2 (high event rates: N events would cover too
    # little motion to measure); 0 disables (the reference's fixed N)
    frontend_min_packet_span: float = param(0.04, "a packet holds at least every event within this span (0: off)",
                                            unit="s", ge=0)
    # packets holding more events than this are thinned uniformly (1 of k, k = ceil(n / max)) before the
    # optimisation: the span (motion) is kept, the cost per packet is bounded at high event rates
    frontend_max_packet_events: int = param(0, "packets with more events are thinned 1 of k; derived: (d + 1) x 10000 "
                                               "x max(1, IWE pixels / 43200)", unit="events", ge=2, le=10_000_000,
                                            zero="derived", off=-1)
    # each integer event pixel is dithered by up to this many pixels (uniform, from a fixed table: deterministic)
    # before warping, so that omega = 0 is not favoured by the pixel grid (pipelines/frontend.PixelDither); 0: none
    frontend_pixel_dither: float = param(0.5, "sub-pixel dither of event coordinates against the pixel-grid bias",
                                         unit="px", ge=0)
    # a packet whose solution moves its events by >= 1 px but raises the contrast by less than this fraction over
    # omega = 0 is "suspect" (report.json counts them; most packets suspect: status "suspect")
    frontend_min_contrast_gain: float = param(0.02, "checked packets moving >= 1 px but gaining less contrast over "
                                                    "omega = 0 are suspect", ge=0)
    # a packet whose optimum moves its farthest event by under 1 px (or 1 px or more away from its warm start) is
    # tested for whether its events measure any motion at all: the score test of omega = 0 (the gradient at omega = 0
    # against the spread of its per-event terms, chi-square with 3 degrees of freedom); under this score the
    # packet is flat: omega = 0, since its optimum is noise (pipelines/frontend_policies.needs_score_test)
    frontend_flat_is_still: bool = param(True, "a packet whose motion is not significant (score test) takes omega = 0")
    frontend_min_motion_score: float = param(16.3, "score of omega = 0 a tested packet needs to keep its motion "
                                                   "(chi-square 3 dof; 16.3: 0.1 % false motion)", ge=0)
    # a flat packet's recent past is score-tested too (pipelines/frontend_policies.LookbackTest): the events of the
    # last 4x its span, then 16x, ..., up to this many seconds (0: off); motions far under a pixel per packet (starts,
    # stops, slow pans) add up to pixels over a longer span. The packet keeps omega = 0; a window of flat packets none
    # of whose lookbacks measured a motion gets no BA (backend_skip_still_windows)
    frontend_flat_lookback: float = param(0.64, "a flat packet's past is tested for motion over the events of the "
                                                "last 4x, 16x ... its span, up to this (0: off)", unit="s", ge=0)
    # the scheduled checks (a cost-only evaluation: vote and blur, ~0.6 of a full one) feed the status, a majority
    # over them: 10 per second of data (100 Hz packets) are plenty for that
    frontend_gain_check_every: int = param(10, "the contrast at omega = 0 (suspect check) is evaluated on 1 of this "
                                              "many moving packets", ge=1)
    # warm start of packet j: "previous" (omega_{j-1}) or "linear" (2 omega_{j-1} - omega_{j-2}, when both exist)
    frontend_warm_start: str = param("linear", "initial omega: previous packet's, or linear extrapolation",
                                     choices=WARM_STARTS)
    # "bfgs" (default): BFGS whose inverse Hessian carries over from packet to packet, so each packet starts with a
    # quasi-Newton step: about 3 evaluations per packet instead of CG's 4-5, for the same accuracy; "cg": the
    # reference's Fletcher-Reeves CG. The frontend_cg_* tolerances (iterations,
    # gradient, relative cost, evaluations per line search, first step) apply to both
    frontend_optimizer: str = param("bfgs", "contrast maximiser per packet", choices=OPTIMIZERS)
    frontend_bfgs_max_step: float = param(2.0, "BFGS steps are capped at this displacement of the packet's "
                                                "farthest event", unit="px", gt=0)
    # 0.05 px (1/20 of the blur sigma): an evaluation that cannot move the farthest event by more does not change
    # omega measurably, so those evaluations are saved
    frontend_bfgs_step_tol: float = param(0.05, "BFGS stops when its next step would move the packet's farthest "
                                                "event by less than this", unit="px", ge=0)
    # Fletcher-Reeves CG
    frontend_cg_init_step: float = param(0.1, "CG first trial step (BFGS: its first step without a Hessian)", gt=0)
    # 0.5 with the "secant" step guess (the reference's 0.05 costs ~2.5x the evaluations for no accuracy on
    # this smooth 3-parameter cost; measured with pipelines/evaluation/bench_frontend.py)
    frontend_cg_line_search_tol: float = param(0.5, "CG line-search (strong Wolfe curvature) tolerance", gt=0, lt=1)
    frontend_cg_max_iters: int = param(50, "CG (BFGS) line searches per packet at most", ge=1)
    frontend_cg_grad_tol: float = param(1e-3, "CG (BFGS) stops below this gradient norm", ge=0)
    frontend_cg_rel_cost_tol: float = param(1e-4, "CG (BFGS) stops below this relative cost change", ge=0)
    frontend_cg_max_line_evals: int = param(4, "evaluations per line search at most (then its best point)", ge=1)
    # first trial step of each later line search: "decrease" (Nocedal & Wright eq. 3.60) or "secant" (minimum of
    # the quadratic model with the last step's secant curvature; see pipelines/optim.py)
    frontend_cg_step_guess: str = param("secant", "first trial step of later line searches", choices=STEP_GUESSES)
    # hot pixels (pipelines/hot_pixels.py): over a block of events, a pixel firing at least hot_pixel_min_events and
    # hot_pixel_factor x (1 + the count of its busiest neighbour within 2 px) is not seeing the scene (motion moves
    # patterns across neighbours): its events are dropped from then on, before the front-end and the back-end see
    # them; report.json "hot_pixels" lists what was flagged
    hot_pixel_filter: bool = param(True, "drop the events of hot pixels (firing far more than every neighbour) at the "
                                         "ingest")
    hot_pixel_factor: float = param(8.0, "a hot pixel fires at least this x (1 + its busiest neighbour's events) in a "
                                         "block", gt=1)
    hot_pixel_min_events: int = param(16, "a hot pixel fires at least this many events in a block", unit="events",
                                      ge=2)
    hot_pixel_hold_time: float = param(0.5, "events are held back at the start until the first block is tested, at "
                                            "most this long", unit="s", ge=0)


@dataclass(frozen=True)
class BackendConfig(Params):
    """Sliding-window CMax bundle adjustment (Sec. III-B, III-C2)."""

    backend_blur_sigma: float = param(1.0, "Gaussian blur of the panoramic IWE", unit="px", ge=0, le=50)
    event_batch_size: int = param(100, "events sharing one pose", unit="events", ge=1)
    backend_event_sample_rate: int = param(1, "keep 1 of Q events", ge=1)
    backend_time_window_size: float = param(0.2, "sliding window length", unit="s", gt=0)
    backend_sliding_window_stride: float = param(0.1, "window step (<= backend_time_window_size)", unit="s", gt=0)
    # 1 linear, 3 cubic. The reference defaults to linear; cubic is measured better at a similar cost on every
    # simulated sequence we ran (rel RMSE 0.12-0.30 vs 0.25-0.36 deg/s, abs 0.07-0.18 vs 0.09-0.21 deg)
    spline_degree: int = param(3, "trajectory spline: 1 linear, 3 cubic", choices=(1, 3))
    dt_knots: float = param(0.05, "control-pose spacing (<= backend_sliding_window_stride)", unit="s", ge=1e-3)
    pano_height: int = param(0, "panoramic map height; derived: width 2 pi f x pano_pixels_per_sensor_pixel, up to a "
                                "multiple of 256, at most 8192", unit="px", ge=8, le=16384, zero="derived")
    pano_width: int = param(0, "panoramic map width", unit="px", ge=16, le=32768, zero="2 x pano_height")
    pano_pixels_per_sensor_pixel: float = param(1.5, "map pixels per sensor pixel at the image centre (derived size)",
                                                gt=0)
    # the BA's map: the output map d times coarser per axis (its blur sigma in the BA map's pixels); derived from the
    # sensor's view on the map (pipelines/sensor_defaults.py)
    backend_map_downsample: int = param(0, "BA map pixel = d x d map pixels; derived: the largest d <= sqrt(6) x "
                                           "blur sigma keeping the sensor's view >= 97200 BA map pixels", ge=1, le=16,
                                        zero="derived")
    backend_min_ev_rate: float = param(0.0, "below this rate the camera is still: no BA; derived: 10000 x pixels / "
                                            "43200", unit="events/s", gt=0, zero="derived")
    # a window with more events is sampled evenly to this many for the BA (all events still go into the map)
    backend_max_window_events: int = param(0, "BA events per window at most (even sample); derived: 5 x pixels x "
                                              "window / 0.2 s, on a coarser BA map at most 2.2 per BA-map pixel of "
                                              "the sensor's view", unit="events", ge=200, zero="derived", off=-1)
    freeze_pixels: bool = param(False, "map pixels stop updating max_update_time after first seen")
    max_update_time: float = param(10.0, "time a map pixel stays updatable (with freeze_pixels)", unit="s", gt=0)
    lambda0: float = param(1.0, "weight of the event area in the map quality figures", gt=0)
    # a window over which the source measured no motion (the front-end: flat or still packets only, none of whose
    # lookbacks measured a motion; a given trajectory or IMU always counts as moving) holds nothing the BA could
    # refine: its events are noise or a still scene, which a BA fits with degrees of spurious rotation; a window that
    # starts still keeps the control poses of its still part (pipelines/backend.SlidingWindowBackend._moving_from)
    backend_skip_still_windows: bool = param(True, "no BA over the parts of windows where the source measured no "
                                                   "motion")
    # a window whose optimum moves the trajectory at its events by more than this (rad) is a false maximum (e.g. a
    # map too coarse for the sensor, or a textureless window): the initialization is kept for that window
    backend_max_correction: float = param(0.1, "a window's larger correction is a false maximum (kept as initialized)",
                                          unit="rad", gt=0)
    # "bfgs" (default): BFGS whose inverse Hessian carries over from window to window (shifted by the knots the
    # window drops; new control poses start with the mean curvature): fewer evaluations per window than CG, and
    # better converged. "cg": the reference's Fletcher-Reeves CG. The backend_cg_* tolerances apply to both
    backend_optimizer: str = param("bfgs", "window optimiser", choices=OPTIMIZERS)
    backend_bfgs_max_step: float = param(0.05, "BFGS steps (norm over the free control poses) are capped at this",
                                         unit="rad", gt=0)
    # the step that would only confirm convergence (predicted cost change under half backend_cg_rel_cost_tol) is
    # taken without its evaluation (pipelines/optim.bfgs): fewer BA evaluations at the same accuracy
    backend_bfgs_last_step_unevaluated: bool = param(True, "BFGS takes a last step predicted to change the cost by "
                                                     "under half backend_cg_rel_cost_tol without evaluating it")
    # Fletcher-Reeves CG
    backend_cg_init_step: float = param(0.1, "CG first trial step (BFGS: its first step without a Hessian)", gt=0)
    backend_cg_line_search_tol: float = param(0.1, "CG line-search (strong Wolfe curvature) tolerance", gt=0, lt=1)
    backend_cg_max_iters: int = param(50, "CG (BFGS) line searches per window at most", ge=1)
    backend_cg_grad_tol: float = param(1e-4, "CG (BFGS) stops below this gradient norm", ge=0)
    backend_cg_rel_cost_tol: float = param(1e-4, "CG (BFGS) stops below this relative cost change", ge=0)
    backend_cg_max_line_evals: int = param(20, "evaluations per line search at most", ge=1)
    backend_cg_step_guess: str = param("decrease", "first trial step of later line searches", choices=STEP_GUESSES)

    def _relations(self) -> None:
        if self.backend_sliding_window_stride > self.backend_time_window_size:
            raise InputError(f"backend_sliding_window_stride must be <= backend_time_window_size "
                             f"({self.backend_time_window_size:g} s), got {self.backend_sliding_window_stride:g}")
        if self.dt_knots > self.backend_sliding_window_stride * (1 + 1e-6):  # windows would refine poses far outside
            raise InputError(f"dt_knots must be <= backend_sliding_window_stride "
                             f"({self.backend_sliding_window_stride:g} s), got {self.dt_knots:g}")

    @property
    def pano_size(self) -> tuple[int, int]:
        """(width, height) of the panoramic map (resolve a derived size with the camera first)."""
        if self.pano_height <= 0:
            raise ValueError("pano_height is derived from the camera: resolve the config first "
                             "(ti_cmax.pipelines.sensor_defaults.resolve_config)")
        return (self.pano_width or 2 * self.pano_height, self.pano_height)


@dataclass(frozen=True)
class LoopClosureConfig(Params):
    """Loop closure on revisits (pipelines/loop_closure.py): the recent events are registered against the map
    regions last observed long ago; an accepted correction is spread over the trajectory since that visit and
    the global map is rebuilt from stored event subsamples."""

    # on by default: without a revisit the output is bitwise that of false (no candidate, or none applied), on
    # revisits it cuts the error the first visit's map carries, and it costs a few % of a run; false turns it off
    loop_closure: bool = param(True, "loop closure on revisits (false: the back-end's output is bitwise that without "
                                     "the loop closer)")
    loop_min_age: float = param(3.0, "time since a map region was last observed for it to count as old", unit="s",
                                gt=0)
    loop_min_travel: float = param(0.0, "rotation the camera travelled since a map region was last observed for it "
                                        "to count as old also before loop_min_age (at least loop_recent_time after); "
                                        "derived: 360 deg less twice the horizontal field of view", unit="deg", gt=0,
                                   zero="derived", off=-1)
    loop_recent_time: float = param(1.0, "recent events registered against the old map; at most one check per this",
                                    unit="s", gt=0)
    loop_min_overlap: float = param(0.15, "fraction of the recent events that must fall on old observed regions",
                                    gt=0, le=1)
    loop_min_confidence: float = param(0.3, "local-texture correlation of the registered recent map with the old "
                                            "map, at least", ge=0)
    loop_min_peak_ratio: float = param(1.5, "that correlation over its best value 4-8 map px away, at least",
                                       ge=1)
    loop_max_correction: float = param(0.1, "larger registrations are rejected as false loops", unit="rad", gt=0)
    loop_min_correction_px: float = param(0.25, "corrections below this are not applied", unit="map px", ge=0)
    loop_min_gain: float = param(0.02, "corrections raising the correlation by less are not applied", ge=0)
    loop_check_drift_px: float = param(2.0, "after an applied loop, the next check waits until the drift rate that "
                                            "loop measured has moved the map this far (between loop_recent_time and "
                                            "loop_min_age; 0: at loop_recent_time)", unit="map px", ge=0)
    loop_registration_events: int = param(0, "recent events used for the registration at most (thinned); derived: "
                                             "20 000 x max(1, pixels / 43200)", unit="events", ge=100,
                                          zero="derived")
    loop_stored_event_rate: float = param(200000.0, "events kept per second to rebuild the map after a loop",
                                          unit="events/s", gt=0)
    loop_max_stored_events: int = param(4000000, "stored events at most (all strides thinned by 2 beyond)",
                                        unit="events", ge=1000)
    loop_joint_refinement: bool = param(True, "at a verified revisit (at most once per turn: 360 deg of rotation "
                                              "travelled and the map seen again since the last one), refine the "
                                              "control poses since the first stored stride jointly with the stored "
                                              "events (a BA of the map over the visits) before the map is rebuilt")
    loop_joint_events: int = param(500000, "stored events the joint refinement uses at most (an even sample)",
                                   unit="events", ge=1000)
    loop_joint_iterations: int = param(20, "L-BFGS iterations of the joint refinement", ge=1)
    loop_joint_start_span: float = param(0.5, "with the joint refinement, the start of the trajectory (up to this "
                                              "long after its first window's worth of events) is refined against the "
                                              "map of the later events (0: not)", unit="s", ge=0)


@dataclass(frozen=True)
class RealtimeConfig(Params):
    """``ti-cmax slam --realtime``: replay in sensor time and the degradation controller (pipelines/realtime.py)."""

    realtime_target_lag: float = param(0.3, "lag (wall time behind sensor time when a window completes) the "
                                            "controller keeps below by degrading", unit="s", gt=0)
    realtime_max_lag: float = param(1.0, "hard bound: above it (at the last degradation level) only 1 of q events is "
                                         "handed over", unit="s", gt=0)
    realtime_chunk: float = param(0.002, "sensor time handed over at once while keeping up", unit="s", gt=0)
    realtime_min_window_events: int = param(0, "BA events per window never sampled below this when degrading; "
                                               "derived: 1 x pixels x window / 0.2 s", unit="events", ge=200,
                                            zero="derived")
    realtime_speed: float = param(1.0, "replay speed: sensor seconds per wall second (above 1: a stress test)",
                                  gt=0)

    def _relations(self) -> None:
        if self.realtime_max_lag < self.realtime_target_lag:
            raise InputError(f"realtime_max_lag must be >= realtime_target_lag ({self.realtime_target_lag:g} s), "
                             f"got {self.realtime_max_lag:g}")
        if self.realtime_chunk > self.realtime_target_lag:  # a longer hand-over is a lag by itself
            raise InputError(f"realtime_chunk must be <= realtime_target_lag ({self.realtime_target_lag:g} s), "
                             f"got {self.realtime_chunk:g}")


@dataclass(frozen=True)
class DatasetConfig(Params):
    """How to open a DATASET (``--set width=346 --set height=260 --set allow_default_calibration=true``)."""

    width: int = param(0, "sensor width", unit="px", ge=1, zero="from the calibration YAML, events file or inferred")
    height: int = param(0, "sensor height", unit="px", ge=1, zero="from the calibration YAML, events file or inferred")
    allow_default_calibration: bool = param(False, "no intrinsics found: use an ideal 60 deg camera instead of failing")
    topic: str = param("", "ROS bag event topic (empty: the only dvs_msgs/EventArray topic)")
    chunk_size: int = param(1_000_000, "events per streamed chunk", unit="events", ge=1)
    time_unit: str = param("auto", "unit of the event times of text and HDF5 files (auto: the file's: seconds in "
                                   "text; in HDF5 its units attribute, else seconds for floats, microseconds for "
                                   "integers)", choices=("auto", "s", "ms", "us", "ns"))

    def _relations(self) -> None:
        if (self.width == 0) != (self.height == 0):
            raise InputError(f"give both width and height, or neither (got width={self.width}, height={self.height})")


@dataclass(frozen=True)
class OutputConfig(Params):
    """What the outputs look like."""

    gamma: float = param(0.75, "gamma of the map images", gt=0)
    trajectory_rate: float = param(200.0, "rate at which continuous trajectories are sampled to TUM", unit="Hz", gt=0,
                                   le=100_000)
    num_threads: int = param(0, "CPU threads of the kernels (--threads wins)", ge=1, le=1024,
                             zero="all cores or TI_CMAX_THREADS")


@dataclass(frozen=True)
class GrayscaleConfig(Params):
    """Mapping module of SMT (App. B; pipelines/workflows/grayscale.py). Load with ``load_config(GrayscaleConfig, ...)`` or nest
    it in a config."""

    contrast_threshold: float = param(0.0, "contrast threshold C", ge=0,
                                      zero="the simulator's value if known, else 0.22 (real data, App. B)")
    measurement_noise: float = param(0.05, "sigma_z of z = p C (log-intensity units)", gt=0)
    initial_gradient_variance: float = param(1.0, "prior covariance of g: this x I (log intensity per map pixel)",
                                             gt=0)
    outlier_distance_px: float = param(10.0, "consecutive events of a sensor pixel farther apart in the map: outlier",
                                       unit="map px", gt=0)
    max_updates_per_pixel: int = param(5, "visits after which a map pixel stops updating", ge=1, zero="no cap")
    visit_gap: float = param(0.1, "time without update that ends a visit of a map pixel (0: every update)", unit="s",
                             ge=0)
    event_batch_size: int = param(100, "events sharing one pose (at the batch's mid-time)", unit="events", ge=1)
    pano_height: int = param(512, "map height", unit="px", ge=2)
    pano_width: int = param(0, "map width", unit="px", ge=4, zero="2 x pano_height")  # the mapper's minimum
    mapping_precision: str = param("f32", "float precision of the EKFs: f32 (production) or f64", choices=("f32", "f64"))
    coverage_interval: float = param(0.01, "time between poses marked in the observed-area mask", unit="s", gt=0)
    display_percentile_low: float = param(1.0, "robust 8-bit normalization of M over the observed pixels: low",
                                          unit="%", ge=0, le=100)
    display_percentile_high: float = param(99.0, "same, high percentile (> low)", unit="%", ge=0, le=100)

    def _relations(self) -> None:
        if not self.display_percentile_low < self.display_percentile_high:
            raise InputError(f"display_percentile_low must be < display_percentile_high "
                             f"({self.display_percentile_high:g}), got {self.display_percentile_low:g}")

    @property
    def pano_size(self) -> tuple[int, int]:
        return (self.pano_width or 2 * self.pano_height, self.pano_height)


@dataclass(frozen=True)
class SlamConfig(Params):
    """All parameters of CMax-SLAM (``ti-cmax slam``, ``refine``, ``frontend``, ``map``, ...)."""

    dataset: DatasetConfig = param(help="opening the dataset", factory=DatasetConfig)
    frontend: FrontendConfig = param(help="CMax-omega front-end", factory=FrontendConfig)
    backend: BackendConfig = param(help="sliding-window BA and the panoramic map", factory=BackendConfig)
    loop: LoopClosureConfig = param(help="loop closure on revisits", factory=LoopClosureConfig)
    realtime: RealtimeConfig = param(help="real-time replay and degradation (slam --realtime)", factory=RealtimeConfig)
    output: OutputConfig = param(help="outputs", factory=OutputConfig)


# ------------------------------------------------------------------------------------------
# work a config implies over a recording
# ------------------------------------------------------------------------------------------

# packets, control poses, windows, trajectory samples or real-time hand-overs a run may need at most: 1e7 packets are
# a day of data at the default 100 Hz; more means a parameter far off its scale (dt_ang_vel=1e-9: 3e8 packets, hours)
MAX_WORK_ITEMS = 10_000_000


def check_workload(cfg, t_start: float, t_end: float, *, realtime: bool = False) -> None:
    """Refuse, before any work, a config whose spacings imply more than MAX_WORK_ITEMS packets (dt_ang_vel), control
    poses (dt_knots), windows (backend_sliding_window_stride) or, with
    ``realtime``, hand-overs (realtime_chunk) over the recording's time range [t_start, t_end] (s): one InputError
    with the estimate. ``cfg``: a SlamConfig or any config holding some of these sections."""
    duration = max(float(t_end) - float(t_start), 0.0)
    fe, be, rt = (getattr(cfg, k, None) for k in ("frontend", "backend", "realtime"))
    items = []  # (key, value, unit, count, what)
    if fe is not None:
        items.append(("dt_ang_vel", fe.dt_ang_vel, "s", duration / fe.dt_ang_vel, "front-end packets"))
    if be is not None:
        items.append(("dt_knots", be.dt_knots, "s", duration / be.dt_knots, "control poses"))
        items.append(("backend_sliding_window_stride", be.backend_sliding_window_stride, "s",
                      duration / be.backend_sliding_window_stride, "back-end windows"))
    if realtime and rt is not None:
        items.append(("realtime_chunk", rt.realtime_chunk, "s", duration / rt.realtime_chunk, "real-time hand-overs"))
    for key, value, unit, count, what in items:
        if count > MAX_WORK_ITEMS:
            raise InputError(f"{key}={value:g} {unit} over this recording's {duration:.6g} s (t = {t_start:.6g} to "
                             f"{t_end:.6g} s) means {count:.3g} {what}, more than {MAX_WORK_ITEMS:.0e}: refused before "
                             f"any work; set {key} to its scale (default {_default_of(cfg, key):g} {unit})")


# The smallest input that gives a trustworthy omega. Measured with the default front-end on simulated city sequences
# (about 1.3 rad/s; 1.6 M events/s on a DAVIS240C, 0.5 M on a DVS128), K events drawn from 40 ms (the minimum packet
# span) at 12 places each: K = 20-100 gave omega off by 110-120 % of the rotation (median; up to 7.9 rad/s) and was
# never called flat (status ok); K = 200-1000 was called flat (omega = 0: off by 100 %); K = 2000 was off by 24-25 %
# (median), K = 5000 by 17-24 %. K consecutive events (1.3 ms at 1.6 M events/s) were flat up to 2000, 28 % off at 5000.
MIN_OMEGA_EVENTS = 2000  # events per packet, on a sensor of up to OMEGA_REFERENCE_PIXELS; scaled with pixels above
OMEGA_REFERENCE_PIXELS = 240 * 180


def min_events_for_omega(width: int, height: int) -> int:
    """The fewest events a packet (or a whole input) needs for a trustworthy omega on a width x height sensor:
    MIN_OMEGA_EVENTS, times the pixel count over OMEGA_REFERENCE_PIXELS on larger sensors (as the packet size N)."""
    return int(math.ceil(MIN_OMEGA_EVENTS * max(1.0, width * height / OMEGA_REFERENCE_PIXELS)))


def too_few_events_for_omega(num_events: int, width: int, height: int) -> str | None:
    """One line saying why ``num_events`` events (a packet's or an input's) give no trustworthy omega on a width x
    height sensor, or None when they are enough (:func:`min_events_for_omega`)."""
    need = min_events_for_omega(width, height)
    if num_events >= need:
        return None
    return (f"{num_events} events are too few for a trustworthy angular velocity on a {width}x{height} sensor (at "
            f"least {need}: with fewer, omega was off by 100 % of the rotation or more)")


def _default_of(cfg, key: str):
    """The default of the leaf field ``key`` of a (nested) config."""
    for _, f, _ in iter_params(type(cfg)):
        if f.name == key:
            return field_default(f)
    raise KeyError(key)


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


def _convert(value, typ, key: str, source: str):
    origin = typing.get_origin(typ)
    try:
        if typ is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                if low in ("1", "true", "yes", "on"):
                    return True
                if low in ("0", "false", "no", "off"):
                    return False
                raise ValueError
            if isinstance(value, bool) or (isinstance(value, numbers.Integral) and value in (0, 1)):
                return bool(value)
            raise ValueError  # 2, [1], 0.5: not a yes / no
        if isinstance(value, bool) and typ in (int, float):  # YAML's true is not the number 1 for a size
            raise ValueError
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
            value = flat[path]
            if isinstance(value, str) and value.strip().lower() == "auto" and \
                    str(f.metadata.get("zero") or "").startswith("derived"):
                value = 0  # "auto": derived from the sensor
            kwargs[f.name] = _convert(value, t, ".".join(path), source)
    try:
        return cls(**kwargs)
    except InputError as exc:
        if exc.source is not None:
            raise
        raise InputError(str(exc), source=source) from None


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
        except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, not a text file
            raise InputError(f"cannot read the config file ({type(exc).__name__}: "
                             f"{getattr(exc, 'strerror', None) or exc})", source=str(path)) from None
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
    "param", "Params", "iter_params", "check_field", "rule_text", "field_default",
    "CONTRAST_MEASURES", "OPTIMIZERS", "SLICING_RULES", "WARM_STARTS", "STEP_GUESSES", "DatasetConfig", "FrontendConfig",
    "BackendConfig", "LoopClosureConfig", "RealtimeConfig", "OutputConfig", "SlamConfig",
    "load_config", "update_config", "build_config", "save_config", "config_to_dict", "parse_overrides", "replace",
    "check_workload", "MAX_WORK_ITEMS", "MIN_OMEGA_EVENTS", "min_events_for_omega", "too_few_events_for_omega",
]

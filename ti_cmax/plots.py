"""PNG figures of the evaluation (matplotlib, Agg, no pyplot state): trajectories per axis (paper Fig. 6/8/12),
errors over time, error distributions per method (violins, Fig. 7/9/13) and panoramic maps side by side
(Fig. 5/10; cropped to the observed region, contrast stretched, so sharpness can be judged).

Each function takes data, writes one PNG (atomically) and returns nothing.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from . import so3
from .metrics import event_area_percent, gradient_magnitude
from .outputs import atomic_path
from .trajectory import Trajectory

if TYPE_CHECKING:
    from .metrics import RotationErrors

_GT_STYLE = dict(color="k", linestyle="--", linewidth=1.2, label="ground truth")
_AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")  # x, y, z (roll, pitch, yaw)
METRICS_CAPTION = ("EA = event area (% of map pixels with events, lower = sharper); "
                   "GM = gradient magnitude of the map (higher = sharper)")


def _figure(width: float, height: float, layout: str | None = "constrained"):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=100, layout=layout)


def _stacked(fig, rows: int, *, title: bool, left: float = 1.05, right: float = 0.2, bottom: float = 0.55,
             gap: float = 0.35):
    """``rows`` axes stacked over a shared time axis, placed with fixed margins and gaps in inches (room for
    two-line y labels, a panel title in each gap and the figure's title) instead of a layout engine, which measures
    every text of the figure in an extra draw: about a third of the cost of a run's figure."""
    w, h = fig.get_size_inches()
    top = 0.5 if title else 0.2
    axes_height = (h - top - bottom - gap * (rows - 1)) / rows
    axes = fig.subplots(rows, 1, sharex=True, gridspec_kw=dict(
        left=left / w, right=1 - right / w, top=1 - top / h, bottom=bottom / h, hspace=gap / axes_height))
    return np.atleast_1d(axes)


def _save(fig, path, compress_level: int | None = None) -> None:
    """The figure as PNG; ``compress_level`` (zlib's 0-9; Pillow's default 6): lower is faster, the file larger."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png",
                    pil_kwargs=None if compress_level is None else {"compress_level": compress_level})


def _angles_deg(traj: Trajectory, representation: str) -> tuple[np.ndarray, list[str]]:
    """Per-axis angles (N, 3) in degrees, unwrapped over time so that no jump of 360 deg is drawn."""
    if representation == "euler":
        ang = np.unwrap(so3.euler_xyz(traj.R), axis=0)
        labels = ["roll (x) [deg]", "pitch (y) [deg]", "yaw (z) [deg]"]
    elif representation == "rotvec":
        ang = so3.log(traj.R)
        labels = ["rotvec x [deg]", "rotvec y [deg]", "rotvec z [deg]"]
    else:
        raise ValueError(f"representation must be 'euler' or 'rotvec', got {representation!r}")
    return np.degrees(ang), labels


def plot_trajectories(path: str | os.PathLike, estimates: Mapping[str, Trajectory],
                      groundtruth: Trajectory | None = None, *, representation: str = "euler",
                      title: str | None = None) -> None:
    """Three stacked panels (one per axis) of angle vs time: each method as a solid line, GT dashed.

    Trajectories are drawn as given: align them first (Trajectory.aligned_to) to compare with the GT.
    Euler angles: scipy's extrinsic 'xyz' (roll about x, pitch about y, yaw about z) of R_world_from_camera.
    """
    fig = _figure(9, 7)
    axes = fig.subplots(3, 1, sharex=True)
    labels = None
    for name, traj in estimates.items():
        ang, labels = _angles_deg(traj, representation)
        for i, ax in enumerate(axes):
            ax.plot(traj.t, ang[:, i], linewidth=1.0, label=name)
    if groundtruth is not None:
        ang, labels = _angles_deg(groundtruth, representation)
        for i, ax in enumerate(axes):
            ax.plot(groundtruth.t, ang[:, i], **_GT_STYLE)
    for i, ax in enumerate(axes):
        if labels:
            ax.set_ylabel(labels[i])
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    if estimates or groundtruth is not None:
        axes[0].legend(loc="best", fontsize="small", ncol=min(4, len(estimates) + 1))
    if title:
        fig.suptitle(title)
    _save(fig, path)


def _violins(ax, data: Mapping[str, np.ndarray], ylabel: str) -> None:
    """One violin per method; a method with fewer than 2 distinct values is drawn as points."""
    names = list(data)
    for i, name in enumerate(names, start=1):
        x = np.asarray(data[name], dtype=float)
        x = x[np.isfinite(x)]
        if len(x) >= 2 and np.ptp(x) > 1e-9 * max(1.0, float(np.max(np.abs(x)))):
            parts = ax.violinplot([x], positions=[i], showmedians=True, showextrema=True, widths=0.8)
            for body in parts["bodies"]:
                body.set_alpha(0.6)
        elif len(x):
            ax.plot(np.full(len(x), i), x, "o", markersize=4)
        else:
            ax.text(i, 0.5, "no data", ha="center", va="center", transform=ax.get_xaxis_transform())
    ax.set_xticks(range(1, len(names) + 1))
    ax.set_xticklabels(names, rotation=30 if len(names) > 4 else 0, ha="right" if len(names) > 4 else "center")
    ax.set_xlim(0.4, len(names) + 0.6)
    ax.set_ylabel(ylabel)
    ax.set_ylim(bottom=0)
    ax.grid(True, axis="y", alpha=0.3)


def plot_error_distributions(path: str | os.PathLike, abs_errors_deg: Mapping[str, np.ndarray],
                             rel_errors_deg_per_s: Mapping[str, np.ndarray] | None = None, *,
                             title: str | None = None) -> None:
    """Violins of absolute errors [deg] (and relative errors [deg/s] in a second panel) per method."""
    panels = 2 if rel_errors_deg_per_s is not None else 1
    fig = _figure(4 + 2.2 * panels + 0.6 * len(abs_errors_deg), 4)
    axes = np.atleast_1d(fig.subplots(1, panels))
    _violins(axes[0], abs_errors_deg, "absolute error [deg]")
    axes[0].set_title("absolute")
    if rel_errors_deg_per_s is not None:
        _violins(axes[1], rel_errors_deg_per_s, "relative error [deg/s]")
        axes[1].set_title("relative")
    if title:
        fig.suptitle(title)
    _save(fig, path)


def plot_errors_over_time(path: str | os.PathLike, errors: Mapping[str, "RotationErrors"], *,
                          title: str | None = None) -> None:
    """Absolute error [deg] at each evaluated time and relative error [deg/s] at each pair start, per method."""
    fig = _figure(9, 6, layout=None)
    axes = _stacked(fig, 2, title=bool(title))
    for name, e in errors.items():
        axes[0].plot(e.abs_times, e.abs_errors_deg, linewidth=1.0, label=name)
        axes[1].plot(e.rel_times, e.rel_errors_deg_per_s, linewidth=1.0, marker=".", markersize=3, label=name)
    axes[0].set_ylabel("absolute error [deg]")
    delta = next(iter(errors.values())).rel_delta if errors else 1.0
    axes[1].set_ylabel(f"relative error [deg/s]\n(pairs of {delta:g} s, at their start)")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    if not any(len(e.rel_times) for e in errors.values()):
        axes[1].text(0.5, 0.5, f"no pair of {delta:g} s fits in the overlap", ha="center", va="center",
                     transform=axes[1].transAxes)
    if errors:
        axes[0].legend(loc="best", fontsize="small", ncol=min(4, len(errors)))
    if title:
        fig.suptitle(title)
    _save(fig, path)


def angular_velocity_from_trajectory(traj: Trajectory, spacing: float | None = None
                                     ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame angular velocity (rad/s) at sample midpoints: log(R_i^T R_{i+1}) / dt, on samples
    ``spacing`` s apart when given (a spline's knot spacing: finer differences only show its kinks)."""
    if spacing:
        traj = traj.resampled(np.arange(traj.t_start, traj.t_end + 1e-12, spacing))
    if len(traj) < 2:
        return np.zeros(0), np.zeros((0, 3))
    R = traj.R
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    dt = np.diff(traj.t)
    return 0.5 * (traj.t[1:] + traj.t[:-1]), so3.log(rel) / dt[:, None]


def plot_angular_velocity(path, estimates: dict, groundtruth=None, title: str | None = None) -> None:
    """Three panels (wx, wy, wz in deg/s vs time), estimates solid, ground truth dashed (Fig. 20a)."""
    fig = _figure(9, 6.5)
    axes = fig.subplots(3, 1, sharex=True)
    for name, (t, w) in estimates.items():
        for i, ax in enumerate(axes):
            ax.plot(t, np.degrees(w[:, i]), linewidth=1.0, label=name)
    if groundtruth is not None:
        t, w = groundtruth
        for i, ax in enumerate(axes):
            ax.plot(t, np.degrees(w[:, i]), **_GT_STYLE)
    for i, ax in enumerate(axes):
        ax.set_ylabel(f"omega_{'xyz'[i]} [deg/s]")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(fontsize="small", loc="best")
    if title:
        fig.suptitle(title)
    _save(fig, path)


_WINDOW_STATES = (  # (WindowReport flag, label, colour) in order of precedence
    ("rejected", "rejected (false maximum)", "tab:red"),
    ("refitted", "refitted (false maximum)", "tab:olive"),
    ("still", "still (no BA)", "tab:gray"),
    ("skipped", "skipped (real-time)", "tab:orange"),
    ("cut_short", "cut short (real-time)", "tab:purple"),
    ("optimized", "optimized", "tab:blue"),
)


def window_states(windows: Sequence) -> list:
    """What the run figure reads of each back-end window (span, largest correction, the _WINDOW_STATES flags), as
    plain values: WindowReports themselves unpickle only with the back-end's modules (and the kernel engine)."""
    from types import SimpleNamespace

    return [SimpleNamespace(t_start=float(w.t_start), t_end=float(w.t_end), max_correction=float(w.max_correction),
                            **{flag: bool(getattr(w, flag, False)) for flag, _, _ in _WINDOW_STATES})
            for w in windows]


def _aligned_run(trajectory: Trajectory, groundtruth: Trajectory | None):
    """(trajectory aligned to the ground truth at the start of their overlap, the ground truth over that overlap,
    the errors); (trajectory, None, None) without ground truth or with too short an overlap to evaluate."""
    if groundtruth is None or len(groundtruth) < 2 or len(trajectory) < 2:
        return trajectory, None, None
    from .errors import InputError
    from .metrics import evaluate_rotations

    lo, hi = max(groundtruth.t_start, trajectory.t_start), min(groundtruth.t_end, trajectory.t_end)
    try:
        errors = evaluate_rotations(groundtruth, trajectory, t0=lo) if hi > lo else None
    except InputError:  # too short an overlap to evaluate: the run is drawn without ground truth
        errors = None
    if errors is None:
        return trajectory, None, None
    return trajectory.aligned_to(groundtruth, errors.t0), groundtruth.slice_time(lo, hi), errors


def _orientation_panel(ax, trajectory: Trajectory, groundtruth: Trajectory | None) -> None:
    ang, _ = _angles_deg(trajectory, "euler")
    for i, name in enumerate(("roll (x)", "pitch (y)", "yaw (z)")):
        ax.plot(trajectory.t, ang[:, i], color=_AXIS_COLORS[i], linewidth=1.2, label=name)
    if groundtruth is not None:
        gang, _ = _angles_deg(groundtruth, "euler")
        for i in range(3):
            ax.plot(groundtruth.t, gang[:, i], color=_AXIS_COLORS[i], linestyle="--", linewidth=0.9,
                    label="ground truth" if i == 0 else None)
    ax.set_ylabel("orientation [deg]\n(Euler xyz)")
    ax.legend(loc="upper left", fontsize="small", ncol=4)


def _angular_velocity_panel(ax, trajectory: Trajectory, groundtruth: Trajectory | None, omega) -> None:
    # from poses: differences over at least 1/300 of the run (a tracker's 14 kHz poses differenced are mostly noise)
    spacing = (trajectory.t_end - trajectory.t_start) / 300 if len(trajectory) > 300 else None
    t_w, w = omega if omega is not None else angular_velocity_from_trajectory(trajectory, spacing)
    w = np.asarray(w, dtype=float).reshape(-1, 3)
    for i in range(3):
        ax.plot(t_w, w[:, i], color=_AXIS_COLORS[i], linewidth=1.0, marker="." if len(t_w) < 30 else None,
                label=f"omega_{'xyz'[i]}")
    if groundtruth is not None:
        gt_t, gt_w = angular_velocity_from_trajectory(groundtruth, spacing)
        for i in range(3):
            ax.plot(gt_t, gt_w[:, i], color=_AXIS_COLORS[i], linestyle="--", linewidth=0.8)
    ax.set_ylabel("angular velocity\n[rad/s, camera]")
    ax.legend(loc="upper left", fontsize="small", ncol=3)


def _backend_panel(ax, windows: Sequence) -> None:
    # windows overlap: a line over each window's span, a dot mid-way; one line collection and one marker line per
    # state (an artist per window cost ~0.1 s per figure of a 3 s run)
    groups: dict = {}
    for win in windows:
        state = next(((f, lab, c) for f, lab, c in _WINDOW_STATES if getattr(win, f, False)),
                     ("none", "no events", "lightgray"))
        groups.setdefault(state, []).append((win.t_start, win.t_end, np.degrees(win.max_correction)))
    for (_, label, color), spans in groups.items():
        t0, t1, y = np.asarray(spans, dtype=float).T
        ax.hlines(y, t0, t1, color=color, alpha=0.5, linewidth=1.5)
        ax.plot(0.5 * (t0 + t1), y, "o", color=color, markersize=4, linestyle="none", label=label)
    ax.set_ylim(bottom=0)
    ax.set_ylabel("BA correction\nper window [deg]")
    ax.legend(loc="upper left", fontsize="small", ncol=3)


def plot_run(path: str | os.PathLike, trajectory: Trajectory, *, omega: tuple | None = None,
             windows: Sequence | None = None, event_rate: tuple | None = None,
             groundtruth: Trajectory | None = None, title: str | None = None) -> list[str]:
    """The figure of one run, with or without ground truth: orientation (roll, pitch, yaw) and angular velocity
    over time, the back-end's correction per window coloured by its status, events per second, and (with ground
    truth) the absolute error over time. Returns the panels drawn.

    ``omega``: (t, (N, 3) rad/s) of the front-end (default: differences of the trajectory); ``windows``: the
    back-end's WindowReports; ``event_rate``: (t, events/s). With ground truth the estimate is aligned to it at the
    start of the overlap and drawn over it (dashed)."""
    trajectory, groundtruth, errors = _aligned_run(trajectory, groundtruth)
    panels = ["orientation", "angular velocity"]
    if windows:
        panels.append("back-end")
    if event_rate is not None and len(event_rate[0]):
        panels.append("event rate")
    if errors is not None:
        panels.append("error")
    fig = _figure(9, 1.9 * len(panels) + 0.8, layout=None)
    axes = dict(zip(panels, _stacked(fig, len(panels), title=bool(title))))

    _orientation_panel(axes["orientation"], trajectory, groundtruth)
    _angular_velocity_panel(axes["angular velocity"], trajectory, groundtruth, omega)
    if "back-end" in axes:
        _backend_panel(axes["back-end"], windows)
    if "event rate" in axes:
        ax = axes["event rate"]
        ax.plot(event_rate[0], np.asarray(event_rate[1]) / 1e6, color="k", linewidth=1.0,
                marker="." if len(event_rate[0]) < 30 else None)
        ax.set_ylabel("event rate\n[M events/s]")
        ax.set_ylim(bottom=0)
    if errors is not None:
        ax = axes["error"]
        ax.plot(errors.abs_times, errors.abs_errors_deg, color="tab:red", linewidth=1.0)
        ax.set_ylabel("absolute error\n[deg]")
        ax.set_ylim(bottom=0)
        ax.set_title(f"absolute rotation error (aligned at {errors.t0:.2f} s): RMSE {errors.abs_rmse_deg:.3f} deg",
                     fontsize="small")
    for ax in axes.values():
        ax.grid(True, alpha=0.3)
    list(axes.values())[-1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title)
    _save(fig, path, compress_level=1)  # the same pixels in ~2/3 of the encoding time (the file ~6 % larger)
    return panels


def map_display(image: np.ndarray, gamma: float = 0.75, percentile: float | None = None,
                peak: float | None = None) -> np.ndarray:
    """IWE -> [0, 1] for display: gamma-corrected (I / peak)^gamma clipped at 1, inverted so events are dark on
    white. ``peak``: given (e.g. a whole map's, for one block of it), else the maximum, or (contrast stretch) this
    percentile of the pixels that hold events."""
    h = np.clip(np.asarray(image, dtype=np.float64), 0, None)
    if peak is None:
        peak = h.max() if h.size else 0.0
    if percentile is not None and peak > 0:
        peak = float(np.percentile(h[h > 0], percentile))
    norm = np.minimum(h / peak, 1.0) ** gamma if peak > 0 else np.zeros_like(h)
    return 1.0 - norm


def observed_window(images: Sequence[np.ndarray], margin: float = 0.03) -> tuple[int, slice, slice]:
    """(column roll, rows, columns) of the smallest window holding every pixel with events in any of the (same
    size, equirectangular) images, plus ``margin`` of the size on each side. Columns wrap (u = 0 is u = w): the
    widest run of empty columns is rolled to the border first, so a region across the seam stays in one piece."""
    mask = np.zeros(np.asarray(images[0]).shape[:2], bool)
    for img in images:
        mask |= np.asarray(img) > 0
    if not mask.any():
        return 0, slice(None), slice(None)
    h, w = mask.shape
    empty = ~mask.any(axis=0)
    best_len, best_end, run = 0, 0, 0
    for i, e in enumerate(np.concatenate([empty, empty])):  # circular runs of empty columns
        run = run + 1 if e else 0
        if min(run, w) > best_len:
            best_len, best_end = min(run, w), (i + 1) % w
    used = w - best_len
    pad_c = min(int(margin * w), (w - used) // 2)
    roll = -(best_end - pad_c) % w if best_len else 0
    rows = np.flatnonzero(mask.any(axis=1))
    pad_r = int(margin * h)
    r0, r1 = max(0, int(rows[0]) - pad_r), min(h, int(rows[-1]) + 1 + pad_r)
    return int(roll), slice(r0, r1), slice(0, min(w, used + 2 * pad_c))


def plot_maps(path: str | os.PathLike, maps: Mapping[str, np.ndarray] | Sequence[tuple[str, np.ndarray]], *,
              gamma: float = 0.75, lambda0: float = 1.0, show_metrics: bool = True, ncols: int | None = None,
              title: str | None = None, crop: bool = True, percentile: float | None = 99.0,
              panel_width: float = 4.5) -> None:
    """Images of warped events side by side, each titled with its name and (optionally) EA% and GM (of the whole
    map). ``crop``: all shown on the same window around what any of them observed (:func:`observed_window`);
    ``percentile``: contrast stretch (:func:`map_display`; None: scaled to the maximum)."""
    items = list(maps.items()) if isinstance(maps, Mapping) else list(maps)
    if not items:
        raise ValueError("plot_maps needs at least one image")
    n = len(items)
    ncols = ncols or min(n, 3)
    nrows = -(-n // ncols)
    shapes = {np.asarray(img).shape[:2] for _, img in items}
    roll, rows, cols = observed_window([img for _, img in items]) if crop and len(shapes) == 1 else (0, None, None)

    def shown(img):
        if rows is None:
            return img
        return np.roll(img, roll, axis=1)[rows, cols]

    h0, w0 = shown(np.asarray(items[0][1])).shape[:2]
    panel_w = panel_width
    fig = _figure(panel_w * ncols, nrows * (panel_w * h0 / max(w0, 1) + 0.6))
    axes = np.atleast_1d(fig.subplots(nrows, ncols)).reshape(-1)
    for ax, (name, img) in zip(axes, items):
        img = np.asarray(img, dtype=np.float64)
        ax.imshow(map_display(shown(img), gamma, percentile), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        label = name
        if show_metrics:
            label += f"\nEA {event_area_percent(img, lambda0):.2f}%  GM {gradient_magnitude(img):.3f}"
        ax.set_title(label, fontsize="small")
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    if show_metrics:
        fig.supxlabel(METRICS_CAPTION, fontsize="small")
    _save(fig, path)


__all__ = ["plot_run", "window_states", "angular_velocity_from_trajectory", "plot_angular_velocity",
           "plot_trajectories", "plot_errors_over_time", "plot_error_distributions", "plot_maps", "map_display",
           "observed_window", "METRICS_CAPTION"]

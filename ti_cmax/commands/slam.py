"""``ti-cmax slam``: CMax-SLAM (front-end + sliding-window BA back-end) on a dataset."""
from __future__ import annotations

import argparse
from pathlib import Path

from . import add_map_arguments

HELP = "run CMax-SLAM: trajectory.txt, angular_velocity.txt, map.png, map.npy, run.png, report.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder (ECD layout) or events file")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--spline", choices=("linear", "cubic"), default=None,
                        help="trajectory model (default: spline_degree of the config, cubic)")
    workers = parser.add_mutually_exclusive_group()
    workers.add_argument("--parallel", dest="parallel", action="store_true", default=None,
                         help="run the back-end in a worker process at the same time as the front-end (the default "
                              "on 2 or more cores with a sensor of at most 0.5 M pixels)")
    workers.add_argument("--sequential", dest="parallel", action="store_false", default=None,
                         help="run the front-end and the back-end one after the other in this process (the default "
                              "on one core or a larger sensor)")
    parser.add_argument("--realtime", action="store_true",
                        help="replay the file in sensor time, degrading on purpose to bound the lag (report.json "
                             "\"realtime\"; --set realtime_target_lag=0.3, realtime_speed=1, ...)")
    add_map_arguments(parser)
    parser.add_argument("--viewer", action="store_true",
                        help="watch the run live in rerun: each packet's image of warped events, the growing map, "
                             "angular velocity and orientation (needs pip install -e \".[viewer]\")")
    parser.add_argument("--save-recording", default=None, metavar="FILE.rrd",
                        help="write the same live view to a rerun recording (open it later: rerun FILE.rrd)")


def spline_override(args) -> list[str]:
    return [] if args.spline is None else [f"spline_degree={1 if args.spline == 'linear' else 3}"]


def write_result(out: Path, result, cfg, camera=None, events_range=None, full_sphere: bool = False,
                 groundtruth=None, title: str | None = None, figures=None) -> dict:
    """Files common to slam, refine and the baselines: trajectory (TUM), map (PNG, gamma, cropped to the observed
    region unless ``full_sphere``: pipelines/panorama.map_image; and raw .npy), the run figure (run.png, with the
    error over time when ``groundtruth`` is given), report, config. The report gets the run's status and reasons
    (ti_cmax.status; ``events_range``: the input's time range, which the trajectory should cover) and is returned.
    ``figures``: a ti_cmax.figure_process.FigureProcess that draws run.png meanwhile (default: here)."""
    import numpy as np

    from .. import timeline
    from ..config import SlamConfig, save_config
    from ..io import write_angular_velocity, write_tum
    from ..outputs import peak_rss_mb, write_report
    from ..pipelines.panorama import PanoramaResult, map_image
    from ..pipelines.sensor_defaults import resolve_config
    from ..plots import plot_run
    from ..status import apply_status

    if isinstance(cfg, SlamConfig) and camera is not None:
        cfg = resolve_config(cfg, camera)  # derived values are written as numbers: a rerun with it is exact

    if figures is None:
        from ..figure_process import FigureProcess

        figures = FigureProcess(None, None)  # jobs run here, when submitted
    # the run figure first: a figure process draws it while this one writes the rest
    figures.submit(plot_run, out / "run.png", result.trajectory,
                   **run_figure_inputs(result.frontend, getattr(result, "windows", None), groundtruth,
                                       title or result.report.get("method")))
    intensity = getattr(result, "map_kind", "events") == "intensity"
    png, shown = map_image(result.map, cfg.output.gamma, full_sphere=full_sphere, intensity=intensity)
    write_png(out / "map.png", png)  # here: the figure process's run.png takes longer than all the rest
    write_tum(out / "trajectory.txt", result.trajectory)
    if result.frontend is not None and len(result.frontend):
        write_angular_velocity(out / "angular_velocity.txt", result.frontend.t, result.frontend.omega)
    np.save(out / "map.npy", result.map)
    report = dict(result.report)
    report["map"] = PanoramaResult(result.map, int(round(float(result.map.sum())))).figures(cfg.backend.lambda0)
    report["map"]["png"] = shown
    if camera is not None:
        report["camera"] = camera.to_dict()
    traj = result.trajectory
    apply_status(report, events_range=events_range,
                 trajectory_range=(traj.t_start, traj.t_end) if len(traj) else None)
    if getattr(result, "realtime_trace", None):  # a real-time replay (baselines and refine have none)
        write_realtime_trace(out / "realtime_windows.csv", result.realtime_trace)
    save_config(cfg, out / "config.yaml")
    if figures.forked:  # the report's engine version (importlib.metadata, ~0.02 s) while the figure is drawn
        from ..kernels.engine import engine_info

        engine_info()
    drawn = figures.wait()
    if drawn:
        report["figure_process"] = drawn
    # of the whole process so far; with a back-end worker (--parallel) plus the worker's own peak, and a figure
    # process's: the sum of the peaks, an upper bound of their total at any moment (the main process alone was half
    # of it on a VGA run)
    report["peak_rss_mb"] = (peak_rss_mb() + report.get("backend_process", {}).get("peak_rss_mb", 0.0)
                             + drawn.get("peak_rss_mb", 0.0))
    timeline.mark("outputs")  # the report is the last output: it holds the points of this process so far
    report["timeline_seconds"] = timeline.points()
    write_report(out, report)
    return report


class OutputPreload:
    """Imports what ``write_result`` needs (matplotlib, Pillow: about 0.4 CPU s) in a thread, started once a
    run's back-end worker is up: this process then mostly waits for the worker, so the imports leave the run's
    critical path. ``join()`` before writing the outputs: the main thread never imports beside it (it imports
    nothing between the start of the run and its outputs)."""

    MODULES = ("matplotlib.figure", "matplotlib.backends.backend_agg", "PIL.Image", "PIL.PngImagePlugin",
               "ti_cmax.plots")

    def __init__(self):
        self._thread = None

    def start(self) -> None:
        import threading

        self._thread = threading.Thread(target=self._run, name="ti-cmax-output-preload", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import importlib

        for name in self.MODULES:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the outputs import it again and report what fails
                return

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()


def write_run_figure(path: Path, trajectory, frontend=None, windows=None, groundtruth=None, title=None) -> None:
    """run.png (plots.plot_run): orientation, angular velocity (the front-end's when there is one), the back-end's
    windows, events per second of the front-end's packets, and the error over time with ground truth."""
    from ..plots import plot_run

    plot_run(path, trajectory, **run_figure_inputs(frontend, windows, groundtruth, title))


def run_figure_inputs(frontend=None, windows=None, groundtruth=None, title=None) -> dict:
    """plots.plot_run's keyword arguments of a run: the front-end's angular velocity and event rate, the windows'
    states (plain values: a figure process unpickles them without the back-end's modules)."""
    import numpy as np

    from ..plots import window_states

    omega = rate = None
    if frontend is not None and len(frontend.t):
        omega = (frontend.t, frontend.omega)
        if getattr(frontend, "num_events", None) is not None and getattr(frontend, "span", None) is not None:
            ok = (np.asarray(frontend.span) > 0) & (np.asarray(frontend.num_events) > 0)
            rate = (frontend.t[ok], np.asarray(frontend.num_events)[ok] / np.asarray(frontend.span)[ok])
    return {"omega": omega, "windows": window_states(windows) if windows else windows, "event_rate": rate,
            "groundtruth": groundtruth, "title": title}


def write_png(path: Path, image) -> None:
    """An 8-bit image (map.png) as PNG, by Pillow (imageio's own first call costs some 0.03 s more; same file)."""
    from PIL import Image

    Image.fromarray(image).save(path, format="png")


def write_realtime_trace(path: Path, rows: list) -> None:
    """The real-time controller's per-window trace (pipelines/realtime.TRACE_COLUMNS), one CSV row per window."""
    import csv

    from ..pipelines.realtime import TRACE_COLUMNS

    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(TRACE_COLUMNS)
        for row in rows:
            writer.writerow(["" if v is None else f"{v:.6g}" if isinstance(v, float) else v for v in row])


def print_derived(report: dict) -> None:
    """The parameters the sensor rules set (pipelines/sensor_defaults.py), for the command's summary."""
    from ..pipelines.sensor_defaults import describe

    if report.get("derived_parameters"):
        print(f"derived from the sensor: {describe(report['derived_parameters'])}")


def run(args) -> int:
    from ..figure_process import FigureProcess

    # forked first, while this process has one thread and little memory: it imports the figure modules while this
    # one imports the pipeline, and draws run.png at the end while this one writes the rest
    with FigureProcess.start() as figures:
        return _run(args, figures)


def _run(args, figures) -> int:
    from ..config import SlamConfig, check_workload, load_config
    from ..io import open_dataset_from_config
    from ..outputs import OutputDir
    from ..pipelines.slam import default_backend_process, run_slam
    from ..status import status_text
    from ..timeline import mark

    mark("imported")
    cfg = load_config(SlamConfig, args.config, list(args.overrides) + spline_override(args))
    dataset = open_dataset_from_config(args.dataset, cfg.dataset)
    camera = dataset.camera
    parallel = default_backend_process(camera) if args.parallel is None else args.parallel
    t0, t1 = dataset.time_range()
    if args.realtime and (args.viewer or args.save_recording):
        from ..errors import InputError

        raise InputError("--viewer and --save-recording are not available with --realtime")
    check_workload(cfg, t0, t1, realtime=args.realtime)
    with OutputDir(args.out) as out:  # locked from here: a second run into --out refuses
        if args.realtime:
            import sys

            from ..pipelines.realtime import READ_EVENTS, run_realtime

            log = None if args.quiet else (lambda msg: print(f"ti-cmax slam: {msg}", file=sys.stderr, flush=True))
            result = run_realtime(dataset.iter_events(min(cfg.dataset.chunk_size, READ_EVENTS)), camera, cfg,
                                  backend_process=parallel, progress_total=t1 - t0, log=log)
        else:
            viewer = None
            if args.viewer or args.save_recording:
                from ..viewer import RerunViewer

                viewer = RerunViewer(camera, cfg, spawn=args.viewer, save=args.save_recording)
            preload = OutputPreload()  # with no figure process: its imports here, while the worker works
            result = run_slam(dataset.iter_events(cfg.dataset.chunk_size), camera, cfg, progress_total=t1 - t0,
                              backend_process=parallel, observer=viewer,
                              on_start=preload.start if parallel and viewer is None and not figures.forked else None)
            preload.join()
            if viewer is not None:
                viewer.finish(result)
        report = write_result(out, result, cfg, camera, events_range=(t0, t1), full_sphere=args.full_sphere,
                              groundtruth=dataset.groundtruth, title=f"CMax-SLAM: {Path(args.dataset).name}",
                              figures=figures)
    figures.close()
    us = result.report["us_per_event"]
    print_derived(result.report)
    print(f"CMax-SLAM: {result.report['events_processed']} events, {len(result.trajectory)} poses, "
          f"front-end {us['frontend']:.3f} us/event, back-end {us['backend']:.3f} us/event "
          f"(compile {result.report['compile_seconds']:.1f} s apart"
          f"{'; back-end in a worker process' if parallel else ''}) -> {args.out}{status_text(report)}")
    if "realtime" in result.report:
        from ..pipelines.realtime import describe

        print(describe(result.report["realtime"]))
    return 0

"""Where the CPU time goes in CMax-SLAM: per stage (Python profiler, grouped by pipeline function) and per Taichi
kernel (Taichi's kernel profiler), on a simulated sequence. Compilation is done first and reported apart.

    python examples/profile_cpu.py [--duration 2] [--scene bay] [--sensor DVS128] [--spline linear|cubic] [--threads 2]
"""
import argparse
import cProfile
import os
import pstats
import time

os.environ["TI_CMAX_KERNEL_PROFILER"] = "1"  # before the runtime initializes Taichi

STAGES = [  # (label, source file, function)
    ("front-end: slicing (+ reading chunks)", "pipelines/frontend.py", "__call__"),
    ("front-end: per-packet CMax (CG)", "pipelines/frontend.py", "estimate"),
    ("back-end: window init (spline fit)", "pipelines/backend.py", "_initialize_until"),
    ("back-end: BA (CG)", "pipelines/backend.py", "_refine"),
    ("back-end: settle into global map", "pipelines/backend.py", "_settle"),
    ("bearings lookup", "ti_cmax/camera.py", "bearings"),
]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--scene", default="bay")
    ap.add_argument("--sensor", default="DAVIS240C", help="DAVIS240C, DVS128, DAVIS346 or VGA")
    ap.add_argument("--spline", choices=("linear", "cubic"), default="linear")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    import ti_cmax
    from ti_cmax.config import load_config
    from ti_cmax import progress
    from ti_cmax.kernels import runtime

    progress.set_quiet(True)
    if args.threads:
        runtime.set_num_threads(args.threads)
    seq = ti_cmax.simulate_sequence(ti_cmax.SimulatorConfig(scene=args.scene, sensor=args.sensor,
                                                             duration=args.duration, max_angular_velocity=3.0))
    cfg = load_config(ti_cmax.SlamConfig, None, [f"spline_degree={1 if args.spline == 'linear' else 3}"])
    tic = time.perf_counter()
    ti_cmax.run_slam(seq.events[:100_000], seq.camera, cfg)  # compile (or load from the offline cache)
    print(f"compile + warm-up: {time.perf_counter() - tic:.2f} s")
    runtime.ti.profiler.clear_kernel_profiler_info()
    prof = cProfile.Profile()
    tic = time.perf_counter()
    prof.enable()
    res = ti_cmax.run_slam(seq.events, seq.camera, cfg)
    prof.disable()
    wall = time.perf_counter() - tic
    n = len(seq.events)
    print(f"\n{n} events, {wall:.2f} s wall, {wall * 1e6 / n:.2f} us/event "
          f"(front-end {res.report['us_per_event']['frontend']:.2f}, back-end {res.report['us_per_event']['backend']:.2f})")
    stats = pstats.Stats(prof).stats
    print(f"\n{'stage':<40} {'seconds':>8} {'us/event':>9}")
    for label, source, func in STAGES:
        total = sum(v[3] for (file, _, name), v in stats.items() if name == func and file.endswith(source))
        print(f"{label:<40} {total:>8.2f} {total * 1e6 / n:>9.3f}")
    print("\nTaichi kernels (steady state):")
    runtime.ti.profiler.print_kernel_profiler_info("count")


if __name__ == "__main__":
    main()

"""ti_cmax: CMax-SLAM (Guo & Gallego, T-RO 2024) on Taichi CPU kernels.

Every name is imported lazily, at its first use (the pipelines load Taichi; the core types numpy), so
``import ti_cmax`` costs nothing: the ``ti-cmax`` command's start-up before its Ctrl-C handling (the console script
imports ti_cmax.cli, and with it this package) stays a few ms instead of numpy's 0.25 s:

    import ti_cmax
    ds = ti_cmax.open_dataset("seq")
    result = ti_cmax.run_slam(ds.iter_events(), ds.camera, ti_cmax.SlamConfig())
"""
import os as _os
import sys as _sys

# numpy's BLAS (OpenBLAS) on one thread unless the user chose a count: set before numpy loads it, so its pool is
# never started (kernels/runtime.limit_blas_threads: its idle threads spin beside the kernels; a 0.3 s `slam` spent
# 0.4-1.2 CPU s more with them). A numpy loaded before this line has its pool already: limit_blas_threads limits it
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
_NUMPY_BEFORE_BLAS_LIMIT = "numpy" in _sys.modules

__version__ = "0.2.0"

_LAZY = {  # name -> (module, attribute; None: the module itself)
    "so3": ("ti_cmax.so3", None),
    "Camera": ("ti_cmax.camera", "Camera"),
    "BackendConfig": ("ti_cmax.config", "BackendConfig"),
    "DatasetConfig": ("ti_cmax.config", "DatasetConfig"),
    "FrontendConfig": ("ti_cmax.config", "FrontendConfig"),
    "OutputConfig": ("ti_cmax.config", "OutputConfig"),
    "SlamConfig": ("ti_cmax.config", "SlamConfig"),
    "load_config": ("ti_cmax.config", "load_config"),
    "InputError": ("ti_cmax.errors", "InputError"),
    "Events": ("ti_cmax.events", "Events"),
    "Trajectory": ("ti_cmax.trajectory", "Trajectory"),
    "open_dataset": ("ti_cmax.io", "open_dataset"),
    "estimate_angular_velocity": ("ti_cmax.pipelines.frontend", "estimate_angular_velocity"),
    "run_slam": ("ti_cmax.pipelines.slam", "run_slam"),
    "refine": ("ti_cmax.pipelines.slam", "refine"),
    "dead_reckoning": ("ti_cmax.pipelines.baselines.imu", "dead_reckoning"),
    "render_panorama": ("ti_cmax.pipelines.panorama", "render_panorama"),
    "evaluate_rotations": ("ti_cmax.metrics", "evaluate_rotations"),
    "simulate_sequence": ("ti_cmax.simulate", "simulate_sequence"),
    "SimulatorConfig": ("ti_cmax.simulate", "SimulatorConfig"),
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        module = importlib.import_module(module)
        return module if attr is None else getattr(module, attr)
    raise AttributeError(f"module 'ti_cmax' has no attribute {name!r}")


__all__ = ["__version__", *_LAZY]

"""ti_cmax: CMax-SLAM (Guo & Gallego, T-RO 2024) on Taichi CPU kernels.

Core types are imported eagerly; the pipelines are exposed lazily (importing them compiles nothing, but
loads Taichi), so ``import ti_cmax`` stays light:

    import ti_cmax
    ds = ti_cmax.open_dataset("seq")
    result = ti_cmax.run_slam(ds.iter_events(), ds.camera, ti_cmax.SlamConfig())
"""
import os as _os

# numpy's BLAS (OpenBLAS) on one thread unless the user chose a count: set before numpy loads it, so its pool is
# never started (kernels/runtime.limit_blas_threads: its idle threads spin beside the kernels; a 0.3 s `slam` spent
# 0.4-1.2 CPU s more with them)
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import so3
from .camera import Camera
from .config import BackendConfig, DatasetConfig, FrontendConfig, OutputConfig, SlamConfig, load_config
from .errors import InputError
from .events import Events
from .trajectory import Trajectory

__version__ = "0.1.0"

_LAZY = {
    "open_dataset": ("ti_cmax.io", "open_dataset"),
    "estimate_angular_velocity": ("ti_cmax.pipelines.frontend", "estimate_angular_velocity"),
    "run_slam": ("ti_cmax.pipelines.slam", "run_slam"),
    "refine": ("ti_cmax.pipelines.slam", "refine"),
    "dead_reckoning": ("ti_cmax.pipelines.imu", "dead_reckoning"),
    "render_panorama": ("ti_cmax.pipelines.panorama", "render_panorama"),
    "evaluate_rotations": ("ti_cmax.metrics", "evaluate_rotations"),
    "simulate_sequence": ("ti_cmax.simulate", "simulate_sequence"),
    "SimulatorConfig": ("ti_cmax.simulate", "SimulatorConfig"),
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'ti_cmax' has no attribute {name!r}")


__all__ = ["Camera", "Events", "Trajectory", "InputError", "DatasetConfig", "FrontendConfig", "BackendConfig",
           "OutputConfig", "SlamConfig", "load_config", "so3", "__version__", *_LAZY]

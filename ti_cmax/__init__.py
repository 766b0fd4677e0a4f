"""ti_cmax: CMax-SLAM (Guo & Gallego, T-RO 2024) on Taichi CPU kernels.

Public API: the `Events` type, `Camera`, configs, readers (`ti_cmax.io`), and the pipelines
(`estimate_angular_velocity`, `run_slam`, `refine`) once imported from `ti_cmax.pipelines`.
"""
from .camera import Camera
from .config import BackendConfig, FrontendConfig, OutputConfig, SlamConfig, load_config
from .errors import InputError
from .events import Events
from . import so3

__version__ = "0.1.0"

__all__ = ["Camera", "Events", "InputError", "FrontendConfig", "BackendConfig", "OutputConfig", "SlamConfig",
           "load_config", "__version__"]

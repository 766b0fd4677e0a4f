"""Rotational event simulator: a panorama seen by a purely rotating event camera (ESIM-like).

Python API: ``simulate_sequence(SimulatorConfig(...))`` -> :class:`SimulatedSequence` in memory;
``write_sequence(seq, out_dir)``; ``simulate_to_folder(config, out_dir)`` streams long sequences to disk.
Command line: ``ti-cmax simulate OUT_DIR``.
"""
from .config import SCENES, TRAJECTORIES, SimulatorConfig
from .generate import generate_events, render_times, sensor_camera
from .scenes import make_panorama
from .sequence import SimulatedSequence, simulate_sequence, simulate_to_folder, write_sequence
from .trajectories import RotationalMotion, make_motion

__all__ = [
    "SimulatorConfig", "SCENES", "TRAJECTORIES", "SimulatedSequence", "simulate_sequence", "simulate_to_folder",
    "write_sequence", "sensor_camera", "make_panorama", "make_motion", "RotationalMotion", "generate_events",
    "render_times",
]

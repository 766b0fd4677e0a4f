"""Event data I/O: readers and writers for events, calibration, trajectories, IMU and angular velocity.

Entry point for reading: ``open_dataset(path)`` (a folder in ECD layout or a single events file);
see :mod:`ti_cmax.io.dataset`. Writers stream, so arbitrarily long recordings can be written in batches.
"""
from .calib import read_calib, read_camera_info_yaml, write_calib_txt, write_camera_info_yaml
from .dataset import Dataset, DatasetConfig, open_dataset, open_dataset_from_config
from .events_txt import EventsTxtWriter, write_events_txt
from .h5 import EventsH5Writer, write_events_h5
from .text import (
    ImuData,
    read_angular_velocity,
    read_imu_txt,
    read_tum,
    write_angular_velocity,
    write_imu_txt,
    write_tum,
)

__all__ = [
    "Dataset", "DatasetConfig", "open_dataset", "open_dataset_from_config",
    "EventsTxtWriter", "write_events_txt", "EventsH5Writer", "write_events_h5",
    "read_calib", "read_camera_info_yaml", "write_calib_txt", "write_camera_info_yaml",
    "ImuData", "read_imu_txt", "write_imu_txt", "read_tum", "write_tum",
    "read_angular_velocity", "write_angular_velocity",
]

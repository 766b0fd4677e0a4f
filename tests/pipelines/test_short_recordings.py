"""A trajectory covers every packet it estimated: on a recording of one or two packets (a few ms) the poses carry
the measured angular velocity instead of standing still."""
import numpy as np
from ti_cmax import so3


def _mean_rate(traj) -> np.ndarray:
    """Angular velocity (camera frame, rad/s) of the whole trajectory: log(R_0^T R_end) / duration."""
    return so3.log(traj.R[0].T @ traj.R[-1]) / (traj.t[-1] - traj.t[0])


def test_real_slice_of_a_few_ms(real_data, ti_runtime):
    """ECD boxes slice, 5.5 ms and 30 000 events: one front-end packet of omega ~ (3.8, 4.1, -1.4) rad/s."""
    from ti_cmax.config import SlamConfig
    from ti_cmax.io import open_dataset
    from ti_cmax.pipelines.slam import run_slam

    ds = open_dataset(real_data / "ecd_slices" / "boxes_rotation")
    res = run_slam(ds.iter_events(), ds.camera, SlamConfig(), backend_process=False)
    omega = res.frontend.omega[-1]
    assert np.linalg.norm(omega) > 3.0
    rate = _mean_rate(res.trajectory)
    assert np.linalg.norm(rate - omega) < 0.15 * np.linalg.norm(omega), (rate, omega)


def test_short_simulated_recording(short_sequence):
    """4 ms of a simulated rotation (one packet): the trajectory turns at the true rate."""
    from ti_cmax.config import SlamConfig
    from ti_cmax.pipelines.slam import run_slam

    seq = short_sequence
    events = seq.events.slice_time(0.6, 0.604)
    res = run_slam(events, seq.camera, SlamConfig(), backend_process=False)
    truth = _mean_rate(seq.groundtruth.slice_time(events.t[0], events.t[-1]))
    rate = _mean_rate(res.trajectory)
    assert len(events) > 2000 and len(res.frontend) == 1 and np.linalg.norm(truth) > 1.0
    assert np.linalg.norm(rate - truth) < 0.2 * np.linalg.norm(truth), (rate, truth)


def test_short_simulated_recording_front_end_alone(short_sequence):
    """The front-end's own trajectory (``ti-cmax frontend``) of a one-packet recording turns at its omega too."""
    from ti_cmax.config import FrontendConfig
    from ti_cmax.pipelines.frontend import estimate_angular_velocity

    seq = short_sequence
    events = seq.events.slice_time(0.6, 0.604)
    res = estimate_angular_velocity(events, seq.camera, FrontendConfig())
    traj = res.trajectory()
    assert len(res) == 1 and len(traj) == 3 and traj.t[0] <= events.t[0] and traj.t[-1] >= events.t[-1]
    assert np.allclose(_mean_rate(traj), res.omega[0])

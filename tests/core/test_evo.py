"""evo reads our TUM outputs: its APE of the rotation angle in degrees, without a rigid alignment, agrees with our
absolute error; Umeyama alignment (``-a``) cannot work on rotation-only files (every translation is 0)."""
import numpy as np
import pytest

from ti_cmax import so3
from ti_cmax.io import write_tum
from ti_cmax.metrics import evaluate_rotations
from ti_cmax.trajectory import Trajectory

evo = pytest.importorskip("evo")


def test_evo_ape_on_our_outputs(tmp_path):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    t = np.round(np.arange(0.0, 2.0, 0.001), 9)
    gt = Trajectory(t, so3.exp(np.stack([0.4 * np.sin(2 * t), 0.3 * t, -1.2 * t], axis=1)))
    rng = np.random.default_rng(0)
    sel = np.arange(0, len(t), 5)  # 200 Hz, on the ground truth's timestamps
    noise = so3.exp(np.cumsum(rng.normal(0.0, 2e-4, (len(sel), 3)), axis=0))
    est = Trajectory(t[sel], gt.R[sel] @ noise)
    write_tum(tmp_path / "groundtruth.txt", gt)
    write_tum(tmp_path / "trajectory.txt", est)

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "groundtruth.txt"))
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "trajectory.txt"))
    ref, traj = sync.associate_trajectories(ref, traj)
    ape = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape.process_data((ref, traj))
    ours = evaluate_rotations(gt, est, align=False)
    assert len(ape.error) == len(est) == ours.num_abs
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(ours.abs_rmse_deg, rel=1e-4)
    assert ape.get_statistic(metrics.StatisticsType.rmse) > 0.01  # the noise is seen, in degrees

    with pytest.raises(Exception, match="(?i)degenerate"):  # why the recipe leaves out -a
        traj.align(ref)

"""SO(3) B-splines (ti_cmax.spline): evaluation, smoothness, Jacobians, lift-solve-retract fit."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from ti_cmax import so3
from ti_cmax.spline import SO3Spline, blending_basis, cumulative_basis


def random_spline(degree, m=8, t0=0.3, dt=0.05, step=0.3, seed=0):
    rng = np.random.default_rng(seed)
    rotvecs = np.cumsum(rng.normal(size=(m, 3)) * step, axis=0)
    return SO3Spline(degree, t0, dt, Rotation.from_rotvec(rotvecs).as_matrix())


def test_linear_spline_is_slerp_between_knots():
    spline = random_spline(1)
    start, end = spline.valid_time_range()
    assert (start, end) == pytest.approx((spline.t0, spline.t0 + 7 * spline.dt))
    times = np.linspace(start, end, 97)
    slerp = Slerp(spline.knot_times(), Rotation.from_matrix(spline.control_R))
    np.testing.assert_allclose(spline.evaluate(times), slerp(times).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(spline.evaluate(spline.knot_times()), spline.control_R, atol=1e-12)


def test_cubic_basis_and_valid_range():
    u = np.linspace(0, 1, 11)
    b, db = cumulative_basis(3, u)
    np.testing.assert_allclose(b[:, 0], 1.0)
    np.testing.assert_allclose(b[0], [1, 5 / 6, 1 / 6, 0])  # Eq. 12 at u = 0
    np.testing.assert_allclose(blending_basis(3, u).sum(axis=1), 1.0)
    spline = random_spline(3, m=6)
    start, end = spline.valid_time_range()
    assert (start, end) == pytest.approx((spline.t0 + spline.dt, spline.t0 + 4 * spline.dt))
    s, uu = spline.support([start, end, start + 1.5 * spline.dt])
    np.testing.assert_array_equal(s, [0, 2, 1])
    np.testing.assert_allclose(uu, [0, 1, 0.5])
    with pytest.raises(ValueError):
        spline.evaluate(start - 0.01)
    with pytest.raises(ValueError):
        spline.evaluate(end + 0.01)


def _fd_angular_velocity(spline, t, h):
    ra = spline.evaluate(t - h)
    rb = spline.evaluate(t + h)
    return so3.log(np.swapaxes(ra, -1, -2) @ rb) / (2 * h)


def test_angular_velocity_matches_finite_differences():
    for degree in (1, 3):
        spline = random_spline(degree, seed=1)
        start, end = spline.valid_time_range()
        t = start + spline.dt * (np.arange(1, 9) * 0.37 % 1 + np.arange(8) % 3)  # between knots
        t = t[t < end]
        np.testing.assert_allclose(spline.angular_velocity(t), _fd_angular_velocity(spline, t, 1e-6), atol=1e-6)


def test_cubic_is_c2_across_knots_and_linear_is_not_c1():
    cubic = random_spline(3, seed=2)
    knots = cubic.knot_times()[2:-2]  # interior knots of the valid range
    eps = 1e-9 * cubic.dt
    h = 1e-3 * cubic.dt

    def accel(t):  # derivative of the analytic angular velocity, one-sided stencils that do not straddle a knot
        return (cubic.angular_velocity(t + h) - cubic.angular_velocity(t - h)) / (2 * h)

    w_minus, w_plus = cubic.angular_velocity(knots - eps), cubic.angular_velocity(knots + eps)
    np.testing.assert_allclose(w_minus, w_plus, atol=1e-6)
    a_minus, a_plus = accel(knots - 2 * h), accel(knots + 2 * h)
    scale = np.abs(a_plus).max()
    assert np.abs(a_minus - a_plus).max() < 1e-2 * scale
    # the same test detects a kink: the linear spline's angular velocity jumps at knots
    linear = random_spline(1, seed=2)
    jump = linear.angular_velocity(knots - eps) - linear.angular_velocity(knots + eps)
    assert np.abs(jump).max() > 1.0


@pytest.mark.parametrize("degree", [1, 3])
def test_jacobians_match_central_differences(degree):
    spline = random_spline(degree, m=7, step=0.4, seed=3)
    start, end = spline.valid_time_range()
    times = np.concatenate([np.linspace(start, end, 9), start + spline.dt * np.array([0.25, 1.6])])
    first, r_t, jac = spline.jacobians(times)
    np.testing.assert_allclose(r_t, spline.evaluate(times), atol=1e-14)
    np.testing.assert_allclose(jac.sum(axis=1), np.broadcast_to(np.eye(3), (len(times), 3, 3)), atol=1e-12)
    h = 1e-6
    for j in range(degree + 1):
        for d in range(3):
            numeric = np.empty((len(times), 3))
            for n, t in enumerate(times):
                delta = np.zeros((1, 3))
                delta[0, d] = h
                plus = spline.copy().retract(delta, first[n] + j).evaluate(t)[0]
                minus = spline.copy().retract(-delta, first[n] + j).evaluate(t)[0]
                numeric[n] = so3.log(plus @ minus.T) / (2 * h)  # left (world-frame) convention
            np.testing.assert_allclose(jac[:, j, :, d], numeric, atol=1e-8)
    # control poses outside the support have no influence
    other = (first[0] + degree + 1) % spline.num_control
    moved = spline.copy().retract(np.full((1, 3), 0.1), other)
    np.testing.assert_allclose(moved.evaluate(times[0]), spline.evaluate(times[0]), atol=1e-14)


@pytest.mark.parametrize("degree", [1, 3])
def test_fit_reproduces_spline_from_its_samples(degree):
    truth = random_spline(degree, m=9, step=0.08, seed=4)
    start, end = truth.valid_time_range()
    times = np.linspace(start, end, 150)
    samples = truth.evaluate(times)
    plain = SO3Spline.fit(degree, truth.dt, times, samples, refine_iters=0)  # lift-solve-retract only
    assert plain.t0 == pytest.approx(truth.t0) and plain.num_control == truth.num_control
    assert so3.geodesic_angle(plain.control_R, truth.control_R).max() < 2e-3
    refined = SO3Spline.fit(degree, truth.dt, times, samples, refine_iters=2)
    # exact up to the smoothness term's pull on these deliberately rough random poses (2e-7 rad measured)
    assert so3.geodesic_angle(refined.control_R, truth.control_R).max() < 2e-6


@pytest.mark.parametrize("degree", [1, 3])
def test_fit_new_segment_keeps_earlier_poses_fixed(degree):
    truth = random_spline(degree, m=10, step=0.08, seed=5)
    keep = 4
    partial = SO3Spline(degree, truth.t0, truth.dt, truth.control_R[:keep])
    _, end = truth.valid_time_range()
    seg_start = truth.knot_times()[keep - 1 - (degree - 1) // 2]
    times = np.linspace(seg_start, end, 80)
    partial.fit_new_segment(times, truth.evaluate(times), first_free=keep, refine_iters=2)
    assert partial.num_control == truth.num_control
    np.testing.assert_array_equal(partial.control_R[:keep], truth.control_R[:keep])
    assert so3.geodesic_angle(partial.control_R, truth.control_R).max() < 2e-6  # smoothness pull: 6e-7 rad


def test_append_retract_and_to_trajectory():
    spline = random_spline(3, m=5)
    spline.append(spline.control_R[-1])
    assert spline.num_control == 6
    traj = spline.to_trajectory(200.0)
    start, end = spline.valid_time_range()
    assert traj.t[0] == pytest.approx(start) and traj.t[-1] == pytest.approx(end)
    assert np.allclose(np.diff(traj.t)[:-1], 1 / 200.0)
    np.testing.assert_allclose(traj.R, spline.evaluate(traj.t), atol=1e-12)
    before = spline.control_R[2].copy()
    spline.retract(np.array([[0.0, 0.0, 0.1]]), first=2)
    np.testing.assert_allclose(spline.control_R[2], so3.exp(np.array([0.0, 0.0, 0.1])) @ before)


def test_fit_extrapolates_poses_that_samples_barely_reach():
    """A cubic control pose whose only sample lies 0.2 knot intervals into its support (basis weight 0.0013)
    follows the smooth extrapolation instead of amplifying 0.05 deg of sample noise into tens of degrees."""
    dt, w = 0.05, np.array([0.3, -1.0, 0.5])
    times = np.arange(0.0, 0.31 + 1e-12, 0.01)  # ends 0.2 dt past the knot at 0.30
    rng = np.random.default_rng(0)
    noise = so3.exp(rng.normal(scale=np.radians(0.05), size=(len(times), 3)))
    sp = SO3Spline(3, -dt, dt, np.broadcast_to(np.eye(3), (4, 3, 3)).copy())
    sp.fit_new_segment(times, noise @ so3.exp(np.outer(times, w)), first_free=0, refine_iters=1)
    clean = SO3Spline(3, -dt, dt, np.broadcast_to(np.eye(3), (4, 3, 3)).copy())
    clean.fit_new_segment(times, so3.exp(np.outer(times, w)), first_free=0, refine_iters=1)
    err = np.degrees(so3.geodesic_angle(sp.control_R, clean.control_R))
    assert err[-1] < 1.5, err  # measured: 0.93 deg; with smoothness 1e-6: 43 deg
    assert max(err[0], err[-2]) < 1.5 and err[1:-2].max() < 0.2, err  # poses at the ends see fewer samples


@pytest.mark.parametrize("degree", [1, 3])
def test_omega_once_per_control_index_gives_the_per_time_values(degree):
    """Omega_{s+j} is computed once per control index the times share, not once per time: the values (hence the
    poses) must be the very bits of the per-time computation."""
    spline = random_spline(degree, m=9)
    start, end = spline.valid_time_range()
    s, u = spline.support(np.sort(np.random.default_rng(1).uniform(start, end, 300)))
    ctrl = spline.control_R
    per_time = np.stack([so3.log(np.swapaxes(ctrl[s + j - 1], -1, -2) @ ctrl[s + j]) for j in range(1, degree + 1)], 1)
    assert np.array_equal(spline._chain(s, u)[2], per_time)


def test_trajectory_query_reads_only_its_intervals_with_the_same_values():
    """Trajectory.at slerps over the samples of the queried intervals only (O(1) for one time on a long
    trajectory); the values are those of a slerp over every sample, bit for bit, at sample times too, and
    scipy's Slerp's to rounding."""
    from ti_cmax import so3
    from ti_cmax.trajectory import Trajectory

    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.001, 0.1, 40))
    traj = Trajectory(t, Rotation.random(40, random_state=3).as_matrix())
    full = Slerp(traj.t, Rotation.from_matrix(traj.R))
    queries = np.concatenate([rng.uniform(t[0] - 0.1, t[-1] + 0.1, 20), t[[0, 1, 17, 38, 39]]])
    for q in [queries, queries[:1], t[[0]], t[[-1]], t[[17]]]:
        assert np.array_equal(traj.at(q), so3.slerp(traj.t, traj.R, np.clip(q, t[0], t[-1])))
        np.testing.assert_allclose(traj.at(q), full(np.clip(q, t[0], t[-1])).as_matrix(), atol=1e-14)


def test_so3_quaternions_log_and_slerp_match_scipy():
    """so3's own matrix <-> quaternion, log and slerp (scipy.spatial is not imported by a run: start-up) agree with
    scipy's Rotation and Slerp, at tiny angles and near pi too."""
    rng = np.random.default_rng(5)
    phi = rng.normal(size=(500, 3))
    phi *= (rng.uniform(0, np.pi, 500) / np.linalg.norm(phi, axis=1))[:, None]
    phi[:5] *= 1e-9
    phi[5:10] *= (np.pi - 1e-7) / np.linalg.norm(phi[5:10], axis=1)[:, None]
    r = Rotation.from_rotvec(phi).as_matrix()
    np.testing.assert_allclose(so3.log(r), phi, atol=1e-12)
    np.testing.assert_allclose(so3.to_quat_xyzw(r), Rotation.from_matrix(r).as_quat(), atol=1e-14)
    q = rng.normal(size=(50, 4))
    np.testing.assert_allclose(so3.from_quat_xyzw(q), Rotation.from_quat(q).as_matrix(), atol=1e-14)
    t = np.sort(rng.uniform(0, 1, 30))
    query = rng.uniform(t[0], t[-1], 100)
    np.testing.assert_allclose(so3.slerp(t, r[:30], query), Slerp(t, Rotation.from_matrix(r[:30]))(query).as_matrix(),
                               atol=1e-14)


def test_small_fits_solve_dense_and_match_the_sparse_path():
    """The sliding window's fits (<= DENSE_FIT_COLUMNS parameters) solve dense, whole-trajectory fits sparse: the
    same control poses to rounding."""
    import ti_cmax.spline as S

    rng = np.random.default_rng(4)
    t = np.linspace(0.0, 0.9, 120)
    rots = so3_exp_path(t, rng)
    dense = S.SO3Spline.fit(3, 0.05, t, rots)
    saved = S.DENSE_FIT_COLUMNS
    try:
        S.DENSE_FIT_COLUMNS = 0
        sparse = S.SO3Spline.fit(3, 0.05, t, rots)
    finally:
        S.DENSE_FIT_COLUMNS = saved
    assert 3 * dense.num_control <= saved
    np.testing.assert_allclose(dense.control_R, sparse.control_R, atol=1e-10)


def so3_exp_path(t, rng):
    w = rng.normal(size=3)
    return so3.exp(np.outer(t, w) + 0.2 * np.sin(np.outer(t, [3.0, 5.0, 7.0])))


@pytest.mark.parametrize("degree", [1, 3])
def test_fit_follows_samples_over_more_than_half_a_turn(degree):
    """A fit over samples that turn 1.5 times (about a tilted axis, with a wobble) follows them: the lift about one
    offset rotation would wrap at half a turn from it."""
    t = np.linspace(0.0, 3.0, 301)
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    yaw = so3.exp(np.outer(3 * np.pi * t / 3.0, axis))
    wobble = so3.exp(0.1 * np.stack([np.sin(2 * t), np.cos(3 * t), np.sin(t)], axis=1))
    rots = yaw @ wobble
    spline = SO3Spline.fit(degree, 0.05, t, rots)
    err = so3.geodesic_angle(spline.evaluate(t[1:-1]), rots[1:-1])
    assert err.max() < (1e-3 if degree == 3 else 5e-3)

"""Local optimisers: Fletcher-Reeves nonlinear CG with strong-Wolfe line search, warm-started BFGS."""
import numpy as np
import pytest
from scipy.optimize import rosen, rosen_der

from ti_cmax.pipelines.optim import bfgs, fletcher_reeves


def test_quadratic_is_solved():
    a = np.diag([1.0, 10.0, 100.0]) + 0.5
    b = np.array([1.0, -2.0, 3.0])
    res = fletcher_reeves(lambda x: (0.5 * x @ a @ x - b @ x, a @ x - b), np.zeros(3), grad_tol=1e-9,
                          rel_cost_tol=0.0)
    assert res.converged and res.message == "gradient tolerance reached"
    np.testing.assert_allclose(res.x, np.linalg.solve(a, b), atol=1e-8)
    assert res.evaluations < 60


def test_rosenbrock_converges():
    res = fletcher_reeves(lambda x: (rosen(x), rosen_der(x)), [-1.2, 1.0], max_iter=500, grad_tol=1e-6,
                          rel_cost_tol=0.0, line_search_tol=0.1)
    assert res.converged
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-4)


def test_maximize_returns_the_objective_as_given():
    c = np.array([2.0, -1.0, 0.5])
    res = fletcher_reeves(lambda x: (-np.sum((x - c) ** 2) + 3.0, -2 * (x - c)), np.zeros(3), maximize=True,
                          grad_tol=1e-8, rel_cost_tol=0.0)
    np.testing.assert_allclose(res.x, c, atol=1e-7)
    assert res.fun == pytest.approx(3.0)


def test_relative_cost_tolerance_stops_early_and_never_returns_a_worse_point():
    calls = []

    def f(x):
        calls.append(x.copy())
        return 5.0 + float(np.sum(np.abs(x) ** 1.5)), 1.5 * np.sign(x) * np.abs(x) ** 0.5

    x0 = np.array([1.0, -2.0])
    res = fletcher_reeves(f, x0, rel_cost_tol=1e-2, grad_tol=1e-12)
    assert res.converged and "relative" in res.message
    assert res.fun <= f(x0)[0]
    assert res.evaluations == len(calls) - 1


def test_secant_step_guess_converges():
    """The secant first trial step (used by the front-end) reaches the same solutions."""
    a = np.array([[3.0, 0.5, 0.2], [0.5, 2.0, 0.1], [0.2, 0.1, 1.0]])
    b = np.array([1.0, -2.0, 0.5])
    res = fletcher_reeves(lambda x: (0.5 * x @ a @ x - b @ x, a @ x - b), np.zeros(3), grad_tol=1e-8,
                          rel_cost_tol=0.0, line_search_tol=0.5, max_line_evals=4, step_guess="secant")
    assert res.converged
    np.testing.assert_allclose(res.x, np.linalg.solve(a, b), atol=1e-6)
    res = fletcher_reeves(lambda x: (rosen(x), rosen_der(x)), [-1.2, 1.0], max_iter=500, grad_tol=1e-6,
                          rel_cost_tol=0.0, line_search_tol=0.1, step_guess="secant")
    assert res.converged
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-4)
    with pytest.raises(ValueError, match="step_guess"):
        fletcher_reeves(lambda x: (rosen(x), rosen_der(x)), np.zeros(2), step_guess="newton")


def _quadratic(a, b):
    return lambda x: (0.5 * x @ a @ x - b @ x, a @ x - b)


def test_bfgs_solves_rosenbrock_and_a_quadratic():
    res, h = bfgs(lambda x: (rosen(x), rosen_der(x)), [-1.2, 1.0], max_iter=500, grad_tol=1e-6,
                  rel_cost_tol=0.0, max_step=1.0)
    assert res.converged
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-4)
    a = np.diag([1.0, 10.0, 100.0]) + 0.5
    b = np.array([1.0, -2.0, 3.0])
    res, h = bfgs(_quadratic(a, b), np.zeros(3), grad_tol=1e-9, rel_cost_tol=0.0, max_step=10.0)
    np.testing.assert_allclose(res.x, np.linalg.solve(a, b), atol=1e-8)
    assert np.abs(h @ a - np.eye(3)).max() < 0.1  # the returned inverse Hessian is learnt


def test_bfgs_warm_inverse_hessian_solves_the_next_problem_in_few_evaluations():
    """The front-end's use: a sequence of similar problems; passing the last inverse Hessian back makes the first
    step a Newton step (a quadratic is then solved by 2 evaluations: start and the step)."""
    a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    cold, h = bfgs(_quadratic(a, np.array([1.0, 0.0, -1.0])), np.zeros(3), grad_tol=1e-10, rel_cost_tol=0.0)
    warm, _ = bfgs(_quadratic(a, np.array([1.1, 0.1, -0.9])), cold.x, inv_hessian=h, grad_tol=1e-6,
                   rel_cost_tol=0.0)
    np.testing.assert_allclose(warm.x, np.linalg.solve(a, [1.1, 0.1, -0.9]), atol=1e-5)
    assert warm.evaluations <= 3 < cold.evaluations


def test_bfgs_maximizes_caps_steps_and_never_returns_a_worse_point():
    c = np.array([20.0, -10.0, 5.0])
    seen = []

    def f(x):
        seen.append(x.copy())
        return -np.sum((x - c) ** 2) + 3.0, -2 * (x - c)

    res, _ = bfgs(f, np.zeros(3), maximize=True, grad_tol=1e-8, rel_cost_tol=0.0, max_step=2.0, max_iter=200)
    np.testing.assert_allclose(res.x, c, atol=1e-6)
    assert res.fun == pytest.approx(3.0)
    steps = np.linalg.norm(np.diff(np.array(seen), axis=0), axis=1)
    assert steps.max() <= 2.0 + 1e-9
    # a cost that only gets worse away from the start: the start is returned
    res, h = bfgs(lambda x: (float(np.sum(np.abs(x))) + 1.0, np.sign(x) + 0.5), np.zeros(2), max_iter=5)
    assert res.fun <= 1.0 and h is None


def test_bfgs_step_tolerance_saves_the_confirming_evaluation():
    """With a learnt inverse Hessian, step_tol stops when the next quasi-Newton step would be shorter than it:
    fewer evaluations, and the solution is within about that distance of the optimum."""
    c = np.array([0.3, -0.2, 0.1])

    def f(x):  # smooth, not quadratic: the Hessian changes along the way
        d = x - c
        return float(np.sum(np.cosh(d))), np.sinh(d)

    h = np.eye(3)  # the inverse Hessian at the optimum (cosh'' = 1 there)
    loose, _ = bfgs(f, np.zeros(3), inv_hessian=h, grad_tol=1e-12, rel_cost_tol=0.0, step_tol=1e-2)
    tight, _ = bfgs(f, np.zeros(3), inv_hessian=h, grad_tol=1e-12, rel_cost_tol=0.0)
    assert loose.message == "step tolerance reached"
    assert loose.evaluations < tight.evaluations
    assert np.linalg.norm(loose.x - c) < 2e-2
    np.testing.assert_allclose(tight.x, c, atol=1e-8)


def test_bfgs_takes_a_last_step_predicted_below_the_cost_tolerance_without_evaluating_it():
    """last_step_unevaluated: the step that would only confirm convergence (its predicted cost change, from the
    learnt curvature, below half rel_cost_tol) is taken blind: the same point as evaluating it, one evaluation less."""
    c = np.array([0.3, -0.2, 0.1])

    def f(x):  # smooth, not quadratic
        d = x - c
        return float(np.sum(np.cosh(d))), np.sinh(d)

    for tol in (1e-4, 1e-6):
        for h in (np.eye(3), None):  # a carried inverse Hessian, and a cold start (learns it first)
            seen, blind_seen = [], []
            checked, _ = bfgs(lambda x: (seen.append(x.copy()), f(x))[1], np.zeros(3), inv_hessian=h, grad_tol=0.0,
                              rel_cost_tol=tol)
            blind, _ = bfgs(lambda x: (blind_seen.append(x.copy()), f(x))[1], np.zeros(3), inv_hessian=h,
                            grad_tol=0.0, rel_cost_tol=tol, last_step_unevaluated=True)
            if blind.message != "predicted cost change below tolerance":
                assert h is None and tol == 1e-4  # a cold start stopped by the measured change before H was learnt
                np.testing.assert_array_equal(blind.x, checked.x)
                continue
            assert blind.converged and checked.message == "relative cost tolerance reached"
            assert blind.evaluations == checked.evaluations - 1
            np.testing.assert_array_equal(blind.x, checked.x)  # the point the checked run evaluated last
            np.testing.assert_array_equal(np.array(blind_seen), np.array(seen[:-1]))
            assert blind.fun == f(blind_seen[-1])[0]  # the cost reported is the last one evaluated


def test_bfgs_deadline_returns_the_best_point_so_far():
    """A real-time budget: past the deadline no new iteration starts; the result is the best point evaluated."""
    import time

    c = np.array([3.0, -2.0, 1.0])
    f = _quadratic(np.diag([1.0, 5.0, 20.0]), np.diag([1.0, 5.0, 20.0]) @ c)
    full, _ = bfgs(f, np.zeros(3), grad_tol=1e-10, rel_cost_tol=0.0, max_step=10.0)
    cut, _ = bfgs(f, np.zeros(3), grad_tol=1e-10, rel_cost_tol=0.0, max_step=10.0, deadline=time.monotonic() - 1.0)
    assert full.converged and cut.message == "time budget reached" and not cut.converged
    assert cut.iterations == 1 and cut.evaluations < full.evaluations
    assert cut.fun < f(np.zeros(3))[0]  # one step was taken and kept


def test_bfgs_drops_a_carried_inverse_hessian_whose_curvature_collapsed():
    """A carried H with one collapsed direction (inverse curvature 1e-4 where the cost's is 1): every step along it
    is too short to teach H otherwise, and the step tolerance stops far from the optimum; with max_condition the
    degenerate H is dropped (a cold start) and the optimum is reached. A well-conditioned carried H is kept."""
    target = np.array([1.0, -0.5, 0.3])

    def fun(x):
        d = x - target
        return float(d @ d), 2.0 * d

    collapsed = np.diag([1e-4, 0.5, 0.5])
    stuck, _ = bfgs(fun, np.zeros(3), inv_hessian=collapsed, step_tol=0.05)
    assert abs(stuck.x[0] - target[0]) > 0.9  # held near its start along the collapsed direction
    res, _ = bfgs(fun, np.zeros(3), inv_hessian=collapsed, step_tol=0.05, max_condition=1e3)
    np.testing.assert_allclose(res.x, target, atol=0.05)
    warm, _ = bfgs(fun, np.zeros(3), inv_hessian=np.eye(3) * 0.5, step_tol=0.05, max_condition=1e3)
    assert warm.evaluations <= 2 and np.allclose(warm.x, target)  # the exact Newton step: H kept

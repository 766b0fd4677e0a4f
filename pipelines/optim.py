"""Local optimisers (generic): Fletcher-Reeves nonlinear CG and a warm-started BFGS.

Fletcher-Reeves CG with a strong-Wolfe line search (the reference's solver; the back-end's).

``fun(x) -> (cost, grad)``; minimises by default, ``maximize=True`` maximises the same function (the
front-end maximises contrast). Parameters mirror the reference's GSL set-up (``conjugate_fr``):
first trial step length ``init_step`` (in x units), line-search tolerance ``line_search_tol`` (the
strong-Wolfe curvature constant: |phi'(a)| <= tol |phi'(0)|, close to GSL's meaning), at most
``max_iter`` line searches, stop when ||grad|| < ``grad_tol`` or when the cost changes by less than
``rel_cost_tol`` relative to its magnitude. The direction restarts with steepest descent every
len(x) iterations and whenever it is not a descent direction (standard for FR, and what GSL does).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ti_cmax.config import STEP_GUESSES


@dataclass(frozen=True)
class CGResult:
    x: np.ndarray
    fun: float  # value of the objective as given (not negated when maximising)
    grad: np.ndarray  # gradient of the objective as given
    iterations: int  # line searches performed
    evaluations: int  # calls of fun
    converged: bool
    message: str


class _Counted:
    """Wraps fun: counts calls, negates for maximisation, remembers the best point seen."""

    def __init__(self, fun, sign):
        self.fun, self.sign, self.count = fun, sign, 0
        self.best = None

    def __call__(self, x):
        self.count += 1
        c, g = self.fun(x)
        c = self.sign * float(c)
        g = self.sign * np.asarray(g, dtype=float)
        if self.best is None or c < self.best[1]:
            self.best = (np.array(x, dtype=float), c, g)
        return c, g


def _cubic_min(a, fa, da, b, fb, db):
    """Minimiser of the cubic through (a, fa, da), (b, fb, db), or None."""
    d1 = da + db - 3 * (fa - fb) / (a - b)
    sq = d1 * d1 - da * db
    if sq < 0:
        return None
    d2 = np.copysign(np.sqrt(sq), b - a)
    den = db - da + 2 * d2
    if den == 0:
        return None
    return b - (b - a) * (db + d2 - d1) / den


def _interpolate(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi):
    """Trial step inside the bracket: cubic interpolation, safeguarded towards the middle."""
    lo, hi = min(a_lo, a_hi), max(a_lo, a_hi)
    t = _cubic_min(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi)
    margin = 0.1 * (hi - lo)
    if t is None or not np.isfinite(t) or t < lo + margin or t > hi - margin:
        t = 0.5 * (lo + hi)
    return t


def wolfe_line_search(fc, x, p, f0, g0, alpha0, c1=1e-4, c2=0.05, max_evals=20):
    """Strong-Wolfe line search (Nocedal & Wright Alg. 3.5/3.6 with cubic zoom).

    Returns (alpha, f, g, ok); when no point satisfies both conditions within ``max_evals``, returns the
    lowest point found with ok=False (alpha = 0 if nothing decreased the cost).
    """
    d0 = float(g0 @ p)
    a_prev, f_prev, d_prev = 0.0, f0, d0
    alpha = alpha0
    best = (0.0, f0, g0)
    evals = 0

    def zoom(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi, evals, best):
        while evals < max_evals:
            a = _interpolate(a_lo, f_lo, d_lo, a_hi, f_hi, d_hi)
            f, g = fc(x + a * p)
            evals += 1
            d = float(g @ p)
            if f < best[1]:
                best = (a, f, g)
            if f > f0 + c1 * a * d0 or f >= f_lo:
                a_hi, f_hi, d_hi = a, f, d
            else:
                if abs(d) <= -c2 * d0:
                    return (a, f, g, True), evals
                if d * (a_hi - a_lo) >= 0:
                    a_hi, f_hi, d_hi = a_lo, f_lo, d_lo
                a_lo, f_lo, d_lo = a, f, d
            if abs(a_hi - a_lo) <= 1e-12 * max(1.0, abs(a_lo)):
                break
        return (best[0], best[1], best[2], False), evals

    while evals < max_evals:
        f, g = fc(x + alpha * p)
        evals += 1
        d = float(g @ p)
        if f < best[1]:
            best = (alpha, f, g)
        if f > f0 + c1 * alpha * d0 or (evals > 1 and f >= f_prev):
            return zoom(a_prev, f_prev, d_prev, alpha, f, d, evals, best)[0]
        if abs(d) <= -c2 * d0:
            return alpha, f, g, True
        if d >= 0:
            return zoom(alpha, f, d, a_prev, f_prev, d_prev, evals, best)[0]
        a_prev, f_prev, d_prev = alpha, f, d
        alpha *= 2.0  # expand until the minimum is bracketed
    return best[0], best[1], best[2], False


def fletcher_reeves(
    fun: Callable[[np.ndarray], tuple[float, np.ndarray]],
    x0,
    *,
    maximize: bool = False,
    init_step: float = 0.1,
    line_search_tol: float = 0.05,
    max_iter: int = 50,
    grad_tol: float = 1e-3,
    rel_cost_tol: float = 1e-4,
    max_line_evals: int = 20,
    step_guess: str = "decrease",
) -> CGResult:
    """Minimise (or maximise) fun with Fletcher-Reeves nonlinear CG; see the module docstring.

    ``step_guess`` chooses the first trial step of every line search after the first: ``"decrease"`` (default)
    predicts the same first-order decrease as the last step (Nocedal & Wright eq. 3.60); ``"secant"`` puts it at
    the minimum of the quadratic model along the new direction whose curvature is the secant one of the last
    step, (s.y)/(s.s) (s: step, y: change of gradient), so on a near-quadratic cost the first trial is usually
    accepted (falls back to "decrease" when s.y <= 0).
    """
    if step_guess not in STEP_GUESSES:
        raise ValueError(f"step_guess must be 'decrease' or 'secant', got {step_guess!r}")
    sign = -1.0 if maximize else 1.0
    fc = _Counted(fun, sign)
    x = np.array(x0, dtype=float)
    n = x.size
    f, g = fc(x)
    it = 0
    converged, message = False, "maximum number of iterations reached"
    if not np.isfinite(f):
        return CGResult(x, sign * f, sign * g, 0, fc.count, False, "non-finite cost at the starting point")
    if np.linalg.norm(g) < grad_tol:
        return CGResult(x, sign * f, sign * g, 0, fc.count, True, "gradient tolerance reached")
    p = -g
    gg = float(g @ g)
    alpha = init_step / np.linalg.norm(p)
    while it < max_iter:
        it += 1
        a, f_new, g_new, ok = wolfe_line_search(fc, x, p, f, g, alpha, c2=line_search_tol, max_evals=max_line_evals)
        if a == 0.0:
            if not np.array_equal(p, -g):  # retry once along steepest descent
                p = -g
                alpha = init_step / np.linalg.norm(p)
                continue
            message = "line search made no progress"
            converged = np.linalg.norm(g) < 10 * grad_tol
            break
        x = x + a * p
        f_old, f = f, f_new
        g_old_p = float(g @ p)
        g_prev, g = g, g_new
        if abs(f - f_old) <= rel_cost_tol * max(abs(f_old), 1e-300):
            converged, message = True, "relative cost tolerance reached"
            break
        if np.linalg.norm(g) < grad_tol:
            converged, message = True, "gradient tolerance reached"
            break
        gg_new = float(g @ g)
        if it % n == 0:
            p_new = -g
        else:
            p_new = -g + (gg_new / gg) * p
        if float(g @ p_new) >= 0:
            p_new = -g
        # next trial step: same predicted decrease as the last one (Nocedal & Wright, eq. 3.60)
        d_new = float(g @ p_new)
        alpha = a * g_old_p / d_new if d_new < 0 else init_step / np.linalg.norm(p_new)
        if step_guess == "secant" and d_new < 0:
            step = a * p
            sy = float(step @ (g - g_prev))
            if sy > 0:
                alpha = -d_new * float(step @ step) / (sy * float(p_new @ p_new))
        if not np.isfinite(alpha) or alpha <= 0:
            alpha = init_step / np.linalg.norm(p_new)
        p, gg = p_new, gg_new
    best_x, best_f, best_g = fc.best
    if best_f < f:  # never return worse than the best point evaluated
        x, f, g = best_x, best_f, best_g
    return CGResult(x, sign * f, sign * g, it, fc.count, converged, message)


def _carried_inverse_hessian(inv_hessian, max_condition: float) -> np.ndarray | None:
    """The inverse Hessian a problem starts from: the carried one, unless ``max_condition`` > 0 and its condition
    number exceeds it (also when it has a non-positive eigenvalue): then None, a cold start. BFGS only corrects H
    along the steps it takes, so a direction whose inverse curvature collapsed (one update across a noisy,
    non-quadratic cost) gets steps too short to ever be corrected, and the step tolerance then stops far from the
    optimum along it, packet after packet."""
    H = None if inv_hessian is None else np.array(inv_hessian, dtype=float)
    if H is not None and max_condition > 0:
        ev = np.linalg.eigvalsh(H)
        if not ev[0] * max_condition >= ev[-1]:
            H = None
    return H


def _bfgs_step(fc, x, p, f, d, norm, steepest, max_line_evals, c1, c2, max_step):
    """Line search along p from x (cost f, slope d, step length norm): backtracking by quadratic interpolation until
    the Armijo condition (c1) holds, at most ``max_line_evals`` evaluations; a steepest-descent step after which the
    cost still falls nearly as steeply (weak Wolfe constant c2) is doubled while that lowers the cost, so a cold
    start far from the optimum does not crawl. Returns (a, accepted, f_new, g_new)."""
    a, accepted, evals = 1.0, False, 0
    while evals < max_line_evals:  # backtrack until the Armijo condition holds
        f_new, g_new = fc(x + a * p)
        evals += 1
        if f_new <= f + c1 * a * d:
            accepted = True
            break
        # minimiser of the quadratic through f, d (at 0) and f_new (at a), kept in [0.1 a, 0.5 a]
        curv = 2.0 * (f_new - f - a * d)
        a = min(max(-d * a * a / curv if curv > 0 else 0.5 * a, 0.1 * a), 0.5 * a)
    # a steepest-descent step (no curvature known yet) after which the cost still falls nearly as steeply (weak
    # Wolfe curvature condition fails): far too short, e.g. a cold start far from the optimum; double it while
    # that lowers the cost. Quasi-Newton steps are not expanded (a far jump could land on another optimum)
    while (steepest and accepted and evals < max_line_evals and float(g_new @ p) < c2 * d
           and 2.0 * a * norm <= max_step * (1.0 + 1e-12)):
        f_try, g_try = fc(x + 2.0 * a * p)
        evals += 1
        if not f_try < f_new:
            break
        a, f_new, g_new = 2.0 * a, f_try, g_try
    return a, accepted, f_new, g_new


def _bfgs_update(H, s, y) -> tuple[np.ndarray | None, int]:
    """BFGS update of the inverse Hessian by the step s and gradient change y (Nocedal & Wright eq. 6.17; the
    first one scaled by eq. 6.20); skipped when s.y <= 0 (it would lose positive definiteness). Returns (H, 1 if
    updated else 0)."""
    sy = float(s @ y)
    if not sy > 0:
        return H, 0
    n = len(s)
    if H is None:
        H = np.eye(n) * (sy / float(y @ y))
    rho = 1.0 / sy
    v = np.eye(n) - rho * np.outer(s, y)
    return v @ H @ v.T + rho * np.outer(s, s), 1


def _bfgs_direction(H, g, init_step: float, max_step: float):
    """The quasi-Newton step -H g, or a steepest-descent step of length ``init_step`` when no curvature is known
    yet or H lost positive definiteness numerically (H is then None), capped at ``max_step``. Returns (H, p,
    d = g.p, |p|, capped)."""
    p = None if H is None else -(H @ g)
    if p is None or not float(g @ p) < 0:
        H = None
        p = -g * (init_step / np.linalg.norm(g))
    d = float(g @ p)
    norm = float(np.linalg.norm(p))
    capped = norm > max_step
    if capped:
        p *= max_step / norm
        d *= max_step / norm
        norm = max_step
    return H, p, d, norm, capped


def _learnt_stop(f, f_old, g, H, learnt: bool, rel_cost_tol: float, step_tol: float) -> str:
    """Why BFGS stops after a step ("" if it goes on). A small cost change means convergence once H has learnt the
    curvature (a carried H, or n updates from a cold start): before that, a step may just be short along a
    direction H underestimates. A next quasi-Newton step -H g shorter than ``step_tol`` (x units) also stops it: the
    evaluation that step would cost cannot move the solution by more than that."""
    if learnt and abs(f - f_old) <= rel_cost_tol * max(abs(f_old), 1e-300):
        return "relative cost tolerance reached"
    if step_tol > 0 and learnt and H is not None and float(np.linalg.norm(H @ g)) < step_tol:
        return "step tolerance reached"
    return ""


def bfgs(
    fun: Callable[[np.ndarray], tuple[float, np.ndarray]],
    x0,
    *,
    maximize: bool = False,
    inv_hessian: np.ndarray | None = None,
    init_step: float = 0.1,
    max_iter: int = 50,
    grad_tol: float = 1e-3,
    rel_cost_tol: float = 1e-4,
    max_step: float = 2.0,
    max_line_evals: int = 4,
    c1: float = 1e-4,
    c2: float = 0.9,
    step_tol: float = 0.0,
    deadline: float | None = None,
    last_step_unevaluated: bool = False,
    max_condition: float = 0.0,
) -> tuple[CGResult, np.ndarray | None]:
    """Minimise (or maximise) fun by BFGS from a given inverse Hessian; returns (result, inverse Hessian).

    Made for a sequence of similar problems (the front-end's packets): the caller passes back the inverse Hessian
    the last problem ended with, so the first step is already a quasi-Newton step. ``inv_hessian=None`` starts with
    a steepest-descent step of length ``init_step`` and scales the first update by (s.y)/(y.y) (Nocedal & Wright
    eq. 6.20); ``max_condition``: :func:`_carried_inverse_hessian`. Steps are capped at ``max_step`` (x units) and
    searched by :func:`_bfgs_step`. Stops at ||grad|| < ``grad_tol`` or, once H is learnt, by :func:`_learnt_stop`.
    A failed line search returns the best point and None (the next problem starts afresh); an update that would
    lose positive definiteness is skipped. ``deadline`` (a ``time.monotonic()`` value): no new iteration starts
    after it (a real-time budget), message "time budget reached". ``last_step_unevaluated``: once H is learnt, a
    full quasi-Newton step whose predicted cost change (g.H.g / 2) is below half ``rel_cost_tol`` is taken without
    evaluating it and BFGS stops there, where the evaluated step would stop too unless the model is off by over 2x
    ("predicted cost change below tolerance"; ``fun``, ``grad``: the last evaluated, H lacks that step's update).
    """
    sign = -1.0 if maximize else 1.0
    fc = _Counted(fun, sign)
    x = np.array(x0, dtype=float)
    n = x.size
    H = _carried_inverse_hessian(inv_hessian, max_condition)
    updates = 0 if H is None else n  # BFGS updates behind H (a carried H counts as learnt)
    f, g = fc(x)
    if not np.isfinite(f):
        return CGResult(x, sign * f, sign * g, 0, fc.count, False, "non-finite cost at the starting point"), None
    it, converged, message = 0, False, "maximum number of iterations reached"
    unevaluated = False  # x is a last step taken without evaluating it (last_step_unevaluated)
    while it < max_iter:
        if np.linalg.norm(g) < grad_tol:
            converged, message = True, "gradient tolerance reached"
            break
        if deadline is not None and it > 0 and time.monotonic() > deadline:
            message = "time budget reached"
            break
        it += 1
        H, p, d, norm, capped = _bfgs_direction(H, g, init_step, max_step)
        steepest = H is None
        if steepest:
            updates = 0
        elif (not capped and last_step_unevaluated and updates >= n
              and -0.5 * d <= 0.5 * rel_cost_tol * max(abs(f), 1e-300)):
            x = x + p
            converged, message, unevaluated = True, "predicted cost change below tolerance", True
            break
        a, accepted, f_new, g_new = _bfgs_step(fc, x, p, f, d, norm, steepest, max_line_evals, c1, c2, max_step)
        if not accepted:
            message = "line search made no progress"
            converged = np.linalg.norm(g) < 10 * grad_tol
            H = None
            break
        s, y = a * p, g_new - g
        H, updated = _bfgs_update(H, s, y)
        updates += updated
        f_old = f
        x, f, g = x + s, f_new, g_new
        stop = _learnt_stop(f, f_old, g, H, updates >= n, rel_cost_tol, step_tol)
        if stop:
            converged, message = True, stop
            break
    best_x, best_f, best_g = fc.best
    if best_f < f and not unevaluated:
        x, f, g = best_x, best_f, best_g
    return CGResult(x, sign * f, sign * g, it, fc.count, converged, message), H


__all__ = ["CGResult", "fletcher_reeves", "wolfe_line_search", "bfgs"]

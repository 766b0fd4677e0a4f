"""Nonlinear conjugate gradient of Fletcher-Reeves with a strong-Wolfe line search (generic).

``fun(x) -> (cost, grad)``; minimises by default, ``maximize=True`` maximises the same function (the
front-end maximises contrast). Parameters mirror the reference's GSL set-up (``conjugate_fr``):
first trial step length ``init_step`` (in x units), line-search tolerance ``line_search_tol`` (the
strong-Wolfe curvature constant: |phi'(a)| <= tol |phi'(0)|, close to GSL's meaning), at most
``max_iter`` line searches, stop when ||grad|| < ``grad_tol`` or when the cost changes by less than
``rel_cost_tol`` relative to its magnitude. The direction restarts with steepest descent every
len(x) iterations and whenever it is not a descent direction (standard for FR, and what GSL does).
"""
from __future__ import annotations

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


__all__ = ["CGResult", "fletcher_reeves", "wolfe_line_search"]

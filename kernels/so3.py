"""SO(3) as Taichi funcs (Taichi has no built-in exp/log): Rodrigues exp, log, Jl, Jr, Jr^-1.

Same formulas and conventions as ``ti_cmax.so3`` (right Jacobian: exp(phi + d) ~= exp(phi) exp(Jr(phi) d)).
``so3_funcs(dtype)`` builds the funcs for one float type (f32 production, f64 for gradient checks); all literals are
cast to that type (constants are ratios of exactly representable numbers: a Python float literal becomes an
f32 constant first, which would spoil the f64 path). Small-angle branches use Taylor series below theta = 0.1
(truncation error < 1e-15 relative), and the sin^2 form of (1 - cos)/theta^2, so f32 keeps full relative
precision for tiny rotations.
"""

import functools
from types import SimpleNamespace

from .runtime import ti

_TAYLOR = 0.1


@functools.cache
def so3_funcs(dtype) -> SimpleNamespace:
    """Namespace of ti.funcs (hat, vee, exp, exp_jl, log, jr, jl, jr_inv) for one float dtype (ti.f32 or ti.f64)."""
    mat3 = ti.types.matrix(3, 3, dtype)
    vec3 = ti.types.vector(3, dtype)

    @ti.func
    def c(x):
        return ti.cast(x, dtype)

    @ti.func
    def hat(v):
        return mat3([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    @ti.func
    def vee(m):
        """Vector of the antisymmetric part of m."""
        return vec3([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) * c(0.5)

    @ti.func
    def coeffs(theta):
        """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, D = coefficient of Jr^-1."""
        t2 = theta * theta
        a = c(0.0)
        bb = c(0.5)
        cc = c(0.0)
        d = c(0.0)
        if theta < c(_TAYLOR):
            a = c(1.0) - t2 / c(6.0) * (c(1.0) - t2 / c(20.0) * (c(1.0) - t2 / c(42.0) * (c(1.0) - t2 / c(72.0))))
            cc = c(1.0) / c(6.0) - t2 / c(120.0) * (
                c(1.0) - t2 / c(42.0) * (c(1.0) - t2 / c(72.0) * (c(1.0) - t2 / c(110.0))))
            d = c(1.0) / c(12.0) + t2 * (c(1.0) / c(720.0) + t2 * (c(1.0) / c(30240.0) + t2 * c(1.0) / c(1209600.0)))
        else:
            sn = ti.sin(theta)
            a = sn / theta
            cc = (theta - sn) / (t2 * theta)
            d = c(1.0) / t2 - (c(1.0) + ti.cos(theta)) / (c(2.0) * theta * sn)
        if theta > c(1e-6):
            h = ti.sin(c(0.5) * theta) / theta
            bb = c(2.0) * h * h
        else:
            bb = c(0.5) - t2 / c(24.0)
        return a, bb, cc, d

    @ti.func
    def exp(v):
        theta = v.norm()
        a, bb, cc, d = coeffs(theta)
        k = hat(v)
        return ti.Matrix.identity(dtype, 3) + a * k + bb * (k @ k)

    @ti.func
    def jr(v):
        """Right Jacobian Jr(v) = I - B [v]x + C [v]x^2."""
        theta = v.norm()
        a, bb, cc, d = coeffs(theta)
        k = hat(v)
        return ti.Matrix.identity(dtype, 3) - bb * k + cc * (k @ k)

    @ti.func
    def jl(v):
        """Left Jacobian Jl(v) = Jr(-v)."""
        return jr(-v)

    @ti.func
    def exp_jl(v):
        """(exp(v), Jl(v)) sharing one set of coefficients (Jl = I + B [v]x + C [v]x^2)."""
        theta = v.norm()
        a, bb, cc, d = coeffs(theta)
        k = hat(v)
        k2 = k @ k
        eye = ti.Matrix.identity(dtype, 3)
        return eye + a * k + bb * k2, eye + bb * k + cc * k2

    @ti.func
    def jr_inv(v):
        """Inverse right Jacobian I + 1/2 [v]x + D [v]x^2."""
        theta = v.norm()
        a, bb, cc, d = coeffs(theta)
        k = hat(v)
        return ti.Matrix.identity(dtype, 3) + c(0.5) * k + d * (k @ k)

    @ti.func
    def log(r):
        """Rotation vector of r (|v| <= pi): atan2 angle, symmetric-part axis near pi."""
        w = vee(r)  # sin(theta) * axis
        s = w.norm()
        cs = ti.min(ti.max(c(0.5) * (r.trace() - c(1.0)), c(-1.0)), c(1.0))
        theta = ti.atan2(s, cs)
        out = vec3(0, 0, 0)
        if cs > c(-0.99):
            scale = c(1.0)
            if s > c(1e-7):
                scale = theta / s
            else:
                scale = c(1.0) + theta * theta / c(6.0)
            out = w * scale
        else:
            sym = c(0.5) * (r + r.transpose()) - cs * ti.Matrix.identity(dtype, 3)  # (1 - cos) a a^T
            i = 0
            if sym[1, 1] > sym[i, i]:
                i = 1
            if sym[2, 2] > sym[i, i]:
                i = 2
            col = vec3(sym[0, i], sym[1, i], sym[2, i])
            axis = col / col.norm()
            if axis.dot(w) < c(0.0):
                axis = -axis
            out = theta * axis
        return out

    return SimpleNamespace(hat=hat, vee=vee, exp=exp, exp_jl=exp_jl, log=log, jr=jr, jl=jl, jr_inv=jr_inv,
                           mat3=mat3, vec3=vec3)

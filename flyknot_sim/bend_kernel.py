"""The frictional bending couples' end-of-step solve, compiled (numba).

The same equations as :func:`flyknot_sim.bend_friction.rope_bend_friction_forces` with
``dt > 0`` (its docstring and the module's state them), written as loops over the joints so
that one call costs tens of microseconds instead of ~0.5 ms of small numpy operations: the
couples are solved at every simulation step, and a 1 ms step of the rope takes ~0.1 ms in
MuJoCo. The numpy function stays the readable reference; ``tests/test_bend_friction.py``
holds the two equal to rounding.

The linear system (I + dt A K) y = dw of the 3 (n - 1) joint rates is block-pentadiagonal
(half-bandwidth 8); it is solved by Gaussian elimination with partial pivoting restricted to
the band (the fill-in of row exchanges widens the upper band to 16), as LAPACK's ``dgbsv``
does.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["bend_friction_forces"]

_KL = 8  # lower half-bandwidth of the joint system (3 * 2 + 2)
_KU = 16  # upper half-bandwidth after the row exchanges of partial pivoting (2 * _KL)


@numba.njit(cache=True, fastmath=True)
def _skew_into(e, s, out):
    """out = s [e]_x (so that out u = s (e x u))."""
    out[0, 0] = out[1, 1] = out[2, 2] = 0.0
    out[0, 1] = -e[2] * s
    out[0, 2] = e[1] * s
    out[1, 0] = e[2] * s
    out[1, 2] = -e[0] * s
    out[2, 0] = -e[1] * s
    out[2, 1] = e[0] * s


@numba.njit(cache=True, fastmath=True)
def _band_solve(ab, b):
    """Solve a y = b in place; ``ab[i, j - i + _KL]`` holds a[i, j] for j - i in
    [-_KL, _KU] (zero above the original upper band: room for the fill-in); returns y."""
    n = ab.shape[0]
    for k in range(n):
        last = min(n - 1, k + _KL)
        p = k
        for i in range(k + 1, last + 1):
            if abs(ab[i, k - i + _KL]) > abs(ab[p, k - p + _KL]):
                p = i
        right = min(n - 1, k + _KU)
        if p != k:
            for j in range(k, right + 1):
                t = ab[k, j - k + _KL]
                ab[k, j - k + _KL] = ab[p, j - p + _KL]
                ab[p, j - p + _KL] = t
            b[k], b[p] = b[p], b[k]
        pivot = ab[k, _KL]
        for i in range(k + 1, last + 1):
            f = ab[i, k - i + _KL] / pivot
            if f != 0.0:
                for j in range(k + 1, right + 1):
                    ab[i, j - i + _KL] -= f * ab[k, j - k + _KL]
                b[i] -= f * b[k]
    y = np.zeros(n)
    for k in range(n - 1, -1, -1):
        s = b[k]
        for j in range(k + 1, min(n - 1, k + _KU) + 1):
            s -= ab[k, j - k + _KL] * y[j]
        y[k] = s / ab[k, _KL]
    return y


@numba.njit(cache=True, fastmath=True)
def _proj_norm2(p, u, at):
    """|p u[at:at + 3]|^2 for a 3x3 p."""
    total = 0.0
    for i in range(3):
        r = p[i, 0] * u[at] + p[i, 1] * u[at + 1] + p[i, 2] * u[at + 2]
        total += r * r
    return total


@numba.njit(cache=True, fastmath=True)
def _mul(a, b, out, scale):
    """out = scale a b for 3x3 a, b."""
    for i in range(3):
        for j in range(3):
            out[i, j] = scale * (a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j])


@numba.njit(cache=True, fastmath=True)
def _mul_t(a, b, out, scale):
    """out = scale a^T b for 3x3 a, b."""
    for i in range(3):
        for j in range(3):
            out[i, j] = scale * (a[0, i] * b[0, j] + a[1, i] * b[1, j] + a[2, i] * b[2, j])


@numba.njit(cache=True, fastmath=True)
def bend_friction_forces(x, v, moment, rate0, inv_mass, dt, span_reg, iterations, tiny):
    """Forces of the frictional bending couples taken at the end of the step, (n + 1, 3) [N].

    Args:
        x: Vertex positions, (n + 1, 3) [m], n >= 2.
        v: Vertex velocities, (n + 1, 3) [m/s].
        moment: M_0 [N m].
        rate0: r_0 [rad/s].
        inv_mass: 1 / vertex mass, (n + 1,) [1/kg] (0: held).
        dt: Step [s] (> 0).
        span_reg: Tikhonov weight of the projectors [-].
        iterations: Fixed-point passes of c_k.
        tiny: Floor of |e|^2 [m^2].
    """
    n = x.shape[0] - 1
    nj = n - 1
    e = np.empty((n, 3))
    inv_l2 = np.empty(n)
    t = np.empty((n, 3))
    sk = np.empty((n, 3, 3))
    for j in range(n):
        for c in range(3):
            e[j, c] = x[j + 1, c] - x[j, c]
        l2 = e[j, 0] ** 2 + e[j, 1] ** 2 + e[j, 2] ** 2
        inv_l2[j] = 1.0 / max(l2, tiny)
        s = np.sqrt(inv_l2[j])
        for c in range(3):
            t[j, c] = e[j, c] * s
        _skew_into(e[j], inv_l2[j], sk[j])
    # joint blocks of J (dw_k = J0 v_k + J1 v_{k+1} + J2 v_{k+2}), projectors, rates
    jb = np.empty((3, nj, 3, 3))
    proj = np.empty((nj, 3, 3))
    dw = np.zeros((nj, 3))
    coef = np.empty(nj)
    g = 1.0 + span_reg
    for k in range(nj):
        for i in range(3):
            for j in range(3):
                jb[0, k, i, j] = sk[k, i, j]
                jb[1, k, i, j] = -sk[k + 1, i, j] - sk[k, i, j]
                jb[2, k, i, j] = sk[k + 1, i, j]
        for b in range(3):
            for i in range(3):
                dw[k, i] += (
                    jb[b, k, i, 0] * v[k + b, 0]
                    + jb[b, k, i, 1] * v[k + b, 1]
                    + jb[b, k, i, 2] * v[k + b, 2]
                )
        ta, tb = t[k], t[k + 1]
        cab = ta[0] * tb[0] + ta[1] * tb[1] + ta[2] * tb[2]
        det = g * g - cab * cab
        for i in range(3):
            for j in range(3):
                sym = g * (ta[i] * ta[j] + tb[i] * tb[j]) - cab * (ta[i] * tb[j] + tb[i] * ta[j])
                proj[k, i, j] = (1.0 if i == j else 0.0) - sym / det
        coef[k] = moment / np.sqrt(_proj_norm2(proj[k], dw[k], 0) + rate0 * rate0)
    # A = J m^-1 J^T: block diagonals d = 0, 1, 2
    amob = np.zeros((3, nj, 3, 3))
    for d in range(min(3, nj)):
        for k in range(nj - d):
            for b in range(3 - d):
                im = inv_mass[k + b + d]
                for i in range(3):
                    for j in range(3):
                        amob[d, k, i, j] += im * (
                            jb[b + d, k, i, 0] * jb[b, k + d, j, 0]
                            + jb[b + d, k, i, 1] * jb[b, k + d, j, 1]
                            + jb[b + d, k, i, 2] * jb[b, k + d, j, 2]
                        )
    size = 3 * nj
    y = np.zeros(size)
    stiff = np.empty((nj, 3, 3))
    blk = np.empty((3, 3))
    ab = np.empty((size, _KL + _KU + 1))
    rhs = np.empty(size)
    for it in range(iterations):
        for k in range(nj):
            for i in range(3):
                for j in range(3):
                    stiff[k, i, j] = coef[k] * proj[k, i, j]
        ab[:] = 0.0
        for d in range(min(3, nj)):
            for k in range(nj - d):
                _mul(amob[d, k], stiff[k + d], blk, dt)  # (A K)_{k, k+d}
                for i in range(3):
                    for j in range(3):
                        row, col = 3 * k + i, 3 * (k + d) + j
                        ab[row, col - row + _KL] += blk[i, j]
                if d > 0:
                    _mul_t(amob[d, k], stiff[k], blk, dt)  # (A K)_{k+d, k}
                    for i in range(3):
                        for j in range(3):
                            row, col = 3 * (k + d) + i, 3 * k + j
                            ab[row, col - row + _KL] += blk[i, j]
        for i in range(size):
            ab[i, _KL] += 1.0
        for k in range(nj):
            for i in range(3):
                rhs[3 * k + i] = dw[k, i]
        y = _band_solve(ab, rhs)
        if it + 1 < iterations:
            for k in range(nj):
                coef[k] = moment / np.sqrt(_proj_norm2(proj[k], y, 3 * k) + rate0 * rate0)
    couple = np.zeros((n, 3))
    for k in range(nj):
        for i in range(3):
            m = -(
                stiff[k, i, 0] * y[3 * k]
                + stiff[k, i, 1] * y[3 * k + 1]
                + stiff[k, i, 2] * y[3 * k + 2]
            )
            couple[k + 1, i] += m
            couple[k, i] -= m
    f = np.zeros((n + 1, 3))
    for j in range(n):
        cj, ej = couple[j], e[j]
        fs0 = (cj[1] * ej[2] - cj[2] * ej[1]) * inv_l2[j]
        fs1 = (cj[2] * ej[0] - cj[0] * ej[2]) * inv_l2[j]
        fs2 = (cj[0] * ej[1] - cj[1] * ej[0]) * inv_l2[j]
        f[j + 1, 0] += fs0
        f[j + 1, 1] += fs1
        f[j + 1, 2] += fs2
        f[j, 0] -= fs0
        f[j, 1] -= fs1
        f[j, 2] -= fs2
    return f

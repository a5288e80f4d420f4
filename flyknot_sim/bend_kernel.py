"""The frictional bending couples' end-of-step solve, compiled (numba).

The same equations as :func:`flyknot_sim.bend_friction.rope_bend_friction_forces` with
``dt > 0`` (its docstring and the module's state them), written as loops over the joints so
that one call costs tens of microseconds instead of ~0.5 ms of small numpy operations: the
couples are solved at every simulation step, and a 1 ms step of the rope takes ~0.1 ms in
MuJoCo. The numpy function stays the readable reference; ``tests/test_bend_friction.py``
holds the two equal within 1e-6 of the largest force (rounding, which the fixed-point passes
amplify where a joint turns at about r_0).

The linear system (I + dt A K) y = dw of the 3 (n - 1) joint rates is solved in its symmetric
form. K = blockdiag(c_k P_k) with P_k symmetric, its eigenvalues 1 (normal of the joint's
plane), lambda / (g + c) and lambda / (g - c) (along t_a + t_b and t_a - t_b; g = 1 + lambda,
c = t_a . t_b, lambda the span regularisation), so K = S S with the symmetric square root
S_k = sqrt(c_k) P_k^(1/2) in closed form. With z = S y the system becomes

    (I + dt S A S) z = S dw,   M = -K y = -S z,   P_k y_k = P_k^(1/2) z_k / sqrt(c_k),

the same equations (S is invertible), but symmetric positive definite: a banded Cholesky
factorisation (half-bandwidth 8, no pivoting, no fill-in) solves it in a fraction of the
time of the general band LU with partial pivoting that the numpy reference calls (LAPACK
``dgbsv``, whose row exchanges widen the upper band to 16).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["add_bend_friction", "bend_friction_forces", "joint_moments"]

_KB = 8  # half-bandwidth of the joint system (3 * 2 + 2)


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
def _band_cholesky_solve(ab, b):
    """Solve h z = b for a symmetric positive definite band matrix h, in place.

    ``ab[i, i - j]`` holds h[i, j] for 0 <= i - j <= _KB (the lower band); it is overwritten
    by the Cholesky factor L (h = L L^T), ``b`` by the solution, which is returned.
    """
    n = ab.shape[0]
    for j in range(n):
        lo = max(0, j - _KB)
        d = ab[j, 0]
        for k in range(lo, j):
            d -= ab[j, j - k] * ab[j, j - k]
        d = np.sqrt(d)
        ab[j, 0] = d
        for i in range(j + 1, min(n, j + _KB + 1)):
            v = ab[i, i - j]
            for k in range(max(0, i - _KB), j):
                v -= ab[i, i - k] * ab[j, j - k]
            ab[i, i - j] = v / d
    for i in range(n):  # L w = b
        v = b[i]
        for k in range(max(0, i - _KB), i):
            v -= ab[i, i - k] * b[k]
        b[i] = v / ab[i, 0]
    for i in range(n - 1, -1, -1):  # L^T z = w
        v = b[i]
        for k in range(i + 1, min(n, i + _KB + 1)):
            v -= ab[k, k - i] * b[k]
        b[i] = v / ab[i, 0]
    return b


@numba.njit(cache=True, fastmath=True)
def _sqrt_projector(ta, tb, g, out):
    """out = P^(1/2) of the joint between unit tangents ta, tb (module docstring):
    I - a_+ (ta + tb)(ta + tb)^T - a_- (ta - tb)(ta - tb)^T,
    a_+- = 1 / (2 (g +- c) (1 + sqrt((g - 1) / (g +- c))))."""
    c = ta[0] * tb[0] + ta[1] * tb[1] + ta[2] * tb[2]
    lam = g - 1.0
    ap = 1.0 / (2.0 * (g + c) * (1.0 + np.sqrt(lam / (g + c))))
    am = 1.0 / (2.0 * (g - c) * (1.0 + np.sqrt(lam / (g - c))))
    for i in range(3):
        for j in range(3):
            sp = (ta[i] + tb[i]) * (ta[j] + tb[j])
            sm = (ta[i] - tb[i]) * (ta[j] - tb[j])
            out[i, j] = (1.0 if i == j else 0.0) - ap * sp - am * sm


@numba.njit(cache=True, fastmath=True)
def _mat_vec_norm2(p, u, at):
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
def bend_friction_forces(x, v, moment, rate0, inv_mass, dt, span_reg, iterations, tiny):
    """Forces of the frictional bending couples taken at the end of the step, (n + 1, 3) [N].

    Args:
        x: Vertex positions, (n + 1, 3) [m], n >= 2.
        v: Vertex velocities, (n + 1, 3) [m/s].
        moment: M_0 of each joint k = 1..n-1, (n - 1,) [N m] (>= 0).
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
    root = np.empty((nj, 3, 3))
    rdw = np.empty(3)
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
        _sqrt_projector(t[k], t[k + 1], g, root[k])
        for i in range(3):  # P_k dw_k = R_k (R_k dw_k)
            rdw[i] = root[k, i, 0] * dw[k, 0] + root[k, i, 1] * dw[k, 1] + root[k, i, 2] * dw[k, 2]
        coef[k] = moment[k] / np.sqrt(_mat_vec_norm2(root[k], rdw, 0) + rate0 * rate0)
    # the symmetric system (I + dt S A S) z = S dw, S_k = sqrt(c_k) R_k, R_k = P_k^(1/2).
    # G_{k,d} = R_k A_{k,k+d} R_{k+d}, A = J m^-1 J^T, does not change over the passes:
    # G_{k,d} = sum_b m^-1_{k+b+d} (R_k J_{b+d,k}) (R_{k+d} J_{b,k+d})^T and
    # H_{k,k+d} = dt sqrt(c_k c_{k+d}) G_{k,d}
    size = 3 * nj
    rj = np.empty((3, nj, 3, 3))
    for b in range(3):
        for k in range(nj):
            _mul(root[k], jb[b, k], rj[b, k], 1.0)
    gmat = np.zeros((3, nj, 3, 3))
    for d in range(min(3, nj)):
        for k in range(nj - d):
            for b in range(3 - d):
                im = inv_mass[k + b + d]
                if im == 0.0:
                    continue
                for i in range(3):
                    for j in range(3):
                        gmat[d, k, i, j] += im * (
                            rj[b + d, k, i, 0] * rj[b, k + d, j, 0]
                            + rj[b + d, k, i, 1] * rj[b, k + d, j, 1]
                            + rj[b + d, k, i, 2] * rj[b, k + d, j, 2]
                        )
    sc = np.empty(nj)
    ab = np.empty((size, _KB + 1))
    z = np.empty(size)
    for it in range(iterations):
        for k in range(nj):
            sc[k] = np.sqrt(coef[k])
        ab[:] = 0.0
        for d in range(min(3, nj)):
            for k in range(nj - d):
                w = dt * sc[k] * sc[k + d]
                for i in range(3):  # the lower band holds H_{k+d, k} = H_{k, k+d}^T
                    for j in range(3 if d > 0 else i + 1):
                        row, col = 3 * (k + d) + i, 3 * k + j
                        ab[row, row - col] += w * gmat[d, k, j, i]
        for i in range(size):
            ab[i, 0] += 1.0
        for k in range(nj):
            for i in range(3):
                z[3 * k + i] = sc[k] * (
                    root[k, i, 0] * dw[k, 0] + root[k, i, 1] * dw[k, 1] + root[k, i, 2] * dw[k, 2]
                )
        z = _band_cholesky_solve(ab, z)
        if it + 1 < iterations:
            for k in range(nj):
                if coef[k] > 0.0:  # a joint without a couple (M_0 = 0) stays without
                    py2 = _mat_vec_norm2(root[k], z, 3 * k) / coef[k]  # |P_k y_k|^2
                    coef[k] = moment[k] / np.sqrt(py2 + rate0 * rate0)
    couple = np.zeros((n, 3))
    for k in range(nj):
        for i in range(3):
            m = -sc[k] * (
                root[k, i, 0] * z[3 * k]
                + root[k, i, 1] * z[3 * k + 1]
                + root[k, i, 2] * z[3 * k + 2]
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


@numba.njit(cache=True)
def joint_moments(moment, arm, efc_type, efc_id, efc_force, eq_id, n, out):
    """Each joint's frictional couple M_0 + arm T_k into ``out`` (n - 1,) [N m] and return it.

    T_k is the tension at joint k (:func:`flyknot_sim.bend_friction.joint_tensions`) from the
    rope's edge-equality rows in MuJoCo's constraint arrays (``efc_type`` / ``efc_id`` /
    ``efc_force`` of ``data``, rows of type equality (0) and id ``eq_id``, one per edge, in
    edge order; the tension of edge j is -efc_force). Found in another number than the n
    edges (no constraint solved yet, e.g. before the first ``mj_forward``): T = 0, M_0 only.
    """
    nj = n - 1
    for k in range(nj):
        out[k] = moment
    if arm <= 0.0:
        return out
    start, count = -1, 0
    for i in range(efc_type.shape[0]):
        if efc_type[i] == 0 and efc_id[i] == eq_id:
            if start < 0:
                start = i
            count += 1
        elif start >= 0 or efc_type[i] != 0:  # past the block, or past the equality rows
            break
    if count != n:
        return out
    for k in range(nj):
        below = max(-efc_force[start + k + 1], 0.0)
        above = below if k == 0 else max(-efc_force[start + k], 0.0)  # edge 0 is held
        out[k] = moment + arm * 0.5 * (above + below)
    return out


@numba.njit(cache=True)
def add_bend_friction(
    qpos,
    qvel,
    qfrc,
    vert_qpos,
    vert_dof,
    pos0,
    added,
    after,
    has_prev,
    params,
    inv_mass,
    it,
    efc_type,
    efc_id,
    efc_force,
    eq_id,
):
    """Add the couples' forces of the current state to ``qfrc`` (``data.qfrc_applied``), in
    place, replacing this applier's previous contribution if ``qfrc`` still holds it.

    Gathers the vertices from ``qpos`` / ``qvel`` (indices ``vert_qpos`` / ``vert_dof``,
    (n + 1, 3); positions offset by ``pos0``), the joints' couples from :func:`joint_moments`
    (``params`` = (moment, rate0, dt, span_reg, tiny, arm); the constraint rows ``efc_*`` of
    the rope's edge equality ``eq_id``, unread when arm is 0), computes
    :func:`bend_friction_forces` with ``it`` passes, and writes
    ``qfrc[dof] = (qfrc[dof] - added if qfrc[dof] == after else qfrc[dof]) + f``; ``added``
    and ``after`` (n + 1, 3) are updated to f and the new values. Returns True.
    """
    nv = vert_qpos.shape[0]
    x = np.empty((nv, 3))
    v = np.empty((nv, 3))
    for i in range(nv):
        for c in range(3):
            x[i, c] = qpos[vert_qpos[i, c]] + pos0[i, c]
            v[i, c] = qvel[vert_dof[i, c]]
    moment, rate0, dt, span_reg, tiny = params[0], params[1], params[2], params[3], params[4]
    moments = joint_moments(
        moment, params[5], efc_type, efc_id, efc_force, eq_id, nv - 1, np.empty(nv - 2)
    )
    f = bend_friction_forces(x, v, moments, rate0, inv_mass, dt, span_reg, it, tiny)
    same = has_prev
    if same:
        for i in range(nv):
            for c in range(3):
                if qfrc[vert_dof[i, c]] != after[i, c]:
                    same = False
    for i in range(nv):
        for c in range(3):
            d = vert_dof[i, c]
            cur = qfrc[d] - added[i, c] if same else qfrc[d]
            qfrc[d] = cur + f[i, c]
            added[i, c] = f[i, c]
            after[i, c] = qfrc[d]
    return True

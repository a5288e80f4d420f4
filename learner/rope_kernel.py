"""Newton on one step of the learner's rope model, compiled (numba).

:class:`learner.rope_model._StepSolver` assembles the scaled KKT system of a step from NumPy
arrays; for the model's 11 links (a 44 x 44 system, a few iterations a step, ~100 steps a
rollout) NumPy's per-call overhead is most of a rollout's time. :func:`newton_step` runs the
same iteration (residuals, KKT matrix, LAPACK solve, backtracking on the squared residual) in
one compiled call. Sums run in a fixed loop order rather than BLAS's, so iterates agree with
the NumPy path to rounding (``tests/test_rope_kernel.py`` checks them against it).
"""

from __future__ import annotations

from functools import lru_cache

import numba
import numpy as np

__all__ = ["CONVERGED", "MAX_ITER", "NON_FINITE", "kkt_indices", "kkt_into", "newton_step"]

CONVERGED, NON_FINITE, MAX_ITER = 0, 1, 2
"""Status codes of :func:`newton_step`."""


@numba.njit(cache=True)
def _residual(p, mu, c, p_tip, H0, ell, r1, r2, dvec):
    """R1s = H0 p' + c - Ghat^T mu' into r1 (N, 3); R2s = g / (2 l) into r2 (N,) [m]."""
    n = p.shape[0]
    for j in range(n):
        for a in range(3):
            dvec[j, a] = p[j, a] - (p_tip[a] if j == 0 else p[j - 1, a])
        r2[j] = (dvec[j, 0] ** 2 + dvec[j, 1] ** 2 + dvec[j, 2] ** 2 - ell * ell) / (2.0 * ell)
    for i in range(n):
        for a in range(3):
            s = 0.0
            for j in range(n):
                s += H0[i, j] * p[j, a]
            g = dvec[i, a] * (mu[i] / ell)
            if i < n - 1:
                g -= dvec[i + 1, a] * (mu[i + 1] / ell)
            r1[i, a] = s + c[i, a] - g


@numba.njit(cache=True)
def _merit(r1, r2, m):
    """phi = |R1s / m|^2 + |R2s|^2 (non-finite: +inf)."""
    phi = 0.0
    for i in range(r1.shape[0]):
        for a in range(3):
            x = r1[i, a] / m[i]
            phi += x * x
        phi += r2[i] * r2[i]
    return phi if np.isfinite(phi) else np.inf


@lru_cache(maxsize=8)
def kkt_indices(n: int) -> tuple[np.ndarray, ...]:
    """Flat indices of the scaled KKT matrix (4N, 4N) of N links (read-only).

    Into K: the (N, N) scalar block for each coordinate (kron(Hs, I3)), order (c, i, j); the
    constraint rows Ghat (own point, previous point) and their transposes. Into an (N, N)
    matrix: the diagonal, the diagonal without its last entry, the sub- and superdiagonal.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    c = np.arange(3)
    rows = 3 * i[None] + c[:, None, None]
    cols = 3 * j[None] + c[:, None, None]
    jj = np.arange(n)[:, None]
    own_r, own_c = 3 * n + jj + 0 * c, 3 * jj + c  # (N, 3)
    prev_r, prev_c = 3 * n + jj[1:] + 0 * c, 3 * (jj[1:] - 1) + c  # (N-1, 3)
    d = np.arange(n)
    out = (
        (rows * 4 * n + cols).ravel(),
        (own_r * 4 * n + own_c).ravel(),
        (own_c * 4 * n + own_r).ravel(),
        (prev_r * 4 * n + prev_c).ravel(),
        (prev_c * 4 * n + prev_r).ravel(),
        d * n + d,
        d[:-1] * n + d[:-1],
        d[1:] * n + d[:-1],
        d[:-1] * n + d[1:],
    )
    for a in out:
        a.setflags(write=False)
    return out


@numba.njit(cache=True)
def kkt_into(p, mu, p_tip, H0, ell, K, dvec):
    """The scaled KKT matrix (4N, 4N) of ``_StepSolver.kkt`` into K, the link vectors into
    dvec (N, 3); K's other entries must be zero (they are never written)."""
    n = p.shape[0]
    for j in range(n):
        for a in range(3):
            dvec[j, a] = p[j, a] - (p_tip[a] if j == 0 else p[j - 1, a])
    for i in range(n):
        for j in range(n):
            h = H0[i, j]
            if i == j:
                h -= mu[i] / ell
                if i < n - 1:
                    h -= mu[i + 1] / ell
            elif i == j + 1:
                h += mu[i] / ell
            elif j == i + 1:
                h += mu[j] / ell
            for a in range(3):
                K[3 * i + a, 3 * j + a] = h
    for j in range(n):
        for a in range(3):
            g = dvec[j, a] / ell
            K[3 * n + j, 3 * j + a] = g
            K[3 * j + a, 3 * n + j] = -g
            if j > 0:
                K[3 * n + j, 3 * (j - 1) + a] = -g
                K[3 * (j - 1) + a, 3 * n + j] = g


@numba.njit(cache=True)
def newton_step(p, mu, c, p_tip, H0, m, ell, tol, max_iter, min_alpha):
    """Newton with backtracking on one model step, from the guess (p, mu).

    Iterates (p', mu') <- (p', mu') + alpha delta with K delta = -(R1s, R2s), alpha the first
    of 1, 1/2, ... with phi(alpha) <= (1 - 2e-4 alpha) phi(0), or ``min_alpha``; stops when
    max(|R1s_i| / m_i, |R2s_j|) <= tol [m].

    Args:
        p: Guess of the new positions, shape (N, 3) [m] (not modified).
        mu: Guess of the scaled multipliers, shape (N,) [m] (not modified).
        c: The step's constant part of R1s, shape (N, 3) [kg m].
        p_tip: Fingertip at the new step, shape (3,) [m].
        H0: diag(m) + (kappa + beta) Df^T Df, shape (N, N).
        m: Point masses, shape (N,) [kg].
        ell: Link length [m].
        tol: Tolerance on the scaled residuals [m].
        max_iter: Most Newton iterations.
        min_alpha: Smallest step fraction.

    Returns:
        (p', mu', iterations, status, residual): status :data:`CONVERGED`, :data:`NON_FINITE`
        or :data:`MAX_ITER`; a singular KKT matrix raises ``numpy.linalg.LinAlgError``.
    """
    n = p.shape[0]
    p = p.copy()
    mu = mu.copy()
    K = np.zeros((4 * n, 4 * n))
    dvec = np.empty((n, 3))
    r1, r2 = np.empty((n, 3)), np.empty(n)
    r1_t, r2_t = np.empty((n, 3)), np.empty(n)
    p_t, mu_t = np.empty((n, 3)), np.empty(n)
    rhs = np.empty(4 * n)
    _residual(p, mu, c, p_tip, H0, ell, r1, r2, dvec)
    phi = _merit(r1, r2, m)
    res = np.inf
    for it in range(max_iter + 1):
        res = 0.0
        for i in range(n):
            for a in range(3):
                x = abs(r1[i, a] / m[i])
                if not np.isfinite(x):
                    return p, mu, it, NON_FINITE, x
                res = max(res, x)
            if not np.isfinite(r2[i]):
                return p, mu, it, NON_FINITE, r2[i]
            res = max(res, abs(r2[i]))
        if res <= tol:
            return p, mu, it, CONVERGED, res
        if it == max_iter:
            break
        kkt_into(p, mu, p_tip, H0, ell, K, dvec)
        for i in range(n):
            for a in range(3):
                rhs[3 * i + a] = -r1[i, a]
            rhs[3 * n + i] = -r2[i]
        delta = np.linalg.solve(K, rhs)
        alpha = 1.0
        while True:
            for i in range(n):
                for a in range(3):
                    p_t[i, a] = p[i, a] + alpha * delta[3 * i + a]
                mu_t[i] = mu[i] + alpha * delta[3 * n + i]
            _residual(p_t, mu_t, c, p_tip, H0, ell, r1_t, r2_t, dvec)
            phi_t = _merit(r1_t, r2_t, m)
            if phi_t <= (1.0 - 2e-4 * alpha) * phi or alpha <= min_alpha:
                break
            alpha *= 0.5
        p[:] = p_t
        mu[:] = mu_t
        r1[:] = r1_t
        r2[:] = r2_t
        phi = phi_t
    return p, mu, max_iter, MAX_ITER, res


@numba.njit(cache=True)
def propagate_sensitivity(
    P, P_tip, MU, dA, dU_tip, dp, dv, m, DtD, DtDin, H0, ell, dt, beta, c_next, slot, out
):
    """Forward propagation of dx_k through each step's KKT system (``state_sensitivity``).

    For k = 0 .. K-1: K_{k+1} dz = -(r1, r2) with
    r1 = -M dp - dt M dv - beta DtD dp + DtDin (c_next dA_{k+1} - beta dA_k)
    + [i = 0] (mu_{k+1,0} / l) dtip_{k+1},  r2 = -[i = 0] (p_{k+1,0} - tip_{k+1}) . dtip_{k+1} / l,
    then dp' = dz[:3N], dv' = (dp' - dp) / dt.

    Args:
        P: Positions (K+1, N, 3) [m].
        P_tip: Fingertip (K+1, 3) [m].
        MU: Scaled multipliers (K+1, N) [m].
        dA: Input point derivatives (K+1, 2, 3, n_theta).
        dU_tip: Fingertip derivatives (K+1, 3, n_theta).
        dp: d p_0 / d theta (N, 3, n_theta) (overwritten).
        dv: d v_0 / d theta (N, 3, n_theta) (overwritten).
        m: Masses (N,) [kg].
        DtD: Df^T Df (N, N).
        DtDin: Df^T Din (N, 2).
        H0: diag(m) + (kappa + beta) DtD (N, N).
        ell: Link length [m].
        dt: Model step [s].
        beta: b dt / l^2.
        c_next: kappa + beta (kappa = k dt^2 / l^2).
        slot: Row of ``out`` for each step 0..K, or -1 (K+1,).
        out: dX rows (len(steps), 6N, n_theta), filled at the steps with a slot (step 0 not
            written here).
    """
    n, nth = P.shape[1], dp.shape[2]
    K = np.zeros((4 * n, 4 * n))
    dvec = np.empty((n, 3))
    rhs = np.empty((4 * n, nth))
    row = np.empty(nth)  # one rhs row, summed term by term in the order of the formula
    last = -1
    for k in range(slot.shape[0]):
        if slot[k] >= 0:
            last = k
    drive = np.empty((2, 3, nth))  # c_next dA_{k+1} - beta dA_k, the same for every row i
    for k in range(last):
        for b in range(2):
            for a in range(3):
                for t in range(nth):
                    drive[b, a, t] = c_next * dA[k + 1, b, a, t] - beta * dA[k, b, a, t]
        for i in range(n):
            for a in range(3):
                for t in range(nth):
                    row[t] = -m[i] * dp[i, a, t] - dt * m[i] * dv[i, a, t]
                for j in range(n):
                    w = beta * DtD[i, j]
                    for t in range(nth):
                        row[t] -= w * dp[j, a, t]
                for b in range(2):
                    for t in range(nth):
                        row[t] += DtDin[i, b] * drive[b, a, t]
                if i == 0:
                    w = MU[k + 1, 0] / ell
                    for t in range(nth):
                        row[t] += w * dU_tip[k + 1, a, t]
                for t in range(nth):
                    rhs[3 * i + a, t] = -row[t]
        for i in range(n):
            for t in range(nth):
                rhs[3 * n + i, t] = 0.0
        for t in range(nth):
            s = 0.0
            for a in range(3):
                s -= (P[k + 1, 0, a] - P_tip[k + 1, a]) / ell * dU_tip[k + 1, a, t]
            rhs[3 * n, t] = -s
        kkt_into(P[k + 1], MU[k + 1], P_tip[k + 1], H0, ell, K, dvec)
        dz = np.linalg.solve(K, rhs)
        for i in range(n):
            for a in range(3):
                for t in range(nth):
                    new = dz[3 * i + a, t]
                    dv[i, a, t] = (new - dp[i, a, t]) / dt
                    dp[i, a, t] = new
        r = slot[k + 1]
        if r >= 0:
            for i in range(n):
                for a in range(3):
                    for t in range(nth):
                        out[r, 3 * i + a, t] = dp[i, a, t]
                        out[r, 3 * n + 3 * i + a, t] = dv[i, a, t]

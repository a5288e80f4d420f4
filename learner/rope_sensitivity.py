"""Linearisation of the rope model by the implicit function theorem (paper eq. rope_ift).

Step k -> k+1 of :func:`learner.rope_model.rollout` solves R(z', x_k, u_k, u') = 0 for
z' = (p', mu') (v' = (p' - p_k) / dt is eliminated, mu = 2 l dt^2 lam is the scaled multiplier),
where x_k = (p_k, v_k) and u = (p_tip, d_tip). The step depends on u_k too, through the
backward-difference input velocities in the damping. The implicit function theorem gives, per step,

    dz' = -(dR/dz')^-1 (dR/dx_k dx_k + dR/du_k du_k + dR/du' du'),   dv' = (dp' - dp_k) / dt,

which, chained from dx_0, is the block-forward-substitution form of the paper's
dz~/du~ = -(df~/dz~)^-1 df~/du~ over the whole horizon. dR/dz' is the KKT matrix Newton used
(solved, never inverted). With R1s, R2s the scaled residuals of :mod:`learner.rope_model`:

    dR1s/dp_k = -(diag(m) + beta DtD),  dR1s/dv_k = -dt diag(m),
    dR1s/dA'  = (kappa + beta) Df^T Din,  dR1s/dA_k = -beta Df^T Din,
    dR1s/dp_tip' += (mu'_0 / l) I on point 1,  dR2s_0/dp_tip' = -(p'_1 - p_tip')^T / l,

with A = (p_tip - l d_tip, p_tip), kappa = k dt^2 / l^2, beta = b dt / l^2 (all kron I3).

The chain starts from dx_0: the rope at rest in its hanging equilibrium, whose derivative with
respect to the first fingertip pose is :func:`hanging_sensitivity` (the same theorem on the
static equilibrium).
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable

import numpy as np

from flyknot.errors import ConfigError
from learner.rope_kernel import kkt_into, propagate_sensitivity
from learner.rope_model import (
    RopeModelParams,
    RopeTrajectory,
    _ops,
    hanging_state,
    link_vectors,
    rollout,
)

N_INPUTS = 6  # d p_tip (3) [m], d d_tip (3) [unit]
COMPILED = True
"""Propagate with :func:`learner.rope_kernel.propagate_sensitivity` (False: the NumPy
reference, :func:`_propagate_numpy`)."""


def check_steps(steps: Iterable[int] | None, n_steps: int) -> list[int]:
    """Validate requested step indices (0..K); None means all."""
    if steps is None:
        return list(range(n_steps + 1))
    out = []
    for s in steps:
        if isinstance(s, bool) or not isinstance(s, numbers.Integral) or not 0 <= s <= n_steps:
            raise ConfigError("steps", f"must be integers in [0, {n_steps}], got {s!r}")
        out.append(int(s))
    if not out:
        raise ConfigError("steps", "must not be empty")
    return out


def _dU(dU: object, n_steps: int) -> np.ndarray:
    dU = np.asarray(dU, dtype=float)
    if dU.ndim != 3 or dU.shape[:2] != (n_steps + 1, N_INPUTS):
        raise ConfigError(
            "dU", f"must have shape ({n_steps + 1}, {N_INPUTS}, n_theta), got {dU.shape}"
        )
    if not np.all(np.isfinite(dU)):
        raise ConfigError("dU", "must be finite")
    return dU


def state_sensitivity(
    traj: RopeTrajectory,
    dU: np.ndarray,
    *,
    dx0: np.ndarray | None = None,
    steps: Iterable[int] | None = None,
) -> np.ndarray:
    """Derivatives of the states x_k = [p_k.ravel(), v_k.ravel()] w.r.t. parameters theta.

    Forward propagation of dx_k through each step's KKT system (see the module docstring).

    Args:
        traj: A converged rollout (its p, lam and inputs are the linearisation point).
        dU: Input derivatives d u_k / d theta, shape (K+1, 6, n_theta); rows 0-2 d p_tip [m],
            rows 3-5 d d_tip (the raw direction; no normalisation is applied).
        dx0: d x_0 / d theta, shape (6N, n_theta); default zero (initial state held fixed).
        steps: Step indices to return (0..K), default all.

    Returns:
        dX, shape (len(steps), 6N, n_theta) [m and m/s per unit theta].

    Raises:
        ConfigError: on malformed arguments.
    """
    if not isinstance(traj, RopeTrajectory):
        raise ConfigError("traj", f"must be a RopeTrajectory, got {type(traj).__name__}")
    params = traj.params
    K = traj.n_steps
    dU = _dU(dU, K)
    steps = check_steps(steps, K)
    n, ell, dt = params.n_links, params.link_length, params.dt
    nth = dU.shape[2]
    if dx0 is None:
        dx0 = np.zeros((6 * n, nth))
    dx0 = np.asarray(dx0, dtype=float)
    if dx0.shape != (6 * n, nth):
        raise ConfigError("dx0", f"must have shape ({6 * n}, {nth}), got {dx0.shape}")
    ops = _ops(params)
    # dA_k / dtheta, shape (K+1, 2, 3, n_theta): (dp_tip - l dd_tip, dp_tip).
    dA = np.ascontiguousarray(np.stack([dU[:, :3] - ell * dU[:, 3:], dU[:, :3]], axis=1))
    slot = np.full(K + 1, -1, dtype=np.int64)
    slot[np.asarray(steps)] = np.arange(len(steps))
    out = np.empty((len(steps), 6 * n, nth))
    if slot[0] >= 0:
        out[slot[0]] = dx0
    dp = dx0[: 3 * n].reshape(n, 3, nth).copy()
    dv = dx0[3 * n :].reshape(n, 3, nth).copy()
    propagate = propagate_sensitivity if COMPILED else _propagate_numpy
    propagate(
        np.ascontiguousarray(traj.p), np.ascontiguousarray(traj.p_tip),
        traj.lam * (2.0 * ell * dt**2), dA, np.ascontiguousarray(dU[:, :3]), dp, dv, ops.m,
        ops.DtD, ops.DtDin, ops.H0, ell, dt, ops.beta, ops.kappa + ops.beta, slot, out,
    )  # fmt: skip
    return out


def _propagate_numpy(
    P, P_tip, MU, dA, dU_tip, dp, dv, m, DtD, DtDin, H0, ell, dt, beta, c_next, slot, out
) -> None:
    """:func:`learner.rope_kernel.propagate_sensitivity` in NumPy (the reference)."""
    n, nth = P.shape[1], dp.shape[2]
    kkt, dvec = np.zeros((4 * n, 4 * n)), np.empty((n, 3))  # kkt_into's buffers
    mm = m[:, None, None]
    for k in range(int(np.flatnonzero(slot >= 0).max())):
        p1, tip1 = P[k + 1], P_tip[k + 1]
        r1 = (
            -mm * dp
            - dt * mm * dv
            - beta * (DtD @ dp.reshape(n, -1)).reshape(n, 3, nth)
            + (DtDin @ (c_next * dA[k + 1] - beta * dA[k]).reshape(2, -1)).reshape(n, 3, nth)
        )
        r1[0] += (MU[k + 1, 0] / ell) * dU_tip[k + 1]
        r2 = np.zeros((n, nth))
        r2[0] = -(link_vectors(p1, tip1)[0] / ell) @ dU_tip[k + 1]
        kkt_into(p1, MU[k + 1], tip1, H0, ell, kkt, dvec)
        dz = -np.linalg.solve(kkt, np.concatenate([r1.reshape(3 * n, nth), r2]))
        dp_new = dz[: 3 * n].reshape(n, 3, nth)
        dv = (dp_new - dp) / dt
        dp = dp_new
        if slot[k + 1] >= 0:
            out[slot[k + 1]] = np.concatenate([dp.reshape(3 * n, nth), dv.reshape(3 * n, nth)])


def fd_sensitivity(
    p_tip: np.ndarray,
    d_tip: np.ndarray,
    dU: np.ndarray,
    params: RopeModelParams | None = None,
    p0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
    *,
    eps: float = 1e-6,
    steps: Iterable[int] | None = None,
    tol: float = 1e-12,
) -> np.ndarray:
    """The same derivatives by central finite differences of :func:`rollout`.

    dX[:, :, j] = (x(u + eps dU_j) - x(u - eps dU_j)) / (2 eps), with the initial state held
    fixed (p0 default: the hanging equilibrium of the unperturbed u_0; v0 default zero).

    Args:
        p_tip: Fingertip positions, shape (K+1, 3) [m].
        d_tip: Tube directions, shape (K+1, 3) (unit).
        dU: Input directions, shape (K+1, 6, n_theta).
        params: Model parameters (default :class:`RopeModelParams()`).
        p0: Initial positions, shape (N, 3) [m].
        v0: Initial velocities, shape (N, 3) [m / s].
        eps: Step along each direction (> 0).
        steps: Step indices to return (0..K), default all.
        tol: Newton tolerance of the perturbed rollouts [m] (tight, so rounding does not
            dominate the difference quotient).

    Returns:
        dX, shape (len(steps), 6N, n_theta).
    """
    params = RopeModelParams() if params is None else params
    p_tip = np.asarray(p_tip, dtype=float)
    d_tip = np.asarray(d_tip, dtype=float)
    K = p_tip.shape[0] - 1
    dU = _dU(dU, K)
    steps = check_steps(steps, K)
    if not (isinstance(eps, numbers.Real) and 0 < eps < np.inf):
        raise ConfigError("eps", f"must be a finite number > 0, got {eps!r}")
    if p0 is None:
        p0, _ = hanging_state(p_tip[0], d_tip[0], params)
    out = np.empty((len(steps), 6 * params.n_links, dU.shape[2]))
    for j in range(dU.shape[2]):
        xs = []
        for sign in (1.0, -1.0):
            du = sign * eps * dU[:, :, j]
            tr = rollout(p_tip + du[:, :3], d_tip + du[:, 3:], params, p0, v0, tol=tol)
            xs.append(tr.x[steps])
        out[:, :, j] = (xs[0] - xs[1]) / (2.0 * eps)
    return out


# --------------------------------------------------------------------------------------------
# the initial hanging state
# --------------------------------------------------------------------------------------------


def _static_multipliers(
    p: np.ndarray, p_tip: np.ndarray, d_tip: np.ndarray, params: RopeModelParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Multipliers of the static equilibrium and the pieces of its residual.

    F(p, lam; u) = -(k / l^2) Df^T (Din A + Df p) + M g_vec + G(p, p_tip)^T lam = 0, with
    (G^T lam)_i = 2 lam_i d_i - 2 lam_{i+1} d_{i+1}, d_i = p_i - p_{i-1} (p_0 := p_tip).
    lam is the least-squares solution of F = 0 (exact at the equilibrium).

    Returns:
        lam (N,) [N/m], G^T as a (3N, N) matrix [m], d (N, 3) link vectors [m].
    """
    ops = _ops(params)
    n, ell = params.n_links, params.link_length
    A = np.stack([p_tip - ell * d_tip, p_tip])
    e = ops.Din @ A + ops.Df @ p
    gvec = np.array([0.0, 0.0, -params.gravity])
    c = -(params.stiffness / ell**2) * (ops.Df.T @ e) + ops.m[:, None] * gvec  # (N, 3)
    d = link_vectors(p, p_tip)
    GT = np.zeros((3 * n, n))
    for i in range(n):
        GT[3 * i : 3 * i + 3, i] = 2.0 * d[i]
        if i > 0:
            GT[3 * (i - 1) : 3 * i, i] = -2.0 * d[i]
    lam, *_ = np.linalg.lstsq(GT, -c.ravel(), rcond=None)
    return lam, GT, d


def hanging_sensitivity(
    p: np.ndarray, p_tip: np.ndarray, d_tip: np.ndarray, params: RopeModelParams
) -> np.ndarray:
    """Derivative of the hanging equilibrium with respect to the fingertip pose.

    The equilibrium (p, lam) solves F(p, lam; u) = 0, g(p, p_tip) = 0 with u = (p_tip, d_tip),
    F as in :func:`_static_multipliers` and g_i = |d_i|^2 - l^2. The implicit function theorem:

        [dF/dp  G^T] [dp  ]     [dF/du]
        [G      0  ] [dlam] = - [dg/du] du,

        dF/dp = -(k / l^2) kron(Df^T Df, I3) + kron(L(2 lam), I3)
        dF/dp_tip = -(k / l^2) kron(Df^T Din 1, I3) - 2 lam_1 E_1,
        dF/dd_tip = (k / l) kron(Df^T Din e_1, I3),   dg_1/dp_tip = -2 d_1^T,

    with L(w) the Laplacian of the links weighted by w (the tip link only on the diagonal) and
    E_1 selecting point 1. Because the model is translation invariant, dp_i/dp_tip = I_3.

    Args:
        p: Equilibrium positions, shape (N, 3) [m] (from
            :func:`learner.system_model.initial_state`).
        p_tip: Fingertip, shape (3,) [m].
        d_tip: Tube direction, shape (3,) (unit).
        params: Rope model parameters.

    Returns:
        dp / du, shape (3N, 6): columns 0-2 per metre of p_tip, 3-5 per unit of d_tip.
    """
    p = np.asarray(p, dtype=float)
    p_tip = np.asarray(p_tip, dtype=float)
    d_tip = np.asarray(d_tip, dtype=float)
    ops = _ops(params)
    n, ell = params.n_links, params.link_length
    kl2 = params.stiffness / ell**2
    lam, GT, d = _static_multipliers(p, p_tip, d_tip, params)
    w = 2.0 * lam
    L = np.diag(w.copy())
    L[np.arange(n - 1), np.arange(n - 1)] += w[1:]
    L[np.arange(1, n), np.arange(n - 1)] -= w[1:]
    L[np.arange(n - 1), np.arange(1, n)] -= w[1:]
    eye3 = np.eye(3)
    Fp = np.kron(-kl2 * ops.DtD + L, eye3)
    kkt = np.zeros((4 * n, 4 * n))
    kkt[: 3 * n, : 3 * n] = Fp
    kkt[: 3 * n, 3 * n :] = GT
    kkt[3 * n :, : 3 * n] = GT.T
    rhs = np.zeros((4 * n, 6))
    # Bending: dA = (dp_tip - l dd, dp_tip); dF = -(k / l^2) DtDin dA.
    rhs[: 3 * n, :3] = np.kron(-kl2 * (ops.DtDin[:, :1] + ops.DtDin[:, 1:]), eye3)
    rhs[: 3 * n, 3:] = np.kron(kl2 * ell * ops.DtDin[:, :1], eye3)
    rhs[:3, :3] -= w[0] * eye3
    rhs[3 * n, :3] = -2.0 * d[0]
    return -np.linalg.solve(kkt, rhs)[: 3 * n]

"""The paper's simplified rope: N point masses on fixed-length links, driven at the fingertip.

Paper, section "Rope Model" and appendix "Rope Dynamics Model". The paper's parameters are
"relative to m = 1"; we read them as SI with the link mass m = 1 kg (for a real link mass m_r,
scale masses, forces, energies, k and b by m_r / 1 kg; the motion is unchanged).

Geometry. Point i = 1..N (array row i - 1) sits i * l from the fingertip along the rope, so with
l = 0.1 and N = 11 the points are the 11 mocap markers at 0.1 .. 1.1 m. The fingertip p_tip (3,)
[m] and the tube direction d_tip (3,) (unit, pointing from the tube out along the rope) are
inputs. A virtual point p_v = p_tip - l d_tip sits behind the fingertip so that the joint at the
fingertip bends too. Extended points P = (p_v, p_tip, p_1, ..., p_N).

Bending (our choice; the paper does not print its form). Discrete second differences

    e_j = P_{j+2} - 2 P_{j+1} + P_j,  j = 0 .. N-1   (joint at the fingertip, then points 1..N-1)
    E_bend = (k / (2 l^2)) sum_j |e_j|^2   [J]

On the constraint manifold |e_j|^2 = 2 l^2 (1 - cos theta_j) for the joint angle theta_j, so
E_bend = k sum_j (1 - cos theta_j) ~ (k/2) sum_j theta_j^2: k is the joint's angular stiffness.
E_bend is linear-quadratic in the positions, invariant to rigid motions of (P, d_tip), and zero
for a straight rope along d_tip. Damping is the matching Rayleigh dissipation

    D = (b / (2 l^2)) sum_j |e_dot_j|^2,  e_dot_j = V_{j+2} - 2 V_{j+1} + V_j,

with the input velocities (of p_tip and p_v) taken as backward differences over the step.
Forces on the free points: f = -(k/l^2) D_f^T e - (b/l^2) D_f^T e_dot + m_i g_vec, where
e = D_in (p_v, p_tip) + D_f p. The last point carries the end mass m_e; the others m = 1.

Step (paper eq. rope_vi_pos/dyn/con, backward Euler with the constraints at the new step):

    p' = p + dt v',
    M (v' - v) = dt f(p', v') + dt G(p', p_tip')^T lam',
    g_j(p', p_tip') = |p'_j - p'_{j-1}|^2 - l^2 = 0  (p'_0 := p_tip'),

solved for (p', lam') by Newton on the KKT system after eliminating v' = (p' - p) / dt. The solver
works on the residual scaled by dt^2 and the constraints divided by 2 l, so both residuals are in
metres, with mu = 2 l dt^2 lam as the internal multiplier.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from flyknot.constants import GRAVITY, MARKER_SPACING, MODEL_DT, N_MARKERS
from flyknot.errors import ConfigError, SolverError, check_nonnegative, check_positive
from flyknot.geometry import readonly
from learner.rope_kernel import CONVERGED, kkt_indices, newton_step

NEWTON_TOL = 1e-10  # [m], scaled residuals (see module docstring)
NEWTON_MAX_ITER = 25
UNIT_TOL = 1e-3  # allowed | |d_tip| - 1 |
_SOLVER = "rope Newton"
_MIN_ALPHA = 1.0 / 64.0  # smallest Newton step fraction of the backtracking line search
_HANG_H_MAX = 10.0  # [s] largest pseudo-time step of hanging_state


@dataclass(frozen=True)
class RopeModelParams:
    """Parameters of the simplified rope (paper table "simulation_params").

    Attributes:
        stiffness: Bending stiffness k per joint [N m / rad], >= 0.
        damping: Bending damping b per joint [N m s / rad], >= 0.
        link_mass: Mass m of points 1..N-1 [kg] (the paper's unit of mass), > 0.
        end_mass: Mass m_e of the last point [kg], > 0.
        link_length: Link length l [m], > 0.
        n_links: Number N of links and point masses, >= 1.
        dt: Time step [s], > 0.
        gravity: Gravity acceleration along -z [m / s^2], >= 0.

    Note: read in our bending form, the paper's k = 1e5 makes the rope nearly rigid. Measured
    with :func:`hanging_state`, a rope held by a horizontal tube droops at its end by 0.004 m
    (k = 1e5), 0.044 m (1e4), 0.39 m (1e3), 0.98 m (100), 1.09 m (10). The paper does not print
    its bending form, so its k may be in other units; the default keeps the paper's number.
    """

    stiffness: float = 1e5
    damping: float = 50.0
    link_mass: float = 1.0
    end_mass: float = 5.0
    link_length: float = MARKER_SPACING
    n_links: int = N_MARKERS
    dt: float = MODEL_DT
    gravity: float = GRAVITY

    def __post_init__(self) -> None:
        for name in ("stiffness", "damping", "gravity"):
            value = getattr(self, name)
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                value = float(value)
            check_nonnegative(name, value)
            object.__setattr__(self, name, value)
        for name in ("link_mass", "end_mass", "link_length", "dt"):
            value = getattr(self, name)
            if isinstance(value, numbers.Real) and not isinstance(value, bool):
                value = float(value)
            check_positive(name, value)
            object.__setattr__(self, name, value)
        n = self.n_links
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
            raise ConfigError("n_links", f"must be an integer >= 1, got {n!r}")
        object.__setattr__(self, "n_links", int(n))

    @property
    def masses(self) -> np.ndarray:
        """Point masses (m, ..., m, m_e), shape (N,) [kg]."""
        m = np.full(self.n_links, self.link_mass)
        m[-1] = self.end_mass
        return m


@dataclass(frozen=True)
class _Ops:
    """Constant matrices of one parameter set (scalar N x N; the 3-D versions are kron(., I3))."""

    m: np.ndarray  # (N,) masses
    Df: np.ndarray  # (N, N) second differences of the free points
    Din: np.ndarray  # (N, 2) second differences of (p_v, p_tip)
    DtD: np.ndarray  # (N, N) Df^T Df
    DtDin: np.ndarray  # (N, 2) Df^T Din
    kappa: float  # k dt^2 / l^2
    beta: float  # b dt / l^2
    H0: np.ndarray  # (N, N) diag(m) + (kappa + beta) DtD


@lru_cache(maxsize=32)
def _ops(params: RopeModelParams) -> _Ops:
    n = params.n_links
    ell = params.link_length
    # D_ext (N, N + 2): row j is P_{j+2} - 2 P_{j+1} + P_j over P = (p_v, p_tip, p_1..p_N).
    D = np.zeros((n, n + 2))
    for j in range(n):
        D[j, j : j + 3] = (1.0, -2.0, 1.0)
    Din, Df = D[:, :2].copy(), D[:, 2:].copy()
    kappa = params.stiffness * params.dt**2 / ell**2
    beta = params.damping * params.dt / ell**2
    m = params.masses
    DtD = Df.T @ Df
    ops = _Ops(
        m=m,
        Df=Df,
        Din=Din,
        DtD=DtD,
        DtDin=Df.T @ Din,
        kappa=kappa,
        beta=beta,
        H0=np.diag(m) + (kappa + beta) * DtD,
    )
    for a in (ops.m, ops.Df, ops.Din, ops.DtD, ops.DtDin, ops.H0):
        a.setflags(write=False)
    return ops


def _check_params(params: object) -> RopeModelParams:
    if not isinstance(params, RopeModelParams):
        raise ConfigError("params", f"must be a RopeModelParams, got {type(params).__name__}")
    return params


def _inputs(p_tip: object, d_tip: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate driving inputs, shapes (K+1, 3) [m] and (K+1, 3) [unit], or (3,) each."""
    p = np.asarray(p_tip, dtype=float)
    d = np.asarray(d_tip, dtype=float)
    if p.ndim not in (1, 2) or p.shape[-1] != 3:
        raise ConfigError("p_tip", f"must have shape (K+1, 3) or (3,), got {p.shape}")
    if d.shape != p.shape:
        raise ConfigError("d_tip", f"must have the shape of p_tip {p.shape}, got {d.shape}")
    for name, a in (("p_tip", p), ("d_tip", d)):
        if not np.all(np.isfinite(a)):
            raise ConfigError(name, "must be finite")
    norm = np.linalg.norm(d, axis=-1)
    if np.any(np.abs(norm - 1.0) > UNIT_TOL):
        raise ConfigError(
            "d_tip",
            f"must be unit vectors (within {UNIT_TOL:g}), got norms in "
            f"[{norm.min():.6g}, {norm.max():.6g}]",
        )
    return p, d


def _anchor(p_tip: np.ndarray, d_tip: np.ndarray, ell: float) -> np.ndarray:
    """Input points A = (p_v, p_tip) = (p_tip - l d_tip, p_tip), shape (..., 2, 3) [m]."""
    return np.stack([p_tip - ell * d_tip, p_tip], axis=-2)


def link_vectors(p: np.ndarray, p_tip: np.ndarray) -> np.ndarray:
    """Link vectors p_j - p_{j-1} with p_0 := p_tip, shape (N, 3) [m] for p (N, 3), p_tip (3,)."""
    p = np.asarray(p, dtype=float)
    return p - np.vstack([np.asarray(p_tip, dtype=float)[None], p[:-1]])


def constraints(p: np.ndarray, p_tip: np.ndarray, params: RopeModelParams) -> np.ndarray:
    """Distance constraints g_j = |p_j - p_{j-1}|^2 - l^2 (p_0 := p_tip), shape (N,) [m^2]."""
    d = link_vectors(p, p_tip)
    return np.einsum("ij,ij->i", d, d) - params.link_length**2


def bending_energy(
    p: np.ndarray, p_tip: np.ndarray, d_tip: np.ndarray, params: RopeModelParams
) -> float:
    """E_bend = (k / (2 l^2)) sum_{j=0}^{N-1} |P_{j+2} - 2 P_{j+1} + P_j|^2  [J].

    Args:
        p: Points, shape (N, 3) [m].
        p_tip: Fingertip, shape (3,) [m].
        d_tip: Tube direction, shape (3,) (unit).
        params: Model parameters.
    """
    params = _check_params(params)
    ops = _ops(params)
    A = _anchor(np.asarray(p_tip, float), np.asarray(d_tip, float), params.link_length)
    e = ops.Din @ A + ops.Df @ np.asarray(p, dtype=float)
    return float(0.5 * params.stiffness / params.link_length**2 * np.sum(e * e))


def rope_energy(
    p: np.ndarray,
    v: np.ndarray,
    p_tip: np.ndarray,
    d_tip: np.ndarray,
    params: RopeModelParams,
) -> float:
    """Total energy E = sum_i m_i |v_i|^2 / 2 + sum_i m_i g z_i + E_bend  [J].

    Args:
        p: Points, shape (N, 3) [m].
        v: Velocities, shape (N, 3) [m / s].
        p_tip: Fingertip, shape (3,) [m].
        d_tip: Tube direction, shape (3,) (unit).
        params: Model parameters.
    """
    m = params.masses
    v = np.asarray(v, dtype=float)
    p = np.asarray(p, dtype=float)
    kinetic = 0.5 * float(np.sum(m * np.einsum("ij,ij->i", v, v)))
    potential = float(np.sum(m * params.gravity * p[:, 2]))
    return kinetic + potential + bending_energy(p, p_tip, d_tip, params)


class _StepSolver:
    """Newton on the scaled KKT system of one step; keeps work arrays between steps."""

    compiled = True  # False: NumPy alone (the reference of tests/test_rope_kernel.py)

    def __init__(self, params: RopeModelParams, tol: float, max_iter: int):
        self.params = params
        self.ops = _ops(params)
        self.tol = tol
        self.max_iter = max_iter
        ops = self.ops
        self.kernel_args = (ops.H0, ops.m, params.link_length, tol, max_iter, _MIN_ALPHA)
        n = params.n_links
        self.n = n
        self.K = np.zeros((4 * n, 4 * n))
        self.gvec = np.array([0.0, 0.0, -params.gravity])
        m = ops.m[:, None]
        self._neg_m = -m  # the constant's terms that do not change from step to step
        self._gravity_term = params.dt**2 * m * self.gvec  # dt^2 M g_vec (N, 3)
        (
            self.idx_H,
            self.idx_G_own,
            self.idx_GT_own,
            self.idx_G_prev,
            self.idx_GT_prev,
            self.diag,
            self.diag_prev,
            self.low,
            self.up,
        ) = kkt_indices(n)

    def kkt(self, p: np.ndarray, mu: np.ndarray, p_tip: np.ndarray) -> np.ndarray:
        """Scaled KKT matrix d(R1s, R2s)/d(p', mu'), shape (4N, 4N), at (p', mu', p_tip').

        R1s = H0 p' + c - Ghat^T mu,  R2s = (|p'_j - p'_{j-1}|^2 - l^2) / (2 l),
        Ghat = G / (2 l);  dR1s/dp' = H0 - (1/l) L(mu) (kron I3), dR1s/dmu = -Ghat^T,
        dR2s/dp' = Ghat, with L(mu) the graph Laplacian of the links weighted by mu (the tip
        link only on the diagonal). The returned array is a work buffer, overwritten by the
        next call.
        """
        ell, K = self.params.link_length, self.K
        dvec = link_vectors(p, p_tip)
        Hs = self.ops.H0.ravel().copy()
        w = mu / ell
        Hs[self.diag] -= w
        Hs[self.diag_prev] -= w[1:]
        Hs[self.low] += w[1:]
        Hs[self.up] += w[1:]
        K.flat[self.idx_H] = np.tile(Hs, 3)
        g_own = (dvec / ell).ravel()
        g_prev = (-dvec[1:] / ell).ravel()
        K.flat[self.idx_G_own] = g_own
        K.flat[self.idx_GT_own] = -g_own
        K.flat[self.idx_G_prev] = g_prev
        K.flat[self.idx_GT_prev] = -g_prev
        return K

    def constant(
        self, p_k: np.ndarray, v_k: np.ndarray, A_k: np.ndarray, A_next: np.ndarray
    ) -> np.ndarray:
        """The part of R1s that does not depend on (p', mu'), shape (N, 3) [kg m].

        c = -M (p_k + dt v_k) + kappa Df^T Din A' + beta (Df^T Din (A' - A_k) - Df^T Df p_k)
            - dt^2 M g_vec,
        with A = (p_tip - l d_tip, p_tip) (2, 3) [m], kappa = k dt^2 / l^2, beta = b dt / l^2.
        """
        ops, dt = self.ops, self.params.dt
        return (
            self._neg_m * (p_k + dt * v_k)
            + ops.kappa * (ops.DtDin @ A_next)
            + ops.beta * (ops.DtDin @ (A_next - A_k) - ops.DtD @ p_k)
            - self._gravity_term
        )

    def residual(
        self, p: np.ndarray, mu: np.ndarray, c: np.ndarray, p_tip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Scaled step residuals at (p', mu').

        R1s = dt^2 (M (v' - v_k) / dt - f(p', v') - G^T lam')
            = H0 p' + c - Ghat^T mu',  shape (N, 3) [kg m]
        R2s = g(p', p_tip') / (2 l),  shape (N,) [m]
        """
        ell = self.params.link_length
        dvec = link_vectors(p, p_tip)
        r2 = (np.einsum("ij,ij->i", dvec, dvec) - ell * ell) / (2 * ell)
        gmu = dvec * (mu / ell)[:, None]
        gmu[:-1] -= dvec[1:] * (mu[1:] / ell)[:, None]
        return self.ops.H0 @ p + c - gmu, r2

    def solve(
        self,
        k: int,
        p_k: np.ndarray,
        v_k: np.ndarray,
        A_k: np.ndarray,
        A_next: np.ndarray,
        mu0: np.ndarray,
        p_guess: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """One step from (p_k, v_k) with inputs A_k -> A_next; returns (p', mu', iterations).

        Converged when max(|R1s_i| / m_i, |R2s|) <= tol [m]. With ``compiled`` the iteration
        is :func:`learner.rope_kernel.newton_step`; a step it cannot finish is run again in
        NumPy (the reference), which raises the :class:`SolverError` naming the failure.
        """
        p = p_k + self.params.dt * v_k if p_guess is None else p_guess
        c = self.constant(p_k, v_k, A_k, A_next)
        p, mu, tip = (np.ascontiguousarray(a, dtype=float) for a in (p, mu0, A_next[1]))
        if self.compiled:
            try:
                out = newton_step(p, mu, c, tip, *self.kernel_args)
            except np.linalg.LinAlgError:
                out = None
            if out is not None and out[3] == CONVERGED:
                return out[0], out[1], int(out[2])
        return self._solve_numpy(k, c, p, mu, tip)

    def _solve_numpy(
        self, k: int, c: np.ndarray, p: np.ndarray, mu0: np.ndarray, p_tip: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Newton in NumPy from the guess (p, mu0), with the step's constant c."""
        n, m = self.n, self.ops.m[:, None]
        mu = mu0.copy()
        res = np.inf
        r1, r2 = self.residual(p, mu, c, p_tip)
        phi = _merit(r1 / m, r2)
        for it in range(self.max_iter + 1):
            res = max(np.max(np.abs(r1 / m)), np.max(np.abs(r2)))
            if not np.isfinite(res):
                raise SolverError(_SOLVER, "non-finite", f"step {k}, iteration {it}")
            if res <= self.tol:
                return p, mu, it
            if it == self.max_iter:
                break
            K = self.kkt(p, mu, p_tip)
            try:
                delta = np.linalg.solve(K, -np.concatenate([r1.ravel(), r2]))
            except np.linalg.LinAlgError as e:
                raise SolverError(_SOLVER, "singular", f"step {k}, iteration {it}: {e}") from e
            dp, dmu = delta[: 3 * n].reshape(n, 3), delta[3 * n :]
            # Backtracking on phi = |r|^2 (the Newton direction descends it): accept the first
            # alpha in 1, 1/2, ... with phi(alpha) <= (1 - 2e-4 alpha) phi(0), or alpha = 1/64.
            alpha = 1.0
            while True:
                p_t, mu_t = p + alpha * dp, mu + alpha * dmu
                r1_t, r2_t = self.residual(p_t, mu_t, c, p_tip)
                phi_t = _merit(r1_t / m, r2_t)
                if phi_t <= (1.0 - 2e-4 * alpha) * phi or alpha <= _MIN_ALPHA:
                    break
                alpha *= 0.5
            p, mu, r1, r2, phi = p_t, mu_t, r1_t, r2_t, phi_t
        raise SolverError(
            _SOLVER,
            "max_iter",
            f"step {k}: residual {res:.3g} m > tol {self.tol:g} m after {self.max_iter} iterations",
        )


def _merit(a: np.ndarray, b: np.ndarray) -> float:
    """phi = |a|^2 + |b|^2 (NaN-safe: non-finite counts as +inf)."""
    phi = float(np.sum(a * a) + np.sum(b * b))
    return phi if np.isfinite(phi) else np.inf


def _solver_options(tol: float, max_iter: int) -> None:
    check_positive("tol", float(tol))
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 1:
        raise ConfigError("max_iter", f"must be an integer >= 1, got {max_iter!r}")


@lru_cache(maxsize=64)
def _with_dt(params: RopeModelParams, dt: float) -> RopeModelParams:
    """``params`` with the step dt [s] (cached: :func:`hanging_state`'s pseudo-time steps)."""
    return dataclasses.replace(params, dt=dt)


def hanging_state(
    p_tip: np.ndarray,
    d_tip: np.ndarray,
    params: RopeModelParams,
    *,
    tol: float = 1e-10,
    max_steps: int = 400,
) -> tuple[np.ndarray, np.ndarray]:
    """Static equilibrium of the rope held at (p_tip, d_tip): min E_grav + E_bend s.t. g = 0.

    Starts from the straight rope along d_tip (p_i = p_tip + i l d_tip) and runs pseudo-time
    steps from rest, p_{j+1} = argmin E(p) + |p - p_j|_M^2 / (2 h_j^2) s.t. g(p) = 0 (the model's
    step with v = 0), with h_j = dt 2^j capped at 1e3 s, until |p_{j+1} - p_j|_inf <= tol. For
    d_tip = -z the straight rope is the equilibrium and is returned unchanged.

    Args:
        p_tip: Fingertip, shape (3,) [m].
        d_tip: Tube direction, shape (3,) (unit).
        params: Model parameters.
        tol: Convergence tolerance on the position change [m].
        max_steps: Most pseudo-time steps.

    Returns:
        (p, v): positions (N, 3) [m] and zero velocities (N, 3) [m / s].

    Raises:
        SolverError: if the equilibrium is not reached in ``max_steps`` steps.
    """
    params = _check_params(params)
    p_tip, d_tip = _inputs(p_tip, d_tip)
    if p_tip.shape != (3,):
        raise ConfigError("p_tip", f"must have shape (3,), got {p_tip.shape}")
    _solver_options(tol, max_steps)
    d_tip = d_tip / np.linalg.norm(d_tip)
    n, ell = params.n_links, params.link_length
    p = p_tip + ell * np.arange(1, n + 1)[:, None] * d_tip
    A = _anchor(p_tip, d_tip, ell)
    mu_scaled = np.zeros(n)  # lam * 2 l (dt-free), rescaled for each pseudo step
    zeros = np.zeros((n, 3))
    for j in range(max_steps):
        h = min(params.dt * 2.0**j, _HANG_H_MAX)
        # The scaled residual grows with h^2 (and so does its rounding): loosen Newton alike.
        newton_tol = NEWTON_TOL * max(1.0, (h / params.dt) ** 2)
        solver = _StepSolver(_with_dt(params, h), newton_tol, NEWTON_MAX_ITER)
        p_new, mu, _ = solver.solve(j, p, zeros, A, A, mu_scaled * h**2)
        mu_scaled = mu / h**2
        change = np.max(np.abs(p_new - p))
        p = p_new
        if change <= tol:
            return p, zeros.copy()
    raise SolverError(
        "rope hanging_state", "max_steps", f"position still changing by {change:.3g} m"
    )


@dataclass(frozen=True)
class RopeTrajectory:
    """A rollout of the rope model.

    Attributes:
        p: Positions, shape (K+1, N, 3) [m].
        v: Velocities, shape (K+1, N, 3) [m / s].
        lam: Constraint multipliers, shape (K+1, N) [N / m]; lam[0] = 0 as in the paper; the
            constraint force on the points is G^T lam (negative lam = tension).
        iterations: Newton iterations of each step, shape (K,).
        p_tip: Fingertip inputs, shape (K+1, 3) [m].
        d_tip: Tube-direction inputs, shape (K+1, 3) (unit).
        params: The model parameters used.
    """

    p: np.ndarray
    v: np.ndarray
    lam: np.ndarray
    iterations: np.ndarray
    p_tip: np.ndarray
    d_tip: np.ndarray
    params: RopeModelParams

    def __post_init__(self) -> None:
        for name in ("p", "v", "lam", "p_tip", "d_tip"):
            object.__setattr__(self, name, readonly(getattr(self, name)))
        it = np.array(self.iterations, dtype=int, copy=True)
        it.setflags(write=False)
        object.__setattr__(self, "iterations", it)

    @property
    def n_steps(self) -> int:
        """Number K of steps."""
        return int(self.p.shape[0] - 1)

    @property
    def t(self) -> np.ndarray:
        """Times k dt, shape (K+1,) [s]."""
        return np.arange(self.p.shape[0]) * self.params.dt

    @property
    def x(self) -> np.ndarray:
        """States x_k = [p_k.ravel(), v_k.ravel()], shape (K+1, 6N)."""
        k1 = self.p.shape[0]
        return np.concatenate([self.p.reshape(k1, -1), self.v.reshape(k1, -1)], axis=1)


def rollout(
    p_tip: np.ndarray,
    d_tip: np.ndarray,
    params: RopeModelParams | None = None,
    p0: np.ndarray | None = None,
    v0: np.ndarray | None = None,
    *,
    tol: float = NEWTON_TOL,
    max_iter: int = NEWTON_MAX_ITER,
) -> RopeTrajectory:
    """Simulate the rope driven by a fingertip trajectory sampled every dt.

    Each step solves p' = p + dt v', M (v' - v) = dt f(p', v') + dt G^T lam', g(p', p_tip') = 0
    by Newton with a backtracking line search on the squared residual (see the module
    docstring), from the guess p' = p + dt (2 v - v_prev), lam' = lam, and again from
    p' = p + dt v if that fails. A step that suddenly compresses the rope hard (fingertip
    accelerations of ~1000 m/s^2 from rest) can have no nearby solution and then fails.

    Args:
        p_tip: Fingertip positions at t = k dt, shape (K+1, 3) [m].
        d_tip: Tube directions, shape (K+1, 3) (unit).
        params: Model parameters (default :class:`RopeModelParams()`).
        p0: Initial positions, shape (N, 3) [m]; default the hanging equilibrium at step 0.
        v0: Initial velocities, shape (N, 3) [m / s]; default zero.
        tol: Newton tolerance on the scaled residuals [m].
        max_iter: Most Newton iterations per step.

    Returns:
        The :class:`RopeTrajectory`.

    Raises:
        ConfigError: on malformed inputs.
        SolverError: if Newton fails (status "max_iter", "singular" or "non-finite").
    """
    params = RopeModelParams() if params is None else _check_params(params)
    p_tip, d_tip = _inputs(p_tip, d_tip)
    if p_tip.ndim != 2:
        raise ConfigError("p_tip", f"must have shape (K+1, 3), got {p_tip.shape}")
    _solver_options(tol, max_iter)
    n, ell, dt = params.n_links, params.link_length, params.dt
    mu_init = np.zeros(n)
    if p0 is None:
        p0, _ = hanging_state(p_tip[0], d_tip[0], params)
        mu_init = -params.gravity * dt**2 * np.cumsum(params.masses[::-1])[::-1]
    p0 = np.asarray(p0, dtype=float)
    v0 = np.zeros((n, 3)) if v0 is None else np.asarray(v0, dtype=float)
    for name, a in (("p0", p0), ("v0", v0)):
        if a.shape != (n, 3):
            raise ConfigError(name, f"must have shape ({n}, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ConfigError(name, "must be finite")
    K = p_tip.shape[0] - 1
    A = _anchor(p_tip, d_tip, ell)
    P = np.empty((K + 1, n, 3))
    V = np.empty((K + 1, n, 3))
    lam = np.zeros((K + 1, n))
    iters = np.zeros(K, dtype=int)
    P[0], V[0] = p0, v0
    solver = _StepSolver(params, tol, max_iter)
    mu = mu_init
    for k in range(K):
        # Predictor: constant acceleration (second-order extrapolation) after the first step.
        guess = None if k == 0 else P[k] + dt * (2.0 * V[k] - V[k - 1])
        try:
            p_new, mu, iters[k] = solver.solve(k, P[k], V[k], A[k], A[k + 1], mu, guess)
        except SolverError:
            if guess is None:
                raise
            # Retry from the first-order guess (helps when the rope is suddenly compressed).
            p_new, mu, iters[k] = solver.solve(k, P[k], V[k], A[k], A[k + 1], mu)
        P[k + 1] = p_new
        V[k + 1] = (p_new - P[k]) / dt
        lam[k + 1] = mu / (2 * ell * dt**2)
    return RopeTrajectory(P, V, lam, iters, p_tip, d_tip, params)

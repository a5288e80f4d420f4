"""The initial-guess NLP: trajectory optimisation tracking the demonstration hand, built only.

Paper, section "Initial Guess" (eq. ik_trajopt) and appendix "Demonstration Tracking". With the
command q(t) = B(kappa, T)(t) (``learner.bezier``) and the fingertip kinematics of the robot
model (``learner.kinematics``, all in the robot base frame), solve over the arm knots and the
base offset b (3,) [m]::

    min   sum_i ||e_h(t_i)||^2_{W_h} + w_j sum_i ||q'''(t_i)||^2
    e_h = [p_tip(t_i) + b - p_h(t_i);  r(R_h(t_i)^T R_tip(t_i));  pdot_tip(t_i) - pdot_h(t_i)]
    W_h = diag(w_p I3, w_R I3, w_v I3)
    s.t.  q_min + dq <= q(t_l) <= q_max - dq          (dq = POSITION_MARGIN [rad])
          |qd_c(t_l)|  <= (1 - limit_margin) qd_max      (qd_c, qdd_c: the controllers'
          |qdd_c(t_l)| <= (1 - limit_margin) qdd_max      central differences, below)
          |tau(t_l)| <= (1 - limit_margin) tau_max    (optional, default on; see below)
          qd(0) = qd(T) = 0                           (exact, by construction)
          z_tip(q(0)) + b_z >= z_min

Frames. The demonstration frame (motion capture, z up, floor at z = 0) and the robot base frame
are taken as parallel; the base offset b is the robot base's position in the demonstration frame
(knot rows 7-9, constant across the knots). ``demo_hand_R`` must already be the *desired
fingertip orientation* in the fingertip site's convention (columns = tip axes in the demo frame,
the rope leaving along column 2); a hand frame with another convention is converted by the
caller (e.g. a hand that is the identity with the rope hanging down is ``R_hand @ Rx(pi)``, since
the xArm's fingertip at home is ``Rx(pi)``). z_min is the fingertip height above the demo
frame's floor at the start, so the 1.1 m rope hangs clear.

Decision variable (45,). The end conditions qd(0) = 7 (k_1 - k_0) / T = 0 and
qd(T) = 7 (k_7 - k_6) / T = 0 are built in by tying k_1 = k_0 and k_6 = k_7: per joint six free
columns c = (k_0, k_2, k_3, k_4, k_5, k_7) with ``kappa_arm = C E`` (E (6, 8) of 0/1), so the
end knots are equal bitwise: 7 (k_1 - k_0) / T is exactly 0.0 (evaluating the whole basis
product adds only rounding, ~1e-15, where BLAS fuses multiply-adds). x holds C (7, 6) row-major
(joint j, free column c at 6 j + c), then b (3,).

Rotation residual. The paper's Log(R_h^T R_tip) (rotation vector, |Log| = theta) is not smooth
at theta = pi. The optimiser uses the quaternion-based vector part instead: with the quaternion
(w, v) of E = R_h^T R_tip, ``r = 2 v`` has ``|r| = 2 sin(theta / 2)`` and

    ||r||^2 = 4 sin^2(theta / 2) = 3 - tr(R_h^T R_tip),

which is *linear* in the entries of R_tip (no square root, no arccos, no sign choice), equals
theta^2 (1 - theta^2 / 12 + ...) near 0, grows monotonically on [0, pi] and is 4 at theta = pi
(vs pi^2 ~= 9.87 for the exact Log: the rotation weight is relatively 0.41x at a half-turn). The
reported errors use the exact Log (scipy ``Rotation.as_rotvec``).

Hand velocity rule. pdot_h is the demonstration positions differentiated on their own samples by
``numpy.gradient``: second-order central differences inside, first-order one-sided at the two ends
(the speed rule of ``learner.demo_timing``), no smoothing (the paper states none).

Sample grids. Cost samples t_i: the demonstration's own samples (``sample_rate_hz=None``,
default), or a uniform grid over the demonstration's time span at ``sample_rate_hz`` with
positions and velocities interpolated linearly and orientations by slerp. The limit samples t_l
are always the 250 Hz command times i / 250 <= T, and the velocities and accelerations bounded
there are the controllers' central differences of those samples with rest padding
(:func:`learner.bezier.controller_basis`): exactly what the simulated controller faults on and
the hardware preflight refuses on. ``limit_margin`` keeps a fraction of the velocity,
acceleration and torque limits free (the preflight's margin, and IPOPT's constraint
tolerance); positions keep POSITION_MARGIN.

Torque. The paper's initial guess has no torque limit, but a command beyond it faults the robot,
so ``torque_limits=True`` (default) adds |robot.inverse_dynamics(q, qd, qdd)| <= tau bounds at
the limit samples; which terms that includes (armature, damping, springs) is fixed when the
RobotModel is built (``RobotModel.from_mjcf`` flags).

The problem is solved by :func:`learner.initial_guess.solve_problem` (IPOPT); the parameters,
the decision vector and the sample grids are in :mod:`learner.initial_guess_params`.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from flyknot.constants import N_JOINTS
from flyknot.errors import ConfigError, check_positive
from flyknot.geometry import readonly
from learner.bezier import bernstein_basis, controller_basis
from learner.initial_guess_params import (
    FREE_TO_KNOTS,
    HOME_Q,
    N_FREE,
    N_X,
    POSITION_MARGIN,
    InitialGuessParams,
    cost_samples,
    limit_sample_times,
)

if TYPE_CHECKING:
    from learner.kinematics import RobotModel

_T_SLACK = 1e-9  # relative (of T) slack for demo times at the ends of [0, T]
_ROT_TOL = 1e-6  # ||R^T R - I||_max and |det R - 1| allowed for demo orientations


@dataclass(frozen=True)
class InitialGuessProblem:
    """The NLP of the initial guess, built but not solved (inspect or test it apart).

    ``f(x)`` is the objective, ``terms(x)`` its ``COST_TERMS`` parts (4, 1) and ``g(x)`` the
    constraint rows, bounded by ``lbg <= g <= ubg`` in the blocks ``blocks`` (name ->
    (start, stop)): ``"z"`` (1 row), then ``"pos"``, ``"vel"``, ``"acc"`` and optionally
    ``"tau"``, 7 rows per limit sample each (sample a, joint j at row start + 7 a + j).
    ``jac_g(x, p) -> (g, dg/dx)`` and ``hess_lag(x, p, lam_f, lam_g) -> triu(H)`` are the
    structured derivatives IPOPT is given (p is empty, shape (0, 1)); see
    :func:`build_problem`.

    Attributes:
        T: Command duration [s].
        t_cost: Cost samples (m,) [s].
        p_h: Desired positions (m, 3) [m].
        R_h: Desired orientations (m, 3, 3).
        v_h: Desired velocities (m, 3) [m/s].
        t_limit: Limit samples (n,) [s].
        x0: Seed (45,).
        lbg: Lower constraint bounds (r,).
        ubg: Upper constraint bounds (r,).
        blocks: Constraint blocks.
        x: CasADi symbol of the decision vector (MX, 45).
        f: ``Function(x) -> objective``.
        terms: ``Function(x) -> (4, 1)`` weighted cost terms.
        g: ``Function(x) -> constraints (r, 1)``.
        jac_g: ``Function(x, p) -> (g (r, 1), dg/dx (r, 45))``.
        hess_lag: ``Function(x, p, lam_f, lam_g) -> triu(d^2/dx^2 (lam_f f + lam_g^T g))``.
        params: The parameters it was built with.
    """

    T: float
    t_cost: np.ndarray
    p_h: np.ndarray
    R_h: np.ndarray
    v_h: np.ndarray
    t_limit: np.ndarray
    x0: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    blocks: Mapping[str, tuple[int, int]]
    x: ca.MX
    f: ca.Function
    terms: ca.Function
    g: ca.Function
    jac_g: ca.Function
    hess_lag: ca.Function
    params: InitialGuessParams


def _check_inputs(
    t: object, p: object, R: object, T: object, robot: object, q_seed: object
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """Validate and convert the inputs of :func:`build_problem`."""
    if isinstance(T, bool) or not isinstance(T, numbers.Real):
        raise ConfigError("T", f"must be a finite number > 0, got {T!r}")
    T = float(T)
    check_positive("T", T)
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.shape[0] < 2:
        raise ConfigError("demo_hand_t", f"must have shape (k,) with k >= 2, got {t.shape}")
    k = t.shape[0]
    p = np.asarray(p, dtype=float)
    if p.shape != (k, 3):
        raise ConfigError("demo_hand_p", f"must have shape ({k}, 3), got {p.shape}")
    R = np.asarray(R, dtype=float)
    if R.shape != (k, 3, 3):
        raise ConfigError("demo_hand_R", f"must have shape ({k}, 3, 3), got {R.shape}")
    for name, a in (("demo_hand_t", t), ("demo_hand_p", p), ("demo_hand_R", R)):
        if not np.all(np.isfinite(a)):
            raise ConfigError(name, "must be finite everywhere")
    if np.any(np.diff(t) <= 0):
        raise ConfigError("demo_hand_t", "must be strictly increasing")
    slack = _T_SLACK * T
    if t[0] < -slack or t[-1] > T + slack:
        raise ConfigError(
            "demo_hand_t",
            f"must lie in [0, T] = [0, {T:g}] s, got [{t[0]:g}, {t[-1]:g}]",
        )
    t = np.clip(t, 0.0, T)
    ortho = np.abs(np.einsum("kba,kbc->kac", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((ortho > _ROT_TOL) | (np.abs(det - 1.0) > _ROT_TOL))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(
            "demo_hand_R",
            f"must hold rotation matrices; sample {i} has max|R^T R - I| = {ortho[i]:.3g}, "
            f"det = {det[i]:.6g}",
        )
    if getattr(robot, "n_joints", None) != N_JOINTS or not hasattr(robot, "inverse_dynamics"):
        raise ConfigError("robot", f"must be a {N_JOINTS}-joint learner.kinematics.RobotModel")
    q_seed = HOME_Q.copy() if q_seed is None else np.asarray(q_seed, dtype=float)
    if q_seed.shape != (N_JOINTS,) or not np.all(np.isfinite(q_seed)):
        raise ConfigError("q_seed", f"must be a finite array of shape ({N_JOINTS},) [rad]")
    return t, p, R, T, q_seed


@dataclass(frozen=True)
class _SampleFunctions:
    """Per-sample CasADi SX Functions (mapped over the samples by :func:`build_problem`).

    * ``track(q, qd, b, p_h, R_h, v_h) -> (e_p (3,), e_R (1,), e_v (3,))``:
      e_p = p_tip(q) + b - p_h [m], e_R = 3 - tr(R_h^T R_tip(q)), e_v = J_p(q) qd - v_h [m/s];
    * ``cost_hess(z, p_h, R_h, v_h) -> (17, 17)``: Hessian over z = (q, qd, b) of
      w_p |e_p|^2 + w_R e_R + w_v |e_v|^2;
    * ``tau_jac(y) -> (7, 21)`` and ``tau_hess(y, lam) -> (21, 21)``: d tau / d y and
      d^2 (lam^T tau) / d y^2 with y = (q, qd, qdd), tau = robot.inverse_dynamics(q, qd, qdd);
    * ``z_grad(q) -> (1, 7)``, ``z_hess(q) -> (7, 7)``: derivatives of z_tip(q).
    """

    track: ca.Function
    cost_hess: ca.Function
    tau_jac: ca.Function
    tau_hess: ca.Function
    z_grad: ca.Function
    z_hess: ca.Function


def _sample_functions(robot: RobotModel, params: InitialGuessParams) -> _SampleFunctions:
    """Build the per-sample Functions (see :class:`_SampleFunctions`)."""
    n = N_JOINTS
    q, qd, qdd = ca.SX.sym("q", n), ca.SX.sym("qd", n), ca.SX.sym("qdd", n)
    b, ph, vh = ca.SX.sym("b", 3), ca.SX.sym("p_h", 3), ca.SX.sym("v_h", 3)
    Rh = ca.SX.sym("R_h", 3, 3)
    lam = ca.SX.sym("lam", n)
    opts = {"cse": True}
    p, R = robot.fk(q)
    e_p = p + b - ph
    e_r = 3.0 - ca.sum1(ca.sum2(Rh * R))
    e_v = robot.p_dot(q, qd) - vh
    track = ca.Function("track", [q, qd, b, ph, Rh, vh], [e_p, e_r, e_v], opts)
    z = ca.vertcat(q, qd, b)
    cost = params.w_p * ca.sumsqr(e_p) + params.w_r * e_r + params.w_v * ca.sumsqr(e_v)
    cost_hess = ca.Function("cost_hess", [z, ph, Rh, vh], [ca.hessian(cost, z)[0]], opts)
    y = ca.vertcat(q, qd, qdd)
    tau = robot.inverse_dynamics(q, qd, qdd)
    tau_jac = ca.Function("tau_jac", [y], [ca.jacobian(tau, y)], opts)
    tau_hess = ca.Function("tau_hess", [y, lam], [ca.hessian(ca.dot(lam, tau), y)[0]], opts)
    z_tip = p[2]
    z_grad = ca.Function("z_grad", [q], [ca.jacobian(z_tip, q)], opts)
    z_hess = ca.Function("z_hess", [q], [ca.hessian(z_tip, q)[0]], opts)
    return _SampleFunctions(track, cost_hess, tau_jac, tau_hess, z_grad, z_hess)


def lift_matrix(G: list[np.ndarray], with_base: bool) -> np.ndarray:
    """Linear map from x (45,) to the stacked per-sample vectors y_a.

    y_a = (q^(r_0)(t_a), q^(r_1)(t_a), ..., [b]) with q^(r)_j(t_a) = sum_c G_r[a, c] x[6 j + c]
    and b = x[42:45]; row a * d + 7 s + j holds q^(r_s)_j(t_a), d = 7 len(G) (+ 3 with the base).

    Args:
        G: Effective bases G_r = B_r(t) E^T, each (L, 6) [1 / s^r].
        with_base: Append b to every y_a.

    Returns:
        P, shape (L d, 45).
    """
    L = G[0].shape[0]
    d = N_JOINTS * len(G) + (3 if with_base else 0)
    P = np.zeros((L, d, N_X))
    for s, Gr in enumerate(G):
        for j in range(N_JOINTS):
            P[:, N_JOINTS * s + j, N_FREE * j : N_FREE * (j + 1)] = Gr
    if with_base:
        P[:, d - 3 :, N_JOINTS * N_FREE :] = np.eye(3)
    return P.reshape(L * d, N_X)


def _sparse_dm(A: np.ndarray) -> ca.DM:
    """A numpy matrix as a CasADi DM keeping only its nonzeros."""
    r, c = np.nonzero(A)
    return ca.DM.triplet(r.tolist(), c.tolist(), ca.DM(A[r, c]), A.shape[0], A.shape[1])


def _sandwich(P: ca.DM, blocks: ca.MX, size: int) -> ca.MX:
    """P^T blockdiag(H_1, ..., H_L) P for blocks (size, size L) side by side; P (L size, 45)."""
    return ca.mtimes([P.T, ca.diagcat(*ca.horzsplit(blocks, size)), P])


def build_problem(
    demo_hand_t: np.ndarray,
    demo_hand_p: np.ndarray,
    demo_hand_R: np.ndarray,
    T: float,
    robot: RobotModel,
    *,
    params: InitialGuessParams | None = None,
    q_seed: np.ndarray | None = None,
) -> InitialGuessProblem:
    """Build the initial-guess NLP (module docstring) without solving it.

    With the effective bases ``G_r = B_r(t) E^T`` (m, 6) of derivative order r, the joint
    samples are ``q^(r)(t) = C G_r^T`` (7, m) [rad / s^r], linear in x; the cost is

        f(x) = w_p sum_i |e_p,i|^2 + w_R sum_i (3 - tr(R_h,i^T R_tip,i))
             + w_v sum_i |e_v,i|^2 + w_j sum_i |q'''(t_i)|^2.

    Structured derivatives (every sample depends on x only through the lifted y_a = P_a x,
    :func:`lift_matrix`), instead of differentiating through all samples at once:

        dg_tau / dx = blockdiag_a(d tau / d y (y_a)) P_tau,
        H = lam_f (sum_i P_i^T d^2 l / dz^2 (z_i) P_i + 2 w_j I_7 (x) G_3^T G_3)
          + lam_z P_0^T d^2 z_tip / dq^2 (q(0)) P_0 + sum_a P_a^T d^2 (lam_a^T tau) / dy^2 P_a,

    with z_i = (q, qd, b)(t_i) for the cost and y_a = (q, qd, qdd)(t_a) for the torque rows.

    Args:
        demo_hand_t: Demonstration times, shape (k,) [s], strictly increasing, within [0, T]
            (the command's clock: a trimmed demonstration starts at 0).
        demo_hand_p: Desired fingertip positions, shape (k, 3) [m], demonstration frame.
        demo_hand_R: Desired fingertip orientations, shape (k, 3, 3) (tip-site convention).
        T: Command duration [s].
        robot: Robot model (fingertip kinematics, inverse dynamics).
        params: Weights, limits and settings (default: the paper's).
        q_seed: Seed joint angles (7,) [rad] for every knot; default ``HOME_Q``.

    Returns:
        The problem.

    Raises:
        ConfigError: Malformed inputs.
    """
    params = InitialGuessParams() if params is None else params
    if not isinstance(params, InitialGuessParams):
        raise ConfigError("params", f"must be InitialGuessParams, got {type(params).__name__}")
    t, p, R, T, q_seed = _check_inputs(demo_hand_t, demo_hand_p, demo_hand_R, T, robot, q_seed)
    ti, ph, Rh, vh = cost_samples(t, p, R, params.sample_rate_hz)
    tl = limit_sample_times(T)
    m, n = ti.shape[0], tl.shape[0]
    fun = _sample_functions(robot, params)
    Gc = [bernstein_basis(ti, T, r) @ FREE_TO_KNOTS.T for r in (0, 1, 3)]  # (m, 6) each
    Gl = [controller_basis(tl, T, r) @ FREE_TO_KNOTS.T for r in (0, 1, 2)]  # (n, 6) each
    Ph_dm, Rh_dm, vh_dm = ca.DM(ph.T), ca.DM(Rh.transpose(1, 0, 2).reshape(3, 3 * m)), ca.DM(vh.T)

    x = ca.MX.sym("x", N_X)
    C = ca.reshape(x[: N_JOINTS * N_FREE], N_FREE, N_JOINTS).T  # (7, 6), C[j, c] = x[6 j + c]
    b = x[N_JOINTS * N_FREE :]
    q0 = C[:, 0]  # q(0) = kappa[:, 0]

    # cost
    Qc = [C @ ca.DM(G.T) for G in Gc]  # q, qd, q''' at the cost samples, (7, m) each
    e_p, e_r, e_v = fun.track.map(m)(Qc[0], Qc[1], ca.repmat(b, 1, m), Ph_dm, Rh_dm, vh_dm)
    terms = ca.vertcat(
        params.w_p * ca.sumsqr(e_p),
        params.w_r * ca.sum2(e_r),
        params.w_v * ca.sumsqr(e_v),
        params.w_j * ca.sumsqr(Qc[2]),
    )
    f = ca.sum1(terms)

    # constraints, each block (7, n) vectorised column-major: sample a, joint j at 7 a + j
    Ql = [C @ ca.DM(G.T) for G in Gl]  # q, qd, qdd at the limit samples, (7, n) each
    P0 = lift_matrix([np.eye(1, N_FREE)], with_base=False)  # (7, 45): q(0) from x
    Y = ca.vertcat(*Ql)  # (21, n): column a is y_a = (q, qd, qdd)(t_a)
    P_tau = _sparse_dm(lift_matrix(Gl, with_base=False))  # (21 n, 45)
    rows = _constraint_rows(Ql, Gl, Y, P_tau, P0, q0, b, robot, fun, params)
    g, jac_g, lbg, ubg, blocks = _stacked(rows)

    # Hessian of the Lagrangian
    lam_f = ca.MX.sym("lam_f")
    lam_g = ca.MX.sym("lam_g", g.numel())
    empty = ca.MX.sym("p", 0, 1)
    Pc = _sparse_dm(lift_matrix(Gc[:2], with_base=True))  # (17 m, 45)
    Z = ca.vertcat(Qc[0], Qc[1], ca.repmat(b, 1, m))  # (17, m)
    H = lam_f * _sandwich(Pc, fun.cost_hess.map(m)(Z, Ph_dm, Rh_dm, vh_dm), 17)
    H = H + lam_f * _sparse_dm(_jerk_hessian(Gc[2], params.w_j))
    H = H + lam_g[0] * ca.mtimes([ca.DM(P0).T, fun.z_hess(q0), ca.DM(P0)])
    if params.torque_limits:
        a, z = blocks["tau"]
        Lam = ca.reshape(lam_g[a:z], N_JOINTS, n)  # column a: multipliers of sample a
        H = H + _sandwich(P_tau, fun.tau_hess.map(n)(Y, Lam), 3 * N_JOINTS)

    # seed: every knot at q_seed, b = p_h(t_0) - FK(q_seed)
    p_seed = np.asarray(robot.fk(q_seed)[0]).ravel()
    x0 = np.concatenate([np.repeat(q_seed, N_FREE), p[0] - p_seed])

    return InitialGuessProblem(
        T=T,
        t_cost=readonly(ti),
        p_h=readonly(ph),
        R_h=readonly(Rh),
        v_h=readonly(vh),
        t_limit=readonly(tl),
        x0=readonly(x0),
        lbg=readonly(np.concatenate(lbg)),
        ubg=readonly(np.concatenate(ubg)),
        blocks=MappingProxyType(blocks),
        x=x,
        f=ca.Function("f", [x], [f]),
        terms=ca.Function("terms", [x], [terms]),
        g=ca.Function("g", [x], [g]),
        jac_g=ca.Function("jac_g", [x, empty], [g, jac_g]),
        hess_lag=ca.Function("hess_lag", [x, empty, lam_f, lam_g], [ca.triu(H)]),
        params=params,
    )


_Row = tuple[str, ca.MX, ca.MX, np.ndarray, np.ndarray]
"""A constraint block: name, expression (k,), its Jacobian (k, 45), lower and upper bounds
(per joint or per block, tiled over the block)."""


def _constraint_rows(
    Ql: list[ca.MX],
    Gl: list[np.ndarray],
    Y: ca.MX,
    P_tau: ca.DM,
    P0: np.ndarray,
    q0: ca.MX,
    b: ca.MX,
    robot: RobotModel,
    fun: _SampleFunctions,
    params: InitialGuessParams,
) -> list[_Row]:
    """The constraint blocks with their structured Jacobians: the fingertip's height at t = 0
    (in the demonstration frame, or above the lab's floor with ``params.base_height``), the
    joint positions, rates and accelerations at the limit samples within the limits less
    their margins, and the joint torques (``params.torque_limits``).

    ``Ql``: q, qd, qdd at the n limit samples, (7, n) each, with their bases ``Gl`` (n, 6)
    each; ``Y`` their stack (21, n) and ``P_tau`` its lift from x (21 n, 45); ``P0`` the lift
    of q(0) (7, 45); ``q0`` (7,) and ``b`` (3,) the parts of x they name."""
    lim = params.limits
    keep = 1.0 - params.limit_margin
    rows: list[_Row] = []
    if params.base_height is None:  # height in the demonstration frame
        e_b = np.zeros((1, N_X))
        e_b[0, N_X - 1] = 1.0
        z_jac = fun.z_grad(q0) @ ca.DM(P0) + ca.DM(e_b)
        rows.append(("z", robot.fk(q0)[0][2] + b[2], z_jac, [params.z_min], [np.inf]))
    else:  # height above the lab's floor
        z_jac = fun.z_grad(q0) @ ca.DM(P0)
        z_expr = robot.fk(q0)[0][2] + params.base_height
        rows.append(("z", z_expr, z_jac, [params.z_min], [np.inf]))
    bounds = {
        "pos": (lim.q_min + POSITION_MARGIN, lim.q_max - POSITION_MARGIN),
        "vel": (-keep * lim.qd_max, keep * lim.qd_max),
        "acc": (-keep * lim.qdd_max, keep * lim.qdd_max),
    }
    for r, name in enumerate(("pos", "vel", "acc")):
        A = _sparse_dm(lift_matrix([Gl[r]], with_base=False))  # (7 n, 45)
        rows.append((name, ca.vec(Ql[r]), A, *bounds[name]))
    if params.torque_limits:
        n = Y.shape[1]
        tau = robot.inverse_dynamics.map(n)(Ql[0], Ql[1], Ql[2])
        dtau = ca.mtimes(ca.diagcat(*ca.horzsplit(fun.tau_jac.map(n)(Y), 3 * N_JOINTS)), P_tau)
        rows.append(("tau", ca.vec(tau), dtau, -keep * lim.tau_max, keep * lim.tau_max))
    return rows


def _stacked(
    rows: list[_Row],
) -> tuple[ca.MX, ca.MX, list[np.ndarray], list[np.ndarray], dict[str, tuple[int, int]]]:
    """The blocks stacked: g (k,), its Jacobian (k, 45), the bounds (k,) and each block's
    [start, end) rows by name."""
    g_parts, jac_parts, lbg, ubg, blocks = [], [], [], [], {}
    start = 0
    for name, expr, jac, lo, hi in rows:
        size = expr.numel()
        reps = size // len(lo)
        g_parts.append(expr)
        jac_parts.append(jac)
        lbg.append(np.tile(lo, reps))
        ubg.append(np.tile(hi, reps))
        blocks[name] = (start, start + size)
        start += size
    return ca.vertcat(*g_parts), ca.vertcat(*jac_parts), lbg, ubg, blocks


def _jerk_hessian(G3: np.ndarray, w_j: float) -> np.ndarray:
    """The jerk term's constant Hessian (45, 45): 2 w_j I_7 (x) G_3^T G_3 on the knots, zero
    on the offset b."""
    H = np.zeros((N_X, N_X))
    H[: N_JOINTS * N_FREE, : N_JOINTS * N_FREE] = np.kron(np.eye(N_JOINTS), 2.0 * w_j * G3.T @ G3)
    return H


__all__ = ["InitialGuessProblem", "build_problem", "lift_matrix"]

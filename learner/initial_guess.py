"""The initial command kappa_0: trajectory optimisation tracking the demonstration hand.

Paper, section "Initial Guess" (eq. ik_trajopt) and appendix "Demonstration Tracking". With the
command q(t) = B(kappa, T)(t) (``learner.bezier``) and the fingertip kinematics of the robot
model (``learner.kinematics``, all in the robot base frame), solve over the arm knots and the
base offset b (3,) [m]::

    min   sum_i ||e_h(t_i)||^2_{W_h} + w_j sum_i ||q'''(t_i)||^2
    e_h = [p_tip(t_i) + b - p_h(t_i);  r(R_h(t_i)^T R_tip(t_i));  pdot_tip(t_i) - pdot_h(t_i)]
    W_h = diag(w_p I3, w_R I3, w_v I3)
    s.t.  q_min + dq <= q(t_l) <= q_max - dq          (dq = POSITION_MARGIN [rad])
          |qd(t_l)|  <= (1 - limit_margin) qd_max
          |qdd(t_l)| <= (1 - limit_margin) qdd_max
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
are always the 250 Hz command times i / 250 <= T plus T itself: exactly the samples the controller
checks. ``limit_margin`` keeps a fraction of the velocity, acceleration and torque limits free
for the controller's finite differences of the 250 Hz samples (O(dt^2) away from the analytic
derivatives; the rest padding halves qdd at the first sample) and for IPOPT's constraint
tolerance; positions keep POSITION_MARGIN.

Torque. The paper's initial guess has no torque limit, but a command beyond it faults the robot,
so ``torque_limits=True`` (default) adds |robot.inverse_dynamics(q, qd, qdd)| <= tau bounds at
the limit samples; which terms that includes (armature, damping, springs) is fixed when the
RobotModel is built (``RobotModel.from_mjcf`` flags).

Solver: CasADi + IPOPT (MUMPS, default options; the paper used SNOPT through Drake). IPOPT gets
exact first and second derivatives assembled from per-sample ones (:func:`build_problem`):
CasADi's own Hessian through all samples at once needs 45 directional sweeps and was 2-3x
slower on the reference motion. Measured there (T = 0.715 s, 144 demo samples at 200 Hz, 180
limit samples, 2 shared cores): ~33-45 iterations, 3-6 s; ~75 % of it the torque rows' Hessian
(torque_limits=False: 1.5 s). A coarser cost grid hardly helps because the 250 Hz torque rows
dominate: 200 / 100 / 50 / 25 Hz gave 3.3 / 3.0 / 3.3 / 6.3 s with tracking errors on the
200 Hz demo within 4 % of each other, so the default keeps the demonstration's samples. The
problem is non-convex: other seeds can reach other local minima (62.6 vs 67.5 on the reference
motion with joint 1 or 7 of the seed moved). Seed: every
knot at ``q_seed`` (default the xArm home) and b such that FK(q_seed) + b = p_h(t_0), so the
seed tracks the first sample exactly and stands still. A failed solve is reported through
``status``/``success``; only :func:`require_success` raises.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_KNOTS, N_ROWS, Z_MIN_TIP
from flyknot.errors import ConfigError, SolverError, check_nonnegative, check_positive
from flyknot.geometry import readonly
from flyknot.limits import JointLimits
from learner.bezier import BezierCommand, bernstein_basis

if TYPE_CHECKING:
    from learner.kinematics import RobotModel

HOME_Q = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])  # xArm 7 home [rad]
HOME_Q.setflags(write=False)
POSITION_MARGIN = 1e-3  # [rad] kept free inside each joint's position range
Z_TOL = 1e-6  # [m] IPOPT's tolerance on the z_min row when judging feasibility
ACTIVE_RTOL = 1e-3  # a limit row counts as binding within this fraction of its bound
IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
COST_TERMS = ("position", "rotation", "velocity", "jerk")
LIMIT_BLOCKS = ("z", "pos", "vel", "acc", "tau")
N_FREE = N_KNOTS - 2  # free knot columns per joint (k_1 = k_0, k_6 = k_7)
N_X = N_JOINTS * N_FREE + 3  # 45
_T_SLACK = 1e-9  # relative (of T) slack for demo times at the ends of [0, T]
_ROT_TOL = 1e-6  # ||R^T R - I||_max and |det R - 1| allowed for demo orientations

# E (6, 8): kappa_arm = C E, columns (k_0, k_2, k_3, k_4, k_5, k_7) -> knots 0..7.
_E = np.zeros((N_FREE, N_KNOTS))
_E[0, 0] = _E[0, 1] = 1.0
for _c in range(1, N_FREE - 1):
    _E[_c, _c + 1] = 1.0
_E[N_FREE - 1, N_KNOTS - 2] = _E[N_FREE - 1, N_KNOTS - 1] = 1.0
_E.setflags(write=False)
_KNOT_COLUMN = np.argmax(_E, axis=0)  # (8,): free column of each knot, (0, 0, 1, 2, 3, 4, 5, 5)


# --------------------------------------------------------------------------------------------
# parameters and result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InitialGuessParams:
    """Weights, limits and solver settings of the initial-guess optimisation.

    Defaults are the paper's (appendix table "Demonstration Tracking Parameters"); ``w_r`` is
    the paper's w_R.

    Attributes:
        w_j: Jerk weight [s^6 / rad^2].
        w_p: Fingertip position weight [1 / m^2].
        w_r: Fingertip rotation weight [1 / rad^2].
        w_v: Fingertip velocity weight [s^2 / m^2].
        z_min: Lowest fingertip height at the start above the floor [m].
        base_height: Height of the robot base above the lab's floor [m] (the lab's
            calibration). Given, the start height is the lab's: z_tip(q(0)) + base_height
            >= z_min, so the rope hangs clear of the real floor whatever the base offset;
            None measures it in the demonstration frame: z_tip(q(0)) + b_z >= z_min.
        sample_rate_hz: Rate of the uniform cost grid [Hz]; None uses the demonstration's own
            samples.
        max_iter: IPOPT iteration limit (integer >= 1).
        limit_margin: Fraction of each velocity, acceleration and torque limit kept free,
            in [0, 1).
        tol: IPOPT's relative convergence tolerance, > 0.
        torque_limits: Impose |tau| <= (1 - limit_margin) tau_max at the limit samples.
        limits: Joint limits (default: the paper's).
    """

    w_j: float = 5e-7
    w_p: float = 10.0
    w_r: float = 0.2
    w_v: float = 0.5
    z_min: float = Z_MIN_TIP
    base_height: float | None = None
    sample_rate_hz: float | None = None
    max_iter: int = 500
    limit_margin: float = 0.05
    tol: float = 1e-6
    torque_limits: bool = True
    limits: JointLimits = field(default_factory=JointLimits)

    def __post_init__(self) -> None:
        for name in ("w_j", "w_p", "w_r", "w_v"):
            check_nonnegative(name, getattr(self, name))
        z = self.z_min
        if isinstance(z, bool) or not isinstance(z, numbers.Real) or not math.isfinite(z):
            raise ConfigError("z_min", f"must be a finite number [m], got {z!r}")
        if self.sample_rate_hz is not None:
            check_positive("sample_rate_hz", self.sample_rate_hz)
        if self.base_height is not None:
            check_nonnegative("base_height", self.base_height)
        mi = self.max_iter
        if isinstance(mi, bool) or not isinstance(mi, numbers.Integral) or mi < 1:
            raise ConfigError("max_iter", f"must be an integer >= 1, got {mi!r}")
        check_nonnegative("limit_margin", self.limit_margin)
        if self.limit_margin >= 1:
            raise ConfigError("limit_margin", f"must be < 1, got {self.limit_margin!r}")
        check_positive("tol", self.tol)
        if not isinstance(self.torque_limits, bool):
            raise ConfigError(
                "torque_limits", f"unknown value {self.torque_limits!r}", [True, False]
            )
        if not isinstance(self.limits, JointLimits):
            raise ConfigError("limits", f"must be a JointLimits, got {type(self.limits).__name__}")


@dataclass(frozen=True)
class InitialGuessResult:
    """Outcome of :func:`initial_guess`.

    Attributes:
        knots: Knots kappa_0 (10, 8): rows 0-6 joints [rad], rows 7-9 the base offset [m]
            (constant across knots). The solver's last iterate, also when it failed (the seed
            if that iterate is not finite).
        T: Command duration [s].
        status: IPOPT's own return status (``"Solve_Succeeded"``, ``"Infeasible_Problem_
            Detected"``, ``"Maximum_Iterations_Exceeded"``, ...).
        converged: IPOPT reported success (``IPOPT_SUCCESS``).
        feasible: The command respects every limit at its 250 Hz samples (analytic
            derivatives, torque if ``torque_limits``) and the z_min row (to ``Z_TOL``).
        success: ``converged and feasible``.
        cost: Objective at ``knots`` (the surrogate rotation term) [-].
        cost_terms: ``COST_TERMS`` -> weighted sums [-]; they add up to ``cost``.
        max_errors: Largest tracking errors over the cost samples: ``"position"`` [m],
            ``"rotation"`` [rad] (exact |Log|), ``"velocity"`` [m/s].
        rms_errors: Root-mean-square of the same [m], [rad], [m/s].
        limit_usage: Largest |value| / limit over the 250 Hz samples and joints for
            ``"vel"``, ``"acc"``, ``"tau"``; for ``"pos"`` the largest |q - mid| / half-range;
            for ``"z"`` the start height margin z_tip(q(0)) + b_z - z_min [m].
        active_limits: ``LIMIT_BLOCKS`` -> number of limit rows within ``ACTIVE_RTOL`` of their
            (margin-reduced) bound at the solution.
        violations: One line per violated limit (empty when feasible).
        iterations: IPOPT iterations.
        build_time: Wall time to build the NLP and the IPOPT instance [s].
        solve_time: Wall time of the IPOPT solve [s].
    """

    knots: np.ndarray
    T: float
    status: str
    converged: bool
    feasible: bool
    success: bool
    cost: float
    cost_terms: Mapping[str, float]
    max_errors: Mapping[str, float]
    rms_errors: Mapping[str, float]
    limit_usage: Mapping[str, float]
    active_limits: Mapping[str, int]
    violations: tuple[str, ...]
    iterations: int
    build_time: float
    solve_time: float

    @property
    def base_offset(self) -> np.ndarray:
        """Base offset b (3,) [m]: the robot base's position in the demonstration frame."""
        return self.knots[N_JOINTS:, 0].copy()

    @property
    def command(self) -> BezierCommand:
        """The knots and duration as a :class:`BezierCommand`."""
        return BezierCommand(self.knots, self.T)


def require_success(result: InitialGuessResult) -> InitialGuessResult:
    """Return ``result`` if the solve converged to a feasible command.

    Raises:
        SolverError: With IPOPT's status, and the violated limits if it converged to an
            infeasible command.
    """
    if not result.success:
        detail = "; ".join(result.violations) if result.violations else ""
        if result.converged and not result.feasible:
            detail = f"converged but infeasible: {detail}"
        raise SolverError("ipopt", result.status, detail)
    return result


# --------------------------------------------------------------------------------------------
# pure kernels
# --------------------------------------------------------------------------------------------


def hand_velocity(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Demonstration hand velocity by finite differences on its own samples.

    pdot_i = (p_{i+1} - p_{i-1}) / (t_{i+1} - t_{i-1}) on a uniform grid (numpy.gradient's
    second-order formula on a non-uniform one), pdot_0 = (p_1 - p_0) / (t_1 - t_0) and
    likewise backwards at the last sample.

    Args:
        t: Sample times, shape (k,) [s], strictly increasing, k >= 2.
        p: Hand positions, shape (k, 3) [m].

    Returns:
        Velocities, shape (k, 3) [m/s].
    """
    return np.gradient(np.asarray(p, dtype=float), np.asarray(t, dtype=float), axis=0)


def rotation_error_sq(R_h: np.ndarray, R_tip: np.ndarray) -> np.ndarray:
    """Smooth squared rotation error, the quaternion vector part of E = R_h^T R_tip.

    ||2 v||^2 = 4 sin^2(theta / 2) = 3 - tr(R_h^T R_tip) = 3 - sum_ab R_h[a, b] R_tip[a, b],
    theta = |Log(E)|.

    Args:
        R_h: Desired orientations, shape (m, 3, 3).
        R_tip: Fingertip orientations, shape (m, 3, 3).

    Returns:
        Squared errors, shape (m,) [rad^2-like, in [0, 4]].
    """
    return 3.0 - np.einsum("mab,mab->m", np.asarray(R_h), np.asarray(R_tip))


def rotation_log(R_h: np.ndarray, R_tip: np.ndarray) -> np.ndarray:
    """Exact rotation error Log(R_h^T R_tip) (rotation vector, |Log| = theta in [0, pi]).

    Args:
        R_h: Desired orientations, shape (m, 3, 3).
        R_tip: Fingertip orientations, shape (m, 3, 3).

    Returns:
        Rotation vectors, shape (m, 3) [rad], in the desired (R_h) frame.
    """
    E = np.einsum("mba,mbc->mac", np.asarray(R_h), np.asarray(R_tip))
    return Rotation.from_matrix(E).as_rotvec()


def knots_from_x(x: np.ndarray) -> np.ndarray:
    """Knots (10, 8) of the decision vector x (45,).

    kappa[0:7] = C E with C = x[:42] as (7, 6) row-major and E the (6, 8) 0/1 map
    (k_1 = k_0, k_6 = k_7); kappa[7:10, :] = x[42:45] repeated.

    Args:
        x: Decision vector, shape (45,) ([rad] then [m]).

    Returns:
        Knots, shape (10, 8).
    """
    x = np.asarray(x, dtype=float)
    if x.shape != (N_X,):
        raise ConfigError("x", f"must have shape ({N_X},), got {x.shape}")
    C = x[: N_JOINTS * N_FREE].reshape(N_JOINTS, N_FREE)
    out = np.empty((N_ROWS, N_KNOTS))
    out[:N_JOINTS] = C[:, _KNOT_COLUMN]  # = C E, by indexing so the ties are bitwise
    out[N_JOINTS:] = x[N_JOINTS * N_FREE :, None]
    return out


def x_from_knots(knots: np.ndarray) -> np.ndarray:
    """Inverse of :func:`knots_from_x` for knots with k_1 = k_0, k_6 = k_7, constant base rows.

    Args:
        knots: Knots, shape (10, 8).

    Returns:
        Decision vector, shape (45,).

    Raises:
        ConfigError: The knots do not have the tied end columns or a constant base.
    """
    k = np.asarray(knots, dtype=float)
    if k.shape != (N_ROWS, N_KNOTS):
        raise ConfigError("knots", f"must have shape ({N_ROWS}, {N_KNOTS}), got {k.shape}")
    arm = k[:N_JOINTS]
    if not (np.array_equal(arm[:, 0], arm[:, 1]) and np.array_equal(arm[:, -1], arm[:, -2])):
        raise ConfigError("knots", "arm rows need knot 1 = knot 0 and knot 6 = knot 7")
    if not np.all(k[N_JOINTS:] == k[N_JOINTS:, :1]):
        raise ConfigError("knots", "base-offset rows must be constant across the knots")
    C = arm[:, [0, 2, 3, 4, 5, 7]]
    return np.concatenate([C.ravel(), k[N_JOINTS:, 0]])


def limit_sample_times(T: float, rate_hz: float = COMMAND_RATE_HZ) -> np.ndarray:
    """Times the limits are imposed at: i / rate_hz <= T, plus T if not among them.

    Args:
        T: Command duration [s], > 0.
        rate_hz: Command rate [Hz].

    Returns:
        Times, shape (n,) [s], increasing, first 0 and last T.
    """
    n = int(np.floor(T * rate_hz + 1e-9)) + 1
    t = np.minimum(np.arange(n) / rate_hz, T)
    if T - t[-1] > 1e-12 * max(T, 1.0):
        t = np.append(t, T)
    return t


def cost_samples(
    t: np.ndarray, p: np.ndarray, R: np.ndarray, sample_rate_hz: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cost grid and the demonstration on it.

    v = :func:`hand_velocity` (t, p) on the demonstration samples; with a rate, the grid is
    n = ceil((t_k - t_1) rate) + 1 uniform times over [t_1, t_k], p and v interpolated
    linearly and R by slerp; without one the grid is t itself.

    Args:
        t: Demonstration times, shape (k,) [s].
        p: Hand positions, shape (k, 3) [m].
        R: Hand orientations, shape (k, 3, 3).
        sample_rate_hz: Grid rate [Hz] or None.

    Returns:
        ``(t_i (m,) [s], p_h (m, 3) [m], R_h (m, 3, 3), v_h (m, 3) [m/s])``.
    """
    v = hand_velocity(t, p)
    if sample_rate_hz is None:
        return t, p, R, v
    n = max(2, int(np.ceil((t[-1] - t[0]) * sample_rate_hz - 1e-9)) + 1)
    ti = np.linspace(t[0], t[-1], n)
    pi = np.stack([np.interp(ti, t, p[:, a]) for a in range(3)], axis=1)
    vi = np.stack([np.interp(ti, t, v[:, a]) for a in range(3)], axis=1)
    Ri = Slerp(t, Rotation.from_matrix(R))(ti).as_matrix()
    return ti, pi, Ri, vi


# --------------------------------------------------------------------------------------------
# the NLP
# --------------------------------------------------------------------------------------------


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
    Gc = [bernstein_basis(ti, T, r) @ _E.T for r in (0, 1, 3)]  # (m, 6) each
    Gl = [bernstein_basis(tl, T, r) @ _E.T for r in (0, 1, 2)]  # (n, 6) each
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
    lim = params.limits
    keep = 1.0 - params.limit_margin
    Ql = [C @ ca.DM(G.T) for G in Gl]  # q, qd, qdd at the limit samples, (7, n) each
    rows: list[tuple[str, ca.MX, ca.MX, np.ndarray, np.ndarray]] = []
    e_b = np.zeros((1, N_X))
    e_b[0, N_X - 1] = 1.0
    P0 = lift_matrix([np.eye(1, N_FREE)], with_base=False)  # (7, 45): q(0) from x
    if params.base_height is None:  # height in the demonstration frame
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
    P_tau = _sparse_dm(lift_matrix(Gl, with_base=False))  # (21 n, 45)
    if params.torque_limits:
        tau = robot.inverse_dynamics.map(n)(Ql[0], Ql[1], Ql[2])
        Y = ca.vertcat(*Ql)  # (21, n): column a is y_a
        dtau = ca.mtimes(ca.diagcat(*ca.horzsplit(fun.tau_jac.map(n)(Y), 3 * N_JOINTS)), P_tau)
        rows.append(("tau", ca.vec(tau), dtau, -keep * lim.tau_max, keep * lim.tau_max))
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
    g = ca.vertcat(*g_parts)
    jac_g = ca.vertcat(*jac_parts)

    # Hessian of the Lagrangian
    lam_f = ca.MX.sym("lam_f")
    lam_g = ca.MX.sym("lam_g", start)
    empty = ca.MX.sym("p", 0, 1)
    Pc = _sparse_dm(lift_matrix(Gc[:2], with_base=True))  # (17 m, 45)
    Z = ca.vertcat(Qc[0], Qc[1], ca.repmat(b, 1, m))  # (17, m)
    H = lam_f * _sandwich(Pc, fun.cost_hess.map(m)(Z, Ph_dm, Rh_dm, vh_dm), 17)
    G3 = Gc[2]
    H_jerk = np.zeros((N_X, N_X))
    H_jerk[: N_JOINTS * N_FREE, : N_JOINTS * N_FREE] = np.kron(
        np.eye(N_JOINTS), 2.0 * params.w_j * G3.T @ G3
    )
    H = H + lam_f * _sparse_dm(H_jerk)
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


# --------------------------------------------------------------------------------------------
# checking a command
# --------------------------------------------------------------------------------------------


def tracking_errors(
    knots: np.ndarray,
    T: float,
    t: np.ndarray,
    p_h: np.ndarray,
    R_h: np.ndarray,
    v_h: np.ndarray,
    robot: RobotModel,
) -> dict[str, np.ndarray]:
    """Fingertip tracking errors of a command at sample times, with the exact rotation Log.

    |p_tip(q(t)) + b - p_h|, |Log(R_h^T R_tip(q(t)))|, |J_p(q) qd(t) - v_h|, with q, qd from
    the knots and b = knots[7:10, 0].

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        t: Sample times (m,) [s] in [0, T].
        p_h: Desired positions (m, 3) [m].
        R_h: Desired orientations (m, 3, 3).
        v_h: Desired velocities (m, 3) [m/s].
        robot: Robot model.

    Returns:
        ``{"position": (m,) [m], "rotation": (m,) [rad], "velocity": (m,) [m/s]}``.
    """
    q = bernstein_basis(t, T, 0) @ knots[:N_JOINTS].T
    qd = bernstein_basis(t, T, 1) @ knots[:N_JOINTS].T
    tip = robot.tip_states(q, qd)
    return {
        "position": np.linalg.norm(tip.p + knots[N_JOINTS:, 0] - p_h, axis=1),
        "rotation": np.linalg.norm(rotation_log(R_h, tip.R), axis=1),
        "velocity": np.linalg.norm(tip.v - v_h, axis=1),
    }


def check_command(
    knots: np.ndarray,
    T: float,
    robot: RobotModel,
    params: InitialGuessParams,
) -> tuple[dict[str, float], list[str]]:
    """Usage of every limit by a command at its 250 Hz samples, and the violations.

    Samples t = :func:`limit_sample_times` (T); analytic q, qd, qdd from the knots;
    tau = robot.torques(q, qd, qdd). A violation is q outside [q_min, q_max], |qd| > qd_max,
    |qdd| > qdd_max, |tau| > tau_max (if ``params.torque_limits``; the *unreduced* limits) or
    z_tip(q(0)) + b_z < z_min - Z_TOL.

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        robot: Robot model.
        params: Limits, z_min and the torque flag.

    Returns:
        ``(usage, violations)``: usage as in :attr:`InitialGuessResult.limit_usage`; one line
        per violated quantity (worst joint and time).
    """
    lim = params.limits
    t = limit_sample_times(T)
    q, qd, qdd = (bernstein_basis(t, T, r) @ knots[:N_JOINTS].T for r in (0, 1, 2))
    tau = robot.torques(q, qd, qdd)
    mid, half = 0.5 * (lim.q_max + lim.q_min), 0.5 * (lim.q_max - lim.q_min)
    ratios = {
        "pos": np.abs(q - mid) / half,
        "vel": np.abs(qd) / lim.qd_max,
        "acc": np.abs(qdd) / lim.qdd_max,
        "tau": np.abs(tau) / lim.tau_max,
    }
    values = {"pos": q, "vel": qd, "acc": qdd, "tau": tau}
    usage: dict[str, float] = {}
    violations: list[str] = []
    for name, ratio in ratios.items():
        usage[name] = float(ratio.max())
        if name == "tau" and not params.torque_limits:
            continue
        if ratio.max() > 1.0:
            a, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
            violations.append(
                f"{name} joint {j + 1} = {values[name][a, j]:.4g} at t = {t[a]:.3f} s "
                f"({ratio[a, j]:.3f} x limit)"
            )
    z_base = knots[N_ROWS - 1, 0] if params.base_height is None else params.base_height
    z0 = float(np.asarray(robot.fk(knots[:N_JOINTS, 0])[0])[2, 0] + z_base)
    usage["z"] = z0 - params.z_min
    if usage["z"] < -Z_TOL:
        violations.append(f"z start height {z0:.4f} m below z_min {params.z_min:g} m")
    return usage, violations


# --------------------------------------------------------------------------------------------
# solving
# --------------------------------------------------------------------------------------------


def _ipopt_options(params: InitialGuessParams) -> dict:
    return {
        "ipopt.max_iter": int(params.max_iter),
        "ipopt.tol": float(params.tol),
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
    }


def solve_problem(problem: InitialGuessProblem, robot: RobotModel) -> InitialGuessResult:
    """Solve a built problem with IPOPT and evaluate the outcome.

    Args:
        problem: From :func:`build_problem`.
        robot: The robot model it was built with (for the checks).

    Returns:
        The result; ``success`` is False (with IPOPT's ``status`` kept) unless IPOPT converged
        and the command respects every limit at 250 Hz.
    """
    params = problem.params
    t_build = time.perf_counter()
    nlp = {"x": problem.x, "f": problem.f(problem.x), "g": problem.g(problem.x)}
    opts = {**_ipopt_options(params), "jac_g": problem.jac_g, "hess_lag": problem.hess_lag}
    solver = ca.nlpsol("initial_guess", "ipopt", nlp, opts)
    build_time = time.perf_counter() - t_build
    t0 = time.perf_counter()
    sol = solver(x0=problem.x0, lbg=problem.lbg, ubg=problem.ubg)
    solve_time = time.perf_counter() - t0
    stats = solver.stats()
    status = str(stats.get("return_status", "unknown"))
    x = np.asarray(sol["x"]).ravel()
    converged = status in IPOPT_SUCCESS and bool(np.all(np.isfinite(x)))
    if not np.all(np.isfinite(x)):
        x = problem.x0.copy()
    knots = knots_from_x(x)
    return _evaluate(problem, robot, x, knots, status, converged, stats, build_time, solve_time)


def _evaluate(
    problem: InitialGuessProblem,
    robot: RobotModel,
    x: np.ndarray,
    knots: np.ndarray,
    status: str,
    converged: bool,
    stats: dict,
    build_time: float,
    solve_time: float,
) -> InitialGuessResult:
    """Errors, costs, limit usage and binding rows of the solution x."""
    T = problem.T
    terms = np.asarray(problem.terms(x)).ravel()
    errs = tracking_errors(knots, T, problem.t_cost, problem.p_h, problem.R_h, problem.v_h, robot)
    usage, violations = check_command(knots, T, robot, problem.params)
    g = np.asarray(problem.g(x)).ravel()
    tol = ACTIVE_RTOL * np.maximum(
        np.where(np.isfinite(problem.ubg), np.abs(problem.ubg), np.abs(problem.lbg)), 1e-12
    )
    near = (np.abs(g - problem.lbg) <= tol) | (np.abs(problem.ubg - g) <= tol)
    active = {name: int(near[a:z].sum()) for name, (a, z) in problem.blocks.items()}
    feasible = not violations
    return InitialGuessResult(
        knots=readonly(knots),
        T=T,
        status=status,
        converged=converged,
        feasible=feasible,
        success=converged and feasible,
        cost=float(terms.sum()),
        cost_terms=MappingProxyType({k: float(v) for k, v in zip(COST_TERMS, terms, strict=True)}),
        max_errors=MappingProxyType({k: float(v.max()) for k, v in errs.items()}),
        rms_errors=MappingProxyType({k: float(np.sqrt(np.mean(v**2))) for k, v in errs.items()}),
        limit_usage=MappingProxyType(usage),
        active_limits=MappingProxyType(active),
        violations=tuple(violations),
        iterations=int(stats.get("iter_count", 0)),
        build_time=build_time,
        solve_time=solve_time,
    )


def initial_guess(
    demo_hand_t: np.ndarray,
    demo_hand_p: np.ndarray,
    demo_hand_R: np.ndarray,
    T: float,
    robot: RobotModel,
    *,
    params: InitialGuessParams | None = None,
    q_seed: np.ndarray | None = None,
) -> InitialGuessResult:
    """The initial command kappa_0 tracking the demonstration hand (module docstring).

    Args:
        demo_hand_t: Demonstration times, shape (k,) [s], within [0, T].
        demo_hand_p: Desired fingertip positions, shape (k, 3) [m], demonstration frame.
        demo_hand_R: Desired fingertip orientations, shape (k, 3, 3) (tip-site convention).
        T: Command duration [s] (the demonstration's hand-motion length).
        robot: Robot model.
        params: Weights, limits and settings (default: the paper's).
        q_seed: Seed joint angles (7,) [rad]; default ``HOME_Q``.

    Returns:
        The result (check ``success`` or call :func:`require_success`).

    Raises:
        ConfigError: Malformed inputs.
    """
    t0 = time.perf_counter()
    problem = build_problem(
        demo_hand_t, demo_hand_p, demo_hand_R, T, robot, params=params, q_seed=q_seed
    )
    built = time.perf_counter() - t0
    result = solve_problem(problem, robot)
    return replace(result, build_time=built + result.build_time)


__all__ = [
    "COST_TERMS",
    "HOME_Q",
    "IPOPT_SUCCESS",
    "LIMIT_BLOCKS",
    "N_X",
    "POSITION_MARGIN",
    "InitialGuessParams",
    "InitialGuessProblem",
    "InitialGuessResult",
    "build_problem",
    "check_command",
    "cost_samples",
    "hand_velocity",
    "initial_guess",
    "knots_from_x",
    "lift_matrix",
    "limit_sample_times",
    "require_success",
    "rotation_error_sq",
    "rotation_log",
    "solve_problem",
    "tracking_errors",
    "x_from_knots",
]

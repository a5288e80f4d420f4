"""The learner's system model and its linearisation M = dx(t) / dkappa (paper eq. dynamics, dyn).

The model maps the command knots kappa (10, 8) to the rope state (paper eq. dynamics):

    q(t)     = B(kappa[:7], T)(t)                      joints, Bezier [rad]
    b(t)     = B(kappa[7:], T)(t)                      base offset, Bezier [m] (constant in a trial)
    p_tip(t) = K_p(q(t)) + b(t),  d_tip(t) = K_R(q(t)) e_z      fingertip in the demo frame
    x(t)     = f(p_tip, d_tip, z_0),  x = [p_1..p_11, v_1..v_11] (66,)  [m, m/s]

with K the robot's forward kinematics in its base frame (:mod:`learner.kinematics`) and f the
paper's rope model (:mod:`learner.rope_model`) on the grid t_k = k dt (:func:`model_times`).
The demonstration frame is the robot base frame shifted by b (no rotation), so the rope sees
p_tip = K_p(q) + b and the rope direction is not affected by b.

Linearisation point. As in the paper, the model is linearised about the rollout driven by the
*measured* robot motion (:func:`rollout_from_joints`): the measured joints are resampled onto
the model grid, the rope starts in the static hanging state at the first sample, and the
rollout is simulated. The derivative is taken with the model's assumption q = q_d (the robot
follows its command), so dq(t_k)/dkappa is the Bezier basis while the kinematic Jacobians are
evaluated at the measured joints:

    dp_tip(t_k)/dkappa[j, i] = dK_p/dq_j(q_k) b_i(t_k)           (arm rows j = 0..6)
    dd_tip(t_k)/dkappa[j, i] = d(K_R e_z)/dq_j(q_k) b_i(t_k)
    dp_tip(t_k)/dkappa[7 + c, i] = e_c b_i(t_k),  dd_tip/dkappa[7 + c, i] = 0   (base rows)

These input derivatives dU (K+1, 6, 80) are chained through the rope model by the implicit
function theorem (:func:`learner.rope_sensitivity.state_sensitivity`). The initial state also
moves with the command: the rope starts at rest in the hanging equilibrium of the first
fingertip pose, so dx_0/dkappa = [dp_0/du_0 dU_0; 0] with dp_0/du_0 from the implicit function
theorem on the static equilibrium (:func:`learner.rope_sensitivity.hanging_sensitivity`). For a
rope hanging straight down this is exactly "every point shifts with the tip" (dp_i/dp_tip = I;
the model is translation invariant) plus the rope's response to tilting the tube.

Everything here returns plain derivatives with respect to the knots, flattened row-major
(knot (row r, j) at column 8 r + j), the convention of :mod:`learner.inverse_qp`.
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from flyknot.constants import (
    COMMAND_RATE_HZ,
    MARKER_RATE_HZ,
    MODEL_DT,
    N_BASE_ROWS,
    N_JOINTS,
    N_KNOTS,
    N_VARS,
)
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, check_choice, check_positive
from flyknot.geometry import matrix_to_quat
from flyknot.record import TrialRecord
from learner.bezier import BezierCommand, bernstein_basis, check_knots
from learner.kinematics import RobotModel
from learner.rope_model import (
    NEWTON_TOL,
    RopeModelParams,
    RopeTrajectory,
    hanging_state,
    rollout,
)
from learner.rope_sensitivity import check_steps, hanging_sensitivity, state_sensitivity

INTERPOLATIONS = ("cubic", "linear")
HANG_TOL = 1e-13  # [m] position-change tolerance of the initial hanging state
_GRID_SLACK = 1e-9  # relative slack when T is (almost) a multiple of dt
_TIME_SLACK = 1e-9  # [s] slack when checking that measured joints cover the model grid


# --------------------------------------------------------------------------------------------
# grid and the critical step
# --------------------------------------------------------------------------------------------


def _float(name: str, value: object) -> float:
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        value = float(value)
    check_positive(name, value)  # type: ignore[arg-type]
    return value  # type: ignore[return-value]


def model_times(T: float, dt: float = MODEL_DT) -> np.ndarray:
    """The model grid t_k = k dt, k = 0..K, with K = floor(T / dt) (up to rounding).

    The grid stops at the last multiple of dt not after T (T is the command duration, which
    need not be a multiple of dt).

    Args:
        T: Command duration [s], > 0.
        dt: Model step [s], > 0.

    Returns:
        Times, shape (K+1,) [s].
    """
    T = _float("T", T)
    dt = _float("dt", dt)
    K = int(np.floor(T / dt * (1.0 + _GRID_SLACK) + _GRID_SLACK))
    return np.minimum(np.arange(K + 1) * dt, T)


def critical_step(t_c: float, dt: float, T: float) -> int:
    """Model step nearest the critical time: k_c = floor(t_c / dt + 1/2) (halves round up).

    The step is capped at the last grid step K = floor(T / dt) (only reachable when T is not a
    multiple of dt and t_c lies within dt / 2 of T).

    Args:
        t_c: Critical time on the command's clock [s], 0 <= t_c < T.
        dt: Model step [s].
        T: Command duration [s].

    Returns:
        k_c, an index into :func:`model_times`.

    Raises:
        ConfigError: if t_c is not in [0, T).
    """
    T = _float("T", T)
    dt = _float("dt", dt)
    if not (isinstance(t_c, numbers.Real) and np.isfinite(t_c) and 0.0 <= t_c < T):
        raise ConfigError("t_c", f"must lie in [0, T) = [0, {T:g}) s, got {t_c!r}")
    K = len(model_times(T, dt)) - 1
    return min(int(np.floor(float(t_c) / dt + 0.5)), K)


# --------------------------------------------------------------------------------------------
# the initial hanging state and its sensitivity
# --------------------------------------------------------------------------------------------


def initial_state(
    p_tip0: np.ndarray, d_tip0: np.ndarray, params: RopeModelParams
) -> tuple[np.ndarray, np.ndarray]:
    """The rope at rest in its hanging equilibrium at the first fingertip pose.

    Args:
        p_tip0: Fingertip, shape (3,) [m] (demo frame).
        d_tip0: Tube direction, shape (3,) (unit).
        params: Rope model parameters.

    Returns:
        (p_0 (N, 3) [m], v_0 = 0 (N, 3) [m/s]), converged to :data:`HANG_TOL`.
    """
    return hanging_state(p_tip0, d_tip0, params, tol=HANG_TOL)


# --------------------------------------------------------------------------------------------
# rollouts
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ModelRollout:
    """A rollout of the system model and the joint samples that drove it.

    Attributes:
        t: Model times, shape (k+1,) [s] (a prefix of :func:`model_times`).
        q: Joint samples used, shape (k+1, 7) [rad].
        base: Base offset at each sample, shape (k+1, 3) [m].
        p_tip: Fingertip in the demo frame, K_p(q) + base, shape (k+1, 3) [m].
        d_tip: Tube direction K_R(q) e_z, shape (k+1, 3) (unit).
        traj: The rope rollout (its x is the model state, (k+1, 66)).
        robot: The robot model that produced p_tip and d_tip.
    """

    t: np.ndarray
    q: np.ndarray
    base: np.ndarray
    p_tip: np.ndarray
    d_tip: np.ndarray
    traj: RopeTrajectory
    robot: RobotModel = field(repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("t", "q", "base", "p_tip", "d_tip"):
            a = np.array(getattr(self, name), dtype=float, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @property
    def x(self) -> np.ndarray:
        """Model states [p_1..p_N, v_1..v_N], shape (k+1, 6N) [m, m/s]."""
        return self.traj.x

    @property
    def params(self) -> RopeModelParams:
        """Rope model parameters of the rollout."""
        return self.traj.params

    @property
    def n_steps(self) -> int:
        """Number k of model steps simulated."""
        return self.traj.n_steps


def tip_inputs(
    robot: RobotModel, q: np.ndarray, base: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rope inputs from joints: p_tip = K_p(q) + b, d_tip = K_R(q) e_z.

    Args:
        robot: Robot model.
        q: Joints, shape (m, 7) [rad].
        base: Base offset, shape (3,) or (m, 3) [m].

    Returns:
        p_tip (m, 3) [m] in the demo frame, d_tip (m, 3) (unit), R_tip (m, 3, 3).
    """
    q = np.asarray(q, dtype=float)
    st = robot.tip_states(q, np.zeros_like(q))
    return st.p + np.asarray(base, dtype=float), st.R[:, :, 2].copy(), st.R


def _simulate(
    t: np.ndarray,
    q: np.ndarray,
    base: np.ndarray,
    robot: RobotModel,
    params: RopeModelParams,
    newton_tol: float,
) -> ModelRollout:
    p_tip, d_tip, _ = tip_inputs(robot, q, base)
    p0, v0 = initial_state(p_tip[0], d_tip[0], params)
    traj = rollout(p_tip, d_tip, params, p0, v0, tol=newton_tol)
    base = np.broadcast_to(np.asarray(base, dtype=float), p_tip.shape)
    return ModelRollout(t=t, q=q, base=base, p_tip=p_tip, d_tip=d_tip, traj=traj, robot=robot)


def _n_steps(n_steps: int | None, K: int) -> int:
    if n_steps is None:
        return K
    if isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral):
        raise ConfigError("n_steps", f"must be an integer in [1, {K}], got {n_steps!r}")
    if not 1 <= n_steps <= K:
        raise ConfigError("n_steps", f"must be an integer in [1, {K}], got {n_steps!r}")
    return int(n_steps)


def _check_params(params: object) -> RopeModelParams:
    if not isinstance(params, RopeModelParams):
        raise ConfigError("rope_params", f"must be a RopeModelParams, got {type(params).__name__}")
    return params


def simulate_command(
    knots: np.ndarray,
    T: float,
    robot: RobotModel,
    rope_params: RopeModelParams,
    *,
    n_steps: int | None = None,
    newton_tol: float = NEWTON_TOL,
) -> ModelRollout:
    """Run the system model under a command with the model's own joints, q = B(kappa, T).

    x(t_k) = f(K_p(B(kappa[:7])(t_k)) + B(kappa[7:])(t_k), K_R(...) e_z, z_0), k = 0..n_steps,
    with z_0 the hanging state at t = 0 (see the module docstring). The base rows are sampled
    as curves, so a perturbation of a single base knot is seen as the model would see it.

    Args:
        knots: Knots, shape (10, 8) (rows 0-6 [rad], rows 7-9 [m]).
        T: Duration [s].
        robot: Robot model.
        rope_params: Rope model parameters (their dt is the grid step).
        n_steps: Simulate steps 0..n_steps only (default the whole grid).
        newton_tol: Newton tolerance of the rope steps [m].

    Returns:
        The :class:`ModelRollout`.
    """
    params = _check_params(rope_params)
    t = model_times(T, params.dt)
    k = _n_steps(n_steps, len(t) - 1)
    t = t[: k + 1]
    y = bernstein_basis(t, T) @ check_knots(knots).T
    return _simulate(t, y[:, :N_JOINTS], y[:, N_JOINTS:], robot, params, newton_tol)


def resample_joints(
    t_src: np.ndarray, q_src: np.ndarray, t: np.ndarray, interpolation: str = "cubic"
) -> np.ndarray:
    """Resample measured joints onto other times.

    ``"cubic"``: a not-a-knot cubic spline through the samples (scipy CubicSpline), error
    O(h^4 q'''') for smooth motion; ``"linear"``: piecewise-linear, error <= h^2 |q''| / 8
    (2e-4 rad at 250 Hz and 100 rad/s^2).

    Args:
        t_src: Sample times, shape (n,) [s], strictly increasing, covering t.
        q_src: Joints, shape (n, 7) [rad].
        t: Query times, shape (m,) [s].
        interpolation: ``"cubic"`` or ``"linear"``.

    Returns:
        Joints at t, shape (m, 7) [rad].
    """
    check_choice("interpolation", interpolation, INTERPOLATIONS)
    t_src = np.asarray(t_src, dtype=float)
    q_src = np.asarray(q_src, dtype=float)
    t = np.asarray(t, dtype=float)
    if t_src.ndim != 1 or t_src.size < 2:
        raise ConfigError("q_meas_t", f"must have shape (n,) with n >= 2, got {t_src.shape}")
    if q_src.shape != (t_src.size, N_JOINTS):
        raise ConfigError(
            "q_meas", f"must have shape ({t_src.size}, {N_JOINTS}), got {q_src.shape}"
        )
    if not (np.all(np.isfinite(t_src)) and np.all(np.diff(t_src) > 0)):
        raise ConfigError("q_meas_t", "must be finite and strictly increasing")
    if not np.all(np.isfinite(q_src)):
        raise ConfigError("q_meas", "must be finite")
    if t.min() < t_src[0] - _TIME_SLACK or t.max() > t_src[-1] + _TIME_SLACK:
        raise ConfigError(
            "q_meas_t",
            f"must cover the model grid [{t.min():.4f}, {t.max():.4f}] s, "
            f"got [{t_src[0]:.4f}, {t_src[-1]:.4f}] s",
        )
    t = np.clip(t, t_src[0], t_src[-1])
    if interpolation == "linear":
        return np.stack([np.interp(t, t_src, q_src[:, j]) for j in range(N_JOINTS)], axis=1)
    return CubicSpline(t_src, q_src, axis=0)(t)


def rollout_from_joints(
    q_meas_t: np.ndarray,
    q_meas: np.ndarray,
    base_offset: np.ndarray,
    robot: RobotModel,
    rope_params: RopeModelParams,
    T: float,
    *,
    interpolation: str = "cubic",
    n_steps: int | None = None,
    newton_tol: float = NEWTON_TOL,
) -> ModelRollout:
    """The model rollout driven by the measured robot motion (the paper's linearisation point).

    q(t_k) = resample(q_meas)(t_k) on t_k = k dt (:func:`resample_joints`; joint velocities are
    not needed: the rope model takes fingertip positions and directions only),
    p_tip = K_p(q) + b, d_tip = K_R(q) e_z, the rope hanging at rest at t_0, then
    :func:`learner.rope_model.rollout`.

    Args:
        q_meas_t: Measured joint times, shape (n,) [s] on the command's clock.
        q_meas: Measured joints, shape (n, 7) [rad].
        base_offset: The command's base offset, shape (3,) [m].
        robot: Robot model.
        rope_params: Rope model parameters (their dt is the grid step).
        T: Command duration [s].
        interpolation: ``"cubic"`` (default) or ``"linear"``.
        n_steps: Simulate steps 0..n_steps only (default the whole grid up to T).
        newton_tol: Newton tolerance of the rope steps [m].

    Returns:
        The :class:`ModelRollout`.

    Raises:
        ConfigError: on malformed inputs or measured joints that do not cover the grid.
        SolverError: if the rope model fails.
    """
    params = _check_params(rope_params)
    t = model_times(T, params.dt)
    k = _n_steps(n_steps, len(t) - 1)
    t = t[: k + 1]
    base = np.asarray(base_offset, dtype=float)
    if base.shape != (N_BASE_ROWS,) or not np.all(np.isfinite(base)):
        raise ConfigError("base_offset", f"must be finite with shape (3,), got {base.shape}")
    q = resample_joints(q_meas_t, q_meas, t, interpolation)
    return _simulate(t, q, base, robot, params, newton_tol)


# --------------------------------------------------------------------------------------------
# linearisation
# --------------------------------------------------------------------------------------------


def input_jacobian(rollout_: ModelRollout, T: float, upto: int | None = None) -> np.ndarray:
    """dU/dkappa: derivatives of the rope inputs (p_tip, d_tip) with respect to the knots.

    dU[k, 0:3, 8 j + i] = dK_p/dq_j(q_k) b_i(t_k),  dU[k, 3:6, 8 j + i] = dK_d/dq_j(q_k) b_i(t_k)
    for joints j = 0..6, and dU[k, c, 8 (7 + c) + i] = b_i(t_k) for the base rows c = 0..2.

    Args:
        rollout_: The linearisation point.
        T: Command duration [s] (the Bezier basis).
        upto: Fill steps 0..upto only (later rows stay zero); default all.

    Returns:
        dU, shape (k+1, 6, 80) [m/rad, 1/rad; m/m].
    """
    n = rollout_.t.size
    upto = n - 1 if upto is None else upto
    t = rollout_.t[: upto + 1]
    basis = bernstein_basis(t, T)  # (m, 8)
    q = rollout_.q[: upto + 1]
    jac = rollout_.robot.tip_jacobians(q, np.zeros_like(q))
    m = t.size
    dU = np.zeros((n, 6, N_VARS))
    arm = N_JOINTS * N_KNOTS
    dU[:m, :3, :arm] = np.einsum("kaj,ki->kaji", jac.dp_dq, basis).reshape(m, 3, arm)
    dU[:m, 3:, :arm] = np.einsum("kaj,ki->kaji", jac.dd_dq, basis).reshape(m, 3, arm)
    for c in range(N_BASE_ROWS):
        col = (N_JOINTS + c) * N_KNOTS
        dU[:m, c, col : col + N_KNOTS] = basis
    return dU


def linearise(rollout: ModelRollout, T: float, steps: Iterable[int]) -> np.ndarray:
    """M(t_k) = dx(t_k)/dkappa at the given model steps (paper eq. dyn).

    dx_0 = [dp_0/du_0 dU_0; 0] (:func:`learner.rope_sensitivity.hanging_sensitivity`), then per
    step the implicit function theorem on the rope step
    (:func:`learner.rope_sensitivity.state_sensitivity`) with dU from :func:`input_jacobian`.

    Args:
        rollout: The linearisation point (:func:`rollout_from_joints` or
            :func:`simulate_command`).
        T: Command duration [s].
        steps: Model step indices (0..rollout.n_steps).

    Returns:
        dX, shape (len(steps), 66, 80) [m/rad, m/m; m/(s rad), m/(s m)].

    Raises:
        ConfigError: on steps outside the rollout.
    """
    if not isinstance(rollout, ModelRollout):
        raise ConfigError("rollout", f"must be a ModelRollout, got {type(rollout).__name__}")
    T = _float("T", T)
    if rollout.t[-1] > T * (1.0 + _GRID_SLACK):
        raise ConfigError("T", f"must be >= the rollout's last time {rollout.t[-1]:g} s")
    steps = check_steps(steps, rollout.n_steps)
    params = rollout.params
    n = params.n_links
    dU = input_jacobian(rollout, T, upto=max(steps))
    S0 = hanging_sensitivity(rollout.traj.p[0], rollout.p_tip[0], rollout.d_tip[0], params)
    dx0 = np.zeros((6 * n, N_VARS))
    dx0[: 3 * n] = S0 @ dU[0]
    return state_sensitivity(rollout.traj, dU, dx0=dx0, steps=steps)


# --------------------------------------------------------------------------------------------
# the model as a mismatch-free "real system" (tests, benchmarks)
# --------------------------------------------------------------------------------------------


def _positions_at(t_model: np.ndarray, p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of p (k+1, N, 3) from t_model onto t (m,) -> (m, N, 3)."""
    flat = p.reshape(p.shape[0], -1)
    out = np.stack([np.interp(t, t_model, flat[:, c]) for c in range(flat.shape[1])], axis=1)
    return out.reshape(t.size, *p.shape[1:])


def model_record(
    command: BezierCommand,
    robot: RobotModel,
    rope_params: RopeModelParams,
    *,
    newton_tol: float = NEWTON_TOL,
) -> TrialRecord:
    """A :class:`TrialRecord` of the system model itself run as the real system.

    The robot follows its command exactly (q_meas = q_cmd at 250 Hz); markers at 200 Hz are
    the model's rope positions linearly interpolated in time; the robot base sits at the mocap
    origin with identity orientation (``base_pose = (0, 0, 0, 1, 0, 0, 0)``), so lab-frame
    positions are demo-frame positions minus the base offset. Covers [0, T].

    Args:
        command: The command.
        robot: Robot model.
        rope_params: Rope model parameters.
        newton_tol: Newton tolerance of the rope steps [m].

    Returns:
        The record (metadata ``{"cell": "model"}``).
    """
    ro = simulate_command(command.knots, command.T, robot, rope_params, newton_tol=newton_tol)
    base = command.base_offset
    t_joint = command.sample_times(COMMAND_RATE_HZ)
    q = command.joint_command(COMMAND_RATE_HZ).q
    p_tip, _, R_tip = tip_inputs(robot, q, np.zeros(3))
    t_marker = np.arange(int(np.floor(command.T * MARKER_RATE_HZ + 1e-9)) + 1) / MARKER_RATE_HZ
    markers = _positions_at(ro.t, ro.traj.p, np.minimum(t_marker, ro.t[-1])) - base
    return TrialRecord(
        t_joint=t_joint,
        q_cmd=q,
        q_meas=q,
        t_marker=t_marker,
        markers=markers,
        fingertip_pos=p_tip,
        fingertip_quat=matrix_to_quat(R_tip),
        base_pose=np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
        metadata={"cell": "model"},
    )


def model_demonstration(
    command: BezierCommand,
    t_c: float,
    robot: RobotModel,
    rope_params: RopeModelParams,
    *,
    newton_tol: float = NEWTON_TOL,
) -> Demonstration:
    """A trimmed :class:`Demonstration` made by the system model under a command.

    Samples at 200 Hz over [0, T]: hand = the model fingertip (demo frame, pose of the tip
    frame), markers = the model's rope positions (demo frame), t_c as given.

    Args:
        command: The command that "demonstrates".
        t_c: Critical time [s] in [0, T].
        robot: Robot model.
        rope_params: Rope model parameters.
        newton_tol: Newton tolerance of the rope steps [m].

    Returns:
        The demonstration (metadata ``{"generator": "model"}``).
    """
    ro = simulate_command(command.knots, command.T, robot, rope_params, newton_tol=newton_tol)
    t = np.arange(int(np.floor(command.T * MARKER_RATE_HZ + 1e-9)) + 1) / MARKER_RATE_HZ
    t = np.minimum(t, ro.t[-1])
    y = command.sample(t)
    p_tip, _, R_tip = tip_inputs(robot, y[:, :N_JOINTS], y[:, N_JOINTS:])
    return Demonstration(
        t=t,
        hand_pos=p_tip,
        hand_quat=matrix_to_quat(R_tip),
        markers=_positions_at(ro.t, ro.traj.p, t),
        t_c=t_c,
        metadata={"generator": "model"},
    )


__all__ = [
    "INTERPOLATIONS",
    "ModelRollout",
    "critical_step",
    "initial_state",
    "input_jacobian",
    "linearise",
    "model_demonstration",
    "model_record",
    "model_times",
    "resample_joints",
    "rollout_from_joints",
    "simulate_command",
    "tip_inputs",
]

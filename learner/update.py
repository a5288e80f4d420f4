"""One Task-Level ILC update (paper, Algorithm 1 and eq. inverse_model_qp).

Given the trial just run (its :class:`TrialRecord`), the command that was played and the
demonstration target, :func:`ilc_update` returns the knot update dkappa and the next knots
kappa_{k+1} = kappa_k - dkappa:

1. Error. err = x_meas(t_c) - x_demo(t_c) (66,) in the demo frame, both by the same local
   marker fit (:mod:`learner.critical_state`). For the equally weighted baseline the same at
   every pre-collision model step t_k <= t_c where both the record and the demonstration have
   markers (samples with lost tracking are skipped).
2. Linearisation point. The model rollout driven by the measured joints
   (:func:`learner.system_model.rollout_from_joints`), simulated only as far as needed (t_c).
3. M = dx(t)/dkappa at the error samples (:func:`learner.system_model.linearise`).
4. Follow-through. Fingertip errors against the matched demonstration hand at t_c and at
   every model step after it up to T (:func:`learner.follow_through.follow_through_terms`).
5. Limits, by constraint generation. All linearised limit rows (position, velocity,
   acceleration, torque) on the 250 Hz command samples are built once
   (:func:`learner.inverse_qp.limit_rows`). The first QP holds only the rows whose current
   value uses at least ``margin`` (default 50 %) of its range, |b - mid| >= margin * half.
   After each solve every row on the full grid is checked at the new knots (linearised,
   b - J dkappa); violated rows (beyond ``LIMIT_TOL`` of the half range) are added and the QP
   is solved again, at most ``max_rounds`` times; if rows are still violated after that, a
   last solve uses every row. The accepted update therefore satisfies every linearised row:
   exactly for position, velocity and acceleration (linear in the knots) and to first order
   for torque.
6. Solve with Clarabel or OSQP. A QP that does not solve returns ``solved=False``, the old
   knots as ``new_knots``, NaN in ``dkappa`` and the solver's status: it is never applied.

The base rows of the update are projected onto the equality constraint after the solve (their
mean over the 8 knots for ``base_update="constant"``, zero for ``"zero"``), removing the
solver's ~1e-9 residual so that the new knots pass :class:`learner.bezier.BezierCommand`'s
exact constant-base check.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flyknot.constants import COMMAND_RATE_HZ, MODEL_DT, N_JOINTS, N_KNOTS, N_ROWS
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError, check_choice, check_nonnegative, check_positive
from flyknot.geometry import readonly, so3_exp, so3_log
from flyknot.limits import JointLimits
from flyknot.record import TrialRecord
from learner.bezier import BezierCommand, sample_command
from learner.critical_state import (
    MarkerFitParams,
    critical_state_from_record,
    local_polyfit_state,
    markers_state_at,
)
from learner.follow_through import follow_through_terms
from learner.inverse_qp import (
    BACKENDS,
    BASE_UPDATES,
    InverseModelWeights,
    LimitRows,
    QPResult,
    build_inverse_qp,
    limit_rows,
    solve_qp,
)
from learner.kinematics import RobotModel
from learner.rope_model import RopeModelParams
from learner.system_model import critical_step, linearise, model_times, rollout_from_joints

OBJECTIVES = ("critical", "equal")
LIMIT_TOL = 1e-6  # a limit row counts as violated beyond this fraction of its half range
STATE_DIM = 66
_ROT_TOL = 1e-6
_TIME_TOL = 1e-9  # [s]


# --------------------------------------------------------------------------------------------
# the target
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class DemoTarget:
    """What the learner aims for, on the model grid of the command's clock (0 = start).

    Attributes:
        t_c: Critical time [s], 0 <= t_c < T.
        T: Command duration [s].
        dt: Model step [s]; the grid is :func:`learner.system_model.model_times` (K+1 steps).
        x_c: Demonstration rope state at t_c, [p_1..p_11, v_1..v_11] (66,) [m, m/s].
        hand_p: Demonstration hand position on the grid, (K+1, 3) [m] (demo frame).
        hand_rot: Demonstration hand orientation on the grid, (K+1, 3, 3).
        hand_v: Demonstration hand velocity on the grid, (K+1, 3) [m/s].
        x_pre: Demonstration rope states at the pre-collision steps k = 0..S-1 (t_k <= t_c),
            (S, 66); a row is NaN where the demonstration's markers were lost.
    """

    t_c: float
    T: float
    dt: float
    x_c: np.ndarray
    hand_p: np.ndarray
    hand_rot: np.ndarray
    hand_v: np.ndarray
    x_pre: np.ndarray

    def __post_init__(self) -> None:
        for name in ("T", "dt"):
            v = getattr(self, name)
            if isinstance(v, numbers.Real) and not isinstance(v, bool):
                v = float(v)
            check_positive(name, v)
            object.__setattr__(self, name, v)
        t_c = self.t_c
        if not (isinstance(t_c, numbers.Real) and np.isfinite(t_c) and 0.0 <= t_c < self.T):
            raise ConfigError("t_c", f"must lie in [0, T) = [0, {self.T:g}) s, got {t_c!r}")
        object.__setattr__(self, "t_c", float(t_c))
        k1 = self.t.size
        n_pre = int(np.sum(self.t <= self.t_c + _TIME_TOL))
        want = {
            "x_c": (STATE_DIM,),
            "hand_p": (k1, 3),
            "hand_rot": (k1, 3, 3),
            "hand_v": (k1, 3),
            "x_pre": (n_pre, STATE_DIM),
        }
        for name, shape in want.items():
            a = readonly(getattr(self, name))
            if a.shape != shape:
                raise ConfigError(name, f"must have shape {shape}, got {a.shape}")
            finite = np.isfinite(a)
            if name == "x_pre":
                partial = ~(finite.all(axis=1) | (~finite).all(axis=1))
                if partial.any():
                    raise ConfigError(
                        name, f"row {int(np.argmax(partial))} is partly NaN (whole rows only)"
                    )
            elif not finite.all():
                raise ConfigError(name, "must be finite")
            object.__setattr__(self, name, a)
        RtR = np.swapaxes(self.hand_rot, 1, 2) @ self.hand_rot
        dev = float(np.max(np.abs(RtR - np.eye(3))))
        if dev > _ROT_TOL or np.any(np.linalg.det(self.hand_rot) <= 0):
            raise ConfigError(
                "hand_rot", f"must hold rotation matrices (R^T R - I up to {dev:.2g})"
            )

    @property
    def t(self) -> np.ndarray:
        """Model grid, shape (K+1,) [s]."""
        return model_times(self.T, self.dt)

    def hand_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Demonstration hand at times t, interpolated on the grid.

        p, v piecewise linear; R(t) = R_i Exp(s Log(R_i^T R_{i+1})), s = (t - t_i) / dt
        (geodesic). Times beyond the last grid step hold its value.

        Args:
            t: Times, shape (m,) [s] in [0, T].

        Returns:
            (p (m, 3) [m], R (m, 3, 3), v (m, 3) [m/s]).
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        grid = self.t
        if (
            t.ndim != 1
            or not np.all(np.isfinite(t))
            or t.min() < -_TIME_TOL
            or (t.max() > self.T + _TIME_TOL)
        ):
            raise ConfigError("t", f"must be finite times in [0, {self.T:g}] s")
        t = np.clip(t, 0.0, grid[-1])
        if grid.size == 1:
            m = t.size
            return (
                np.repeat(self.hand_p, m, 0),
                np.repeat(self.hand_rot, m, 0),
                np.repeat(self.hand_v, m, 0),
            )
        i = np.minimum((t / self.dt).astype(int), grid.size - 2)
        s = np.clip((t - grid[i]) / self.dt, 0.0, 1.0)[:, None]
        p = (1 - s) * self.hand_p[i] + s * self.hand_p[i + 1]
        v = (1 - s) * self.hand_v[i] + s * self.hand_v[i + 1]
        Ri = self.hand_rot[i]
        rel = so3_log(np.swapaxes(Ri, 1, 2) @ self.hand_rot[i + 1])
        R = Ri @ so3_exp(s * rel)
        return p, R, v

    @classmethod
    def from_demonstration(
        cls,
        demo: Demonstration,
        dt: float = MODEL_DT,
        fit: MarkerFitParams | None = None,
    ) -> DemoTarget:
        """Build the target from a trimmed demonstration (its first sample is t = 0).

        T = t[-1] - t[0], t_c on the command clock = demo.t_c - t[0]. On the model grid:
        hand position and velocity by the local polynomial fit of
        :func:`learner.critical_state.local_polyfit_state` (the same rule as the marker
        states), hand orientation by spherical linear interpolation of the quaternions; the
        rope states at t_c and at the pre-collision steps by
        :func:`learner.critical_state.markers_state_at` (NaN rows where markers are lost).

        Args:
            demo: The trimmed demonstration (demo frame, z up).
            dt: Model step [s].
            fit: Marker/hand fit parameters (default :class:`MarkerFitParams()`).

        Returns:
            The target.

        Raises:
            RecordError: if the demonstration's markers are lost at t_c.
            ConfigError: if t_c is not before the end of the demonstration.
        """
        if not isinstance(demo, Demonstration):
            raise ConfigError("demo", f"must be a Demonstration, got {type(demo).__name__}")
        fit = MarkerFitParams() if fit is None else fit
        td = demo.t - demo.t[0]
        T = float(td[-1])
        t_c = float(demo.t_c - demo.t[0])
        if not t_c < T:
            raise ConfigError("demo.t_c", f"must lie before the demonstration's end {T:g} s")
        grid = model_times(T, dt)
        hp = np.empty((grid.size, 3))
        hv = np.empty((grid.size, 3))
        for k, tk in enumerate(grid):
            hp[k], hv[k] = local_polyfit_state(td, demo.hand_pos, float(tk), fit)
        rots = Rotation.from_quat(np.asarray(demo.hand_quat), scalar_first=True)
        hR = Slerp(td, rots)(grid).as_matrix()
        p, v = markers_state_at(td, demo.markers, t_c, fit)
        x_c = np.concatenate([p.ravel(), v.ravel()])
        pre = grid[grid <= t_c + _TIME_TOL]
        x_pre = np.full((pre.size, STATE_DIM), np.nan)
        for k, tk in enumerate(pre):
            try:
                p, v = markers_state_at(td, demo.markers, float(tk), fit)
            except RecordError:
                continue
            x_pre[k] = np.concatenate([p.ravel(), v.ravel()])
        return cls(t_c=t_c, T=T, dt=dt, x_c=x_c, hand_p=hp, hand_rot=hR, hand_v=hv, x_pre=x_pre)


# --------------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """Outcome of one ILC update.

    Attributes:
        dkappa: Knot update (10, 8), subtracted from the knots; NaN when not solved.
        new_knots: kappa_k - dkappa (10, 8); the old knots when not solved.
        qp_status: The solver's status text of the last solve.
        solved: True when the QP solved and the update may be applied.
        cost_before: Critical-point cost ||err||_Q^2 at the current knots.
        predicted_cost_after: Model-predicted critical-point cost ||err - M dkappa||_Q^2.
        err: Critical-point error x_meas(t_c) - x_demo(t_c) (66,) [m, m/s] (NaN if the
            record lost tracking before t_c, allowed for the equal objective only).
        timings: Wall times [s]: error, rollout, linearise, follow_through, limit_rows,
            qp_build, qp_solve (both summed over rounds), total.
        objective: ``"critical"`` or ``"equal"``.
        backend: QP solver.
        n_error_samples: Error samples in the objective (1 for critical).
        limit_rounds: QP solves made (constraint-generation rounds).
        n_limit_rows: Limit rows in the last QP (of ``n_limit_rows_total``).
        n_limit_rows_total: Limit rows on the full 250 Hz grid (0 without limits).
        limit_violation: Largest linearised row violation b - J dkappa over the full grid,
            as a fraction of the row's half range (0 when all rows hold or without limits).
        qp_objective: The QP's cost at the solution (NaN when not solved).
        sampled_violation: Largest violation of the *updated* command's own limits on its
            250 Hz samples (q, qd, qdd exact; torque by inverse dynamics, so the torque
            linearisation error shows here), as a fraction of the half range (0 when all
            hold, without limits or when not solved).
        t_eff: Time of the critical point actually used [s]: t_c, or the fallback time
            before it when the record lost tracking before t_c.
    """

    dkappa: np.ndarray
    new_knots: np.ndarray
    qp_status: str
    solved: bool
    cost_before: float
    predicted_cost_after: float
    err: np.ndarray
    timings: Mapping[str, float] = field(default_factory=dict)
    objective: str = "critical"
    backend: str = "clarabel"
    n_error_samples: int = 1
    limit_rounds: int = 1
    n_limit_rows: int = 0
    n_limit_rows_total: int = 0
    limit_violation: float = 0.0
    qp_objective: float = float("nan")
    sampled_violation: float = 0.0
    t_eff: float = float("nan")

    def __post_init__(self) -> None:
        for name in ("dkappa", "new_knots"):
            a = readonly(getattr(self, name))
            if a.shape != (N_ROWS, N_KNOTS):
                raise ConfigError(name, f"must have shape ({N_ROWS}, {N_KNOTS}), got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "err", readonly(self.err))
        object.__setattr__(self, "timings", MappingProxyType(dict(self.timings)))


# --------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------


def _q_weights(weights: InverseModelWeights) -> np.ndarray:
    """Diagonal of Q = diag(w_crit_pos I_33, w_crit_vel I_33), (66,)."""
    half = STATE_DIM // 2
    return np.concatenate([np.full(half, weights.w_crit_pos), np.full(half, weights.w_crit_vel)])


def _row_scale(rows: LimitRows) -> tuple[np.ndarray, np.ndarray]:
    """Mid point and half range of every row (half range 1 where a bound is infinite)."""
    lo, hi = rows.lo, rows.hi
    finite = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    mid = np.where(finite, 0.5 * (lo + hi), 0.0)
    half = np.where(finite, 0.5 * (hi - lo), 1.0)
    return mid, half


def initial_active_rows(rows: LimitRows, margin: float) -> np.ndarray:
    """Rows whose current value uses at least ``margin`` of the range: |b - mid| >= m * half.

    Args:
        rows: All limit rows.
        margin: Fraction in [0, 1]; 0 selects every row.

    Returns:
        Sorted row indices.
    """
    mid, half = _row_scale(rows)
    return np.flatnonzero(np.abs(rows.b - mid) >= margin * half)


def limit_violation(rows: LimitRows, dkappa: np.ndarray) -> np.ndarray:
    """Linearised violation of every row after the update, relative to the half range.

    y = b - J dkappa,  viol = max(lo - y, y - hi, 0) / half.

    Args:
        rows: Limit rows.
        dkappa: Update (10, 8) or (80,).

    Returns:
        Violations, shape (r,) (0 where the row holds).
    """
    _, half = _row_scale(rows)
    y = rows.b - rows.J @ np.asarray(dkappa, dtype=float).ravel()
    return np.maximum(0.0, np.maximum(rows.lo - y, y - rows.hi)) / half


def sampled_violation(
    knots: np.ndarray, T: float, t: np.ndarray, robot: RobotModel, limits: JointLimits
) -> float:
    """Largest violation of the limits by a command on its samples, relative to half ranges.

    max over samples, joints and kinds of max(lo - y, y - hi, 0) / ((hi - lo) / 2) for
    y = q, qd, qdd (Bezier, exact) and tau = ID(q, qd, qdd).

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        t: Sample times (m,) [s].
        robot: Robot model (inverse dynamics).
        limits: The limits.

    Returns:
        The violation (0 when every limit holds).
    """
    q, qd, qdd = (sample_command(knots, T, t, r)[:, :N_JOINTS] for r in (0, 1, 2))
    worst = 0.0
    for y, lo, hi in (
        (q, limits.q_min, limits.q_max),
        (qd, -limits.qd_max, limits.qd_max),
        (qdd, -limits.qdd_max, limits.qdd_max),
        (robot.torques(q, qd, qdd), -limits.tau_max, limits.tau_max),
    ):
        over = np.maximum(lo - y, y - hi) / (0.5 * (hi - lo))
        worst = max(worst, float(over.max()))
    return worst


def subset_rows(rows: LimitRows, idx: np.ndarray) -> LimitRows:
    """The rows ``idx`` (sorted) of ``rows``, with the named blocks kept contiguous."""
    idx = np.asarray(idx, dtype=int)
    blocks = {}
    for name, (a, z) in rows.blocks.items():
        start = int(np.searchsorted(idx, a))
        stop = int(np.searchsorted(idx, z))
        blocks[name] = (start, stop)
    return LimitRows(J=rows.J[idx], b=rows.b[idx], lo=rows.lo[idx], hi=rows.hi[idx], blocks=blocks)


def _project_base(dk: np.ndarray, base_update: str) -> np.ndarray:
    dk = np.array(dk, dtype=float)
    if base_update == "zero":
        dk[N_JOINTS:] = 0.0
    else:
        dk[N_JOINTS:] = dk[N_JOINTS:].mean(axis=1, keepdims=True)
    return dk


def _check_margin(margin: object) -> float:
    if not (isinstance(margin, numbers.Real) and 0.0 <= margin <= 1.0):
        raise ConfigError("margin", f"must be a number in [0, 1], got {margin!r}")
    return float(margin)


def _check_rounds(max_rounds: object) -> int:
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, numbers.Integral):
        raise ConfigError("max_rounds", f"must be an integer >= 1, got {max_rounds!r}")
    if max_rounds < 1:
        raise ConfigError("max_rounds", f"must be an integer >= 1, got {max_rounds!r}")
    return int(max_rounds)


# --------------------------------------------------------------------------------------------
# the update
# --------------------------------------------------------------------------------------------


def _fallback_critical_point(
    record: TrialRecord,
    target: DemoTarget,
    base: np.ndarray,
    fit: MarkerFitParams,
    fallback_s: float,
) -> tuple[int, np.ndarray]:
    """The latest model step k with t_c - fallback_s <= t_k < t_c (by default any step) where
    the record's and the demonstration's marker states both exist, and the error there,
    x_meas(t_k) - x_demo(t_k).

    Raises:
        RecordError: no such step (tracking lost before t_c - fallback_s).
    """
    check_nonnegative("fallback_s", fallback_s)
    grid = target.t
    for k in range(len(target.x_pre) - 1, -1, -1):
        if grid[k] >= target.t_c - _TIME_TOL:
            continue
        if grid[k] < target.t_c - fallback_s - _TIME_TOL:
            break
        if not np.all(np.isfinite(target.x_pre[k])):
            continue
        try:
            x = critical_state_from_record(record, float(grid[k]), base, fit)
        except RecordError:
            continue
        return k, x - target.x_pre[k]
    raise RecordError(
        f"tracking lost before t_c = {target.t_c:.3f} s and no state within "
        f"{fallback_s:.3f} s before it"
    )


def ilc_update(
    record: TrialRecord,
    command: BezierCommand,
    demo_target: DemoTarget,
    robot: RobotModel,
    rope_params: RopeModelParams,
    weights: InverseModelWeights | None = None,
    *,
    objective: str = "critical",
    backend: str = "clarabel",
    limits: JointLimits | None = JointLimits(),  # noqa: B008 (frozen, compared by value)
    follow_through: bool = True,
    base_update: str = "constant",
    margin: float = 0.5,
    max_rounds: int = 4,
    interpolation: str = "cubic",
    fit: MarkerFitParams | None = None,
    solver_settings: Mapping[str, object] | None = None,
    fallback_s: float = 10.0,
    trust_region: float | None = None,
    extra_records: Sequence[TrialRecord] = (),
) -> UpdateResult:
    """One ILC update: measured error -> linearised model -> inverse-model QP -> new knots.

    Solves (module docstring; :func:`learner.inverse_qp.build_inverse_qp` for the cost)

        min_dk ||M(t_c) dk - err||_Q^2 + sum_{t >= t_c} ||e_ft(t) - J_ft(t) dk||_W(t)^2
               + w_control ||dk_arm||^2
        s.t.   base rows of dk constant (or zero);  lo <= b - J dk <= hi (limit rows)

    and returns kappa_{k+1} = kappa_k - dk.

    Args:
        record: The trial's record (markers in the lab frame, joints on the command clock).
        command: The command that was played (knots, T, base offset).
        demo_target: The target (:meth:`DemoTarget.from_demonstration`); its T must equal the
            command's and its dt the rope model's.
        robot: Robot model.
        rope_params: Rope model parameters.
        weights: QP weights (default: the paper's).
        objective: ``"critical"`` (the paper's) or ``"equal"`` (every pre-collision sample
            weighted equally).
        backend: ``"clarabel"`` (default) or ``"osqp"``.
        limits: Joint limits on the updated command, or None for none.
        follow_through: Include the follow-through fingertip terms.
        base_update: ``"constant"`` or ``"zero"`` (see :mod:`learner.inverse_qp`).
        margin: Initial active-set threshold of the constraint generation, in [0, 1].
        max_rounds: Most constraint-generation solves before a solve with every row.
        interpolation: Resampling of the measured joints, ``"cubic"`` or ``"linear"``.
        fit: Marker fit parameters of the measured (and equal-objective) states (default
            :class:`MarkerFitParams()`).
        solver_settings: Extra settings for the QP solver.
        fallback_s: When the record lost tracking before t_c (the rope touched itself
            early), the critical point falls back to the latest model step within
            ``fallback_s`` before t_c at which both the record and the demonstration give a
            marker state (``UpdateResult.t_eff``); 0 disables the fallback.
        trust_region: Largest change of any arm knot [rad] (a box in the QP), or None.
        extra_records: Earlier plays of the same command: the critical-point error is the
            mean over ``record`` and those of them that kept tracking to t_c (the
            follow-through term uses ``record`` alone).

    Returns:
        The :class:`UpdateResult`.

    Raises:
        ConfigError: on inconsistent inputs.
        RecordError: if the record lost tracking before t_c - fallback_s (critical
            objective) or has no usable sample (equal objective).
        SolverError: if the rope model fails on the measured motion.
    """
    t_all = time.perf_counter()
    timings = dict.fromkeys(
        (
            "error",
            "rollout",
            "linearise",
            "follow_through",
            "limit_rows",
            "qp_build",
            "qp_solve",
        ),
        0.0,
    )
    check_choice("objective", objective, OBJECTIVES)
    check_choice("backend", backend, BACKENDS)
    check_choice("base_update", base_update, BASE_UPDATES)
    margin = _check_margin(margin)
    max_rounds = _check_rounds(max_rounds)
    if not isinstance(record, TrialRecord):
        raise ConfigError("record", f"must be a TrialRecord, got {type(record).__name__}")
    if not isinstance(command, BezierCommand):
        raise ConfigError("command", f"must be a BezierCommand, got {type(command).__name__}")
    if not isinstance(demo_target, DemoTarget):
        raise ConfigError("demo_target", f"must be a DemoTarget, got {type(demo_target).__name__}")
    if not isinstance(rope_params, RopeModelParams):
        raise ConfigError(
            "rope_params", f"must be a RopeModelParams, got {type(rope_params).__name__}"
        )
    if limits is not None and not isinstance(limits, JointLimits):
        raise ConfigError("limits", f"must be a JointLimits or None, got {type(limits).__name__}")
    weights = InverseModelWeights() if weights is None else weights
    fit = MarkerFitParams() if fit is None else fit
    T = command.T
    if abs(T - demo_target.T) > 1e-9 * max(1.0, T):
        raise ConfigError(
            "command.T", f"must equal the target's T = {demo_target.T:g} s, got {T:g} s"
        )
    if abs(rope_params.dt - demo_target.dt) > 1e-12:
        raise ConfigError(
            "rope_params.dt",
            f"must equal the target's model step {demo_target.dt:g} s, got {rope_params.dt:g} s",
        )
    knots = command.knots
    base = command.base_offset
    t_c = demo_target.t_c
    grid = demo_target.t
    k_c = critical_step(t_c, demo_target.dt, T)
    qw = _q_weights(weights)

    # 1. errors
    t0 = time.perf_counter()
    t_eff = t_c
    try:
        err = critical_state_from_record(record, t_c, base, fit) - demo_target.x_c
        # Averaged over earlier plays of the same command (those that kept tracking to t_c):
        # err = mean_i (x_i(t_c) - x_demo(t_c)); each play's noise averages out.
        errs = [err]
        for other in extra_records:
            try:
                errs.append(critical_state_from_record(other, t_c, base, fit) - demo_target.x_c)
            except RecordError:
                continue
        err = np.mean(errs, axis=0)
    except RecordError:
        if objective == "critical":
            k_c, err = _fallback_critical_point(record, demo_target, base, fit, fallback_s)
            t_eff = float(grid[k_c])
        else:
            err = np.full(STATE_DIM, np.nan)
    samples: list[tuple[int, np.ndarray]] = []
    if objective == "equal":
        for k, x_demo in enumerate(demo_target.x_pre):
            if not np.all(np.isfinite(x_demo)):
                continue
            try:
                x_meas = critical_state_from_record(record, float(grid[k]), base, fit)
            except RecordError:
                continue
            samples.append((k, x_meas - x_demo))
        if not samples:
            raise RecordError(
                "no pre-collision model step has markers in both the record and the "
                "demonstration (equal objective)"
            )
    timings["error"] = time.perf_counter() - t0

    # 2-3. linearisation point and M
    steps = sorted({k_c, *(k for k, _ in samples)})
    t0 = time.perf_counter()
    ro = rollout_from_joints(
        record.t_joint,
        record.q_meas,
        base,
        robot,
        rope_params,
        T,
        interpolation=interpolation,
        n_steps=max(1, steps[-1]),
    )
    timings["rollout"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    dX = linearise(ro, T, steps)
    timings["linearise"] = time.perf_counter() - t0
    M_c = dX[steps.index(k_c)]

    # 4. follow-through
    follow = None
    if follow_through:
        t0 = time.perf_counter()
        t_ft = np.concatenate([[t_c], grid[grid > t_c + _TIME_TOL]])
        hand = demo_target.hand_at(t_ft)
        follow = follow_through_terms(knots, T, t_ft, t_c, *hand, robot)
        timings["follow_through"] = time.perf_counter() - t0

    # 5. limit rows on the full 250 Hz grid
    rows = None
    if limits is not None:
        t0 = time.perf_counter()
        rows = limit_rows(knots, T, command.sample_times(COMMAND_RATE_HZ), robot, limits)
        timings["limit_rows"] = time.perf_counter() - t0

    if objective == "critical":
        qp_terms = {"M_crit": M_c, "err_crit": err}
    else:
        qp_terms = {"equal": [(dX[steps.index(k)], e) for k, e in samples]}

    def solve(idx: np.ndarray | None) -> QPResult:
        t1 = time.perf_counter()
        lim = None if rows is None or idx is None or idx.size == 0 else subset_rows(rows, idx)
        qp = build_inverse_qp(
            **qp_terms,
            weights=weights,
            follow=follow,
            limits=lim,
            base_update=base_update,
            trust_region=trust_region,
        )
        timings["qp_build"] += time.perf_counter() - t1
        t1 = time.perf_counter()
        res = solve_qp(qp, backend, **dict(solver_settings or {}))
        timings["qp_solve"] += time.perf_counter() - t1
        return res

    # 6. solve, with constraint generation
    idx = None if rows is None else initial_active_rows(rows, margin)
    rounds = 0
    res = solve(idx)
    rounds += 1
    viol = np.zeros(0)
    if rows is not None and res.solved:
        tol = LIMIT_TOL
        while True:
            viol = limit_violation(rows, res.dkappa)
            new = np.setdiff1d(np.flatnonzero(viol > tol), idx)
            if new.size == 0:
                break
            idx = np.union1d(idx, new) if rounds < max_rounds else np.arange(rows.n_rows)
            res = solve(idx)
            rounds += 1
            if not res.solved:
                break
            if idx.size == rows.n_rows:
                viol = limit_violation(rows, res.dkappa)
                break

    n_rows_qp = 0 if idx is None else int(idx.size)
    n_total = 0 if rows is None else rows.n_rows
    cost_before = float(np.sum(qw * err**2))
    sampled = 0.0
    if res.solved:
        dk = _project_base(res.dkappa, base_update)
        if rows is not None:
            viol = limit_violation(rows, dk)
        new_knots = knots - dk
        if limits is not None:
            sampled = sampled_violation(
                new_knots, T, command.sample_times(COMMAND_RATE_HZ), robot, limits
            )
        r = err - M_c @ dk.ravel()
        predicted = float(np.sum(qw * r**2))
    else:
        dk = np.full((N_ROWS, N_KNOTS), np.nan)
        new_knots = knots.copy()
        predicted = float("nan")
    timings["total"] = time.perf_counter() - t_all
    return UpdateResult(
        dkappa=dk,
        new_knots=new_knots,
        qp_status=res.status,
        solved=bool(res.solved),
        cost_before=cost_before,
        predicted_cost_after=predicted,
        err=err,
        timings=timings,
        objective=objective,
        backend=backend,
        n_error_samples=1 if objective == "critical" else len(samples),
        limit_rounds=rounds,
        n_limit_rows=n_rows_qp,
        n_limit_rows_total=n_total,
        limit_violation=float(viol.max()) if (res.solved and viol.size) else 0.0,
        qp_objective=float(res.objective),
        sampled_violation=sampled,
        t_eff=t_eff,
    )


__all__ = [
    "LIMIT_TOL",
    "OBJECTIVES",
    "DemoTarget",
    "UpdateResult",
    "ilc_update",
    "initial_active_rows",
    "limit_violation",
    "sampled_violation",
    "subset_rows",
]

"""One Task-Level ILC update (paper, Algorithm 1 and eq. inverse_model_qp).

Given the trial just run (its :class:`TrialRecord`), the command that was played and the
demonstration target (:class:`learner.target.DemoTarget`), :func:`ilc_update` returns the knot
update dkappa and the next knots kappa_{k+1} = kappa_k - dkappa; :class:`UpdateSettings` holds
what stays fixed over a run (objective, weights, limits, solver):

1. Error. err = x_meas(t_c) - x_demo(t_c) (66,) in the demo frame, both by the same local
   marker fit (:mod:`learner.critical_state`). For the equally weighted baseline the same at
   every pre-collision model step t_k <= t_c where both the record and the demonstration have
   markers (samples with lost tracking are skipped).
2. Linearisation point. The model rollout driven by the measured joints
   (:func:`learner.system_model.rollout_from_joints`), simulated only as far as needed (t_c).
3. M = dx(t)/dkappa at the error samples (:func:`learner.system_model.linearise`).
4. Follow-through. Fingertip errors against the matched demonstration hand at t_c and at
   every model step after it up to T (:func:`learner.follow_through.follow_through_terms`).
5. Limits, by constraint generation (:mod:`learner.limit_rows`). All linearised limit rows
   (position, velocity, acceleration, torque) on the 250 Hz command samples are built once
   (:func:`learner.limit_rows.limit_rows`). The first QP holds only the rows whose current
   value uses at least ``margin`` (default 50 %) of its range, |b - mid| >= margin * half.
   After each solve every row on the full grid is checked at the new knots (linearised,
   b - J dkappa); violated rows (beyond ``LIMIT_TOL`` of the half range) are added and the QP
   is solved again, at most ``max_rounds`` times; if rows are still violated after that, a
   last solve uses every row. The accepted update therefore satisfies every linearised row:
   exactly for position, velocity and acceleration (linear in the knots) and to first order
   for torque.
6. Solve with Clarabel or OSQP (:func:`learner.inverse_qp.build_inverse_qp`, then
   :func:`learner.qp_solve.solve_qp`). A QP that does not solve returns ``solved=False``,
   the current knots as ``new_knots``, NaN in ``dkappa`` and the solver's status: it is never
   applied.

The base rows of the update are projected onto the equality constraint after the solve (their
mean over the 8 knots for ``base_update="constant"``, zero for ``"zero"``), removing the
solver's ~1e-9 residual so that the new knots pass :class:`learner.bezier.BezierCommand`'s
exact constant-base check.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import ConfigError, check_choice, check_nonnegative, check_positive
from flyknot.geometry import readonly
from flyknot.limits import JointLimits
from flyknot.options import NOT_AN_OPTION, ReadOnlyMap
from flyknot.record import TrialRecord
from learner.bezier import BezierCommand
from learner.critical_state import MarkerFitParams
from learner.follow_through import FollowThrough, follow_through_terms
from learner.inverse_qp import BASE_UPDATES, InverseModelWeights, build_inverse_qp
from learner.jacobians import jacobian_kind
from learner.kinematics import RobotModel
from learner.limit_rows import (
    GeneratedSolve,
    LimitRows,
    generate_constraints,
    limit_rows,
    limit_violation,
    sampled_violation,
)
from learner.objectives import OBJECTIVES, objective_kind
from learner.qp_solve import BACKENDS, QPResult, solve_qp
from learner.rope_model import RopeModelParams
from learner.system_model import (
    INTERPOLATIONS,
    critical_step,
    linearise,
    rollout_from_joints,
)
from learner.target import STATE_DIM, TIME_TOL, DemoTarget

_TIMED = ("error", "rollout", "linearise", "follow_through", "limit_rows", "qp_build", "qp_solve")


# --------------------------------------------------------------------------------------------
# settings and result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class UpdateSettings:
    """How :func:`ilc_update` forms and solves the inverse-model QP; fixed over a run.

    Attributes:
        objective: A name of :data:`learner.objectives.OBJECTIVES`: ``"critical"`` (the
            paper's), ``"equal"`` (every pre-collision sample weighted equally), ``"launch"``.
        weights: QP weights (default: the paper's).
        limits: Joint limits on the updated command, or None for none (the cell's: set by
            the program, not an option a file gives).
        follow_through: Include the follow-through fingertip terms.
        base_update: ``"constant"`` or ``"zero"`` (see :mod:`learner.inverse_qp`).
        trust_region: Largest change of any arm knot [rad] (a box in the QP), or None.
        backend: QP solver, ``"clarabel"`` (default) or ``"osqp"``.
        margin: Initial active-set threshold of the constraint generation, in [0, 1].
        max_rounds: Most constraint-generation solves before a solve with every row (>= 1).
        solver_settings: Extra settings for the QP solver (kept read-only).
        interpolation: Resampling of the measured joints, ``"cubic"`` or ``"linear"``.
        fit: Marker fit parameters of the measured (and equal-objective) states.
        fallback_s: When the record lost tracking before t_c (the rope touched itself
            early), the critical point falls back to the latest model step within
            ``fallback_s`` before t_c at which both the record and the demonstration give a
            marker state (``UpdateResult.t_eff``); 0 disables the fallback.
        jacobian: Where M(t_c) comes from (:data:`learner.jacobians.JACOBIANS`):
            ``"model"`` (the paper's), ``"secant"`` (the model's, corrected from the measured
            trials) or ``"oracle"`` (the simulated lab's own, measured).

    Raises:
        ConfigError: on an unknown choice or a value out of range.
    """

    objective: str = "critical"
    weights: InverseModelWeights = field(default_factory=InverseModelWeights)
    limits: JointLimits | None = field(default_factory=JointLimits, metadata=NOT_AN_OPTION)
    follow_through: bool = True
    base_update: str = "constant"
    trust_region: float | None = None
    backend: str = "clarabel"
    margin: float = 0.5
    max_rounds: int = 4
    solver_settings: Mapping[str, object] = field(default_factory=dict)
    interpolation: str = "cubic"
    fit: MarkerFitParams = field(default_factory=MarkerFitParams)
    fallback_s: float = 10.0
    jacobian: str = "model"

    def __post_init__(self) -> None:
        objective = objective_kind(self.objective)
        kind = jacobian_kind(self.jacobian)
        if (kind.needs_provider or kind.learns) and not objective.takes_jacobian:
            raise ConfigError("jacobian", f"{self.jacobian!r} is for the critical objective only")
        check_choice("backend", self.backend, BACKENDS)
        check_choice("base_update", self.base_update, BASE_UPDATES)
        check_choice("interpolation", self.interpolation, INTERPOLATIONS)
        margin = self.margin
        if not (isinstance(margin, numbers.Real) and 0.0 <= margin <= 1.0):
            raise ConfigError("margin", f"must be a number in [0, 1], got {margin!r}")
        rounds = self.max_rounds
        if isinstance(rounds, bool) or not isinstance(rounds, numbers.Integral) or rounds < 1:
            raise ConfigError("max_rounds", f"must be an integer >= 1, got {rounds!r}")
        if not isinstance(self.follow_through, (bool, np.bool_)):
            raise ConfigError("follow_through", f"must be a bool, got {self.follow_through!r}")
        if self.trust_region is not None:
            check_positive("trust_region", self.trust_region)
        check_nonnegative("fallback_s", self.fallback_s)
        for name, cls, want in (
            ("weights", InverseModelWeights, "an InverseModelWeights"),
            ("fit", MarkerFitParams, "a MarkerFitParams"),
            ("limits", (JointLimits, type(None)), "a JointLimits or None"),
            ("solver_settings", Mapping, "a mapping"),
        ):
            value = getattr(self, name)
            if not isinstance(value, cls):
                raise ConfigError(name, f"must be {want}, got {type(value).__name__}")
        object.__setattr__(self, "follow_through", bool(self.follow_through))
        object.__setattr__(self, "margin", float(margin))
        object.__setattr__(self, "max_rounds", int(rounds))
        object.__setattr__(self, "solver_settings", ReadOnlyMap(self.solver_settings))


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """Outcome of one ILC update.

    Attributes:
        dkappa: Knot update (10, 8), subtracted from the knots; NaN when not solved.
        new_knots: kappa_k - dkappa (10, 8); the current knots when not solved.
        qp_status: The solver's status text of the last solve.
        solved: True when the QP solved and the update may be applied.
        cost_before: Critical-point cost ||err||_Q^2 at the current knots.
        predicted_cost_after: Model-predicted critical-point cost ||err - M dkappa||_Q^2.
        err: Critical-point error x_meas(t_c) - x_demo(t_c) (66,) [m, m/s] (NaN if the
            record lost tracking before t_c, allowed for the equal objective only).
        timings: Wall times [s]: error, rollout, linearise, follow_through, limit_rows,
            qp_build, qp_solve (both summed over rounds), total.
        objective: A name of :data:`learner.objectives.OBJECTIVES`.
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
        object.__setattr__(self, "timings", ReadOnlyMap(self.timings))


# --------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------


@contextmanager
def _timed(timings: dict[str, float], key: str) -> Iterator[None]:
    """Add the wall time of the block to ``timings[key]``."""
    t0 = time.perf_counter()
    yield
    timings[key] += time.perf_counter() - t0


def _q_weights(weights: InverseModelWeights) -> np.ndarray:
    """Diagonal of Q = diag(w_crit_pos I_33, w_crit_vel I_33), (66,)."""
    return weights.critical_diagonal(STATE_DIM)


def _project_base(dk: np.ndarray, base_update: str) -> np.ndarray:
    dk = np.array(dk, dtype=float)
    if base_update == "zero":
        dk[N_JOINTS:] = 0.0
    else:
        dk[N_JOINTS:] = dk[N_JOINTS:].mean(axis=1, keepdims=True)
    return dk


def _check_inputs(
    record: object, command: object, target: object, rope_params: object, settings: object
) -> None:
    """Types of the inputs of :func:`ilc_update`, and the command's T and the model step
    against the target's."""
    for name, value, cls in (
        ("record", record, TrialRecord),
        ("command", command, BezierCommand),
        ("demo_target", target, DemoTarget),
        ("rope_params", rope_params, RopeModelParams),
        ("settings", settings, UpdateSettings),
    ):
        if not isinstance(value, cls):
            article = "an" if cls.__name__[0] in "AEIOU" else "a"
            raise ConfigError(name, f"must be {article} {cls.__name__}, got {type(value).__name__}")
    T = command.T
    if abs(T - target.T) > 1e-9 * max(1.0, T):
        raise ConfigError("command.T", f"must equal the target's T = {target.T:g} s, got {T:g} s")
    if abs(rope_params.dt - target.dt) > 1e-12:
        raise ConfigError(
            "rope_params.dt",
            f"must equal the target's model step {target.dt:g} s, got {rope_params.dt:g} s",
        )


def _given_jacobians(
    jacobian: Mapping[float, object], objective: str, dt: float, T: float
) -> dict[int, np.ndarray]:
    """Jacobians handed to :func:`ilc_update` as ``{t [s]: M(t)}``, by model step
    k = floor(t / dt + 1/2), each checked by :func:`_given_jacobian`."""
    if not isinstance(jacobian, Mapping):
        kind = type(jacobian).__name__
        raise ConfigError("jacobian", f"must map times [s] to (66, 80) arrays, got {kind}")
    return {critical_step(t, dt, T): _given_jacobian(M, objective) for t, M in jacobian.items()}


def _given_jacobian(jacobian: object, objective: str) -> np.ndarray:
    """A Jacobian handed to :func:`ilc_update`, checked: (66, 80), finite, an objective that
    takes one."""
    if not objective_kind(objective).takes_jacobian:
        raise ConfigError("jacobian", f"is for the critical objective only, not {objective!r}")
    M = np.asarray(jacobian, dtype=float)
    if M.shape != (STATE_DIM, N_ROWS * N_KNOTS):
        raise ConfigError(
            "jacobian", f"must have shape ({STATE_DIM}, {N_ROWS * N_KNOTS}), got {M.shape}"
        )
    if not np.all(np.isfinite(M)):
        raise ConfigError("jacobian", "must be finite")
    return M


# --------------------------------------------------------------------------------------------
# the update
# --------------------------------------------------------------------------------------------


def _checked_step(
    res: QPResult,
    viol: np.ndarray,
    rows: LimitRows | None,
    knots: np.ndarray,
    T: float,
    t_samples: np.ndarray,
    robot: RobotModel,
    s: UpdateSettings,
    M_c: np.ndarray,
    err: np.ndarray,
    qw: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, float]:
    """The solved step as it is applied, and what it does.

    dk = P(dkappa) (the base rows projected, ``s.base_update``), kappa_{k+1} = kappa - dk,
    the predicted cost ||err - M_c dk||_Q^2 and the limit rows' violations (the QP's rows at
    the projected step; every 250 Hz sample of the new command). An unsolved QP gives a
    NaN step and the knots unchanged.

    Returns:
        ``(dk (10, 8), new_knots (10, 8), predicted cost, violation per active row,
        sampled violation)``.
    """
    if not res.solved:
        return np.full((N_ROWS, N_KNOTS), np.nan), knots.copy(), float("nan"), viol, 0.0
    dk = _project_base(res.dkappa, s.base_update)
    if rows is not None and not np.array_equal(dk[:N_JOINTS], res.dkappa[:N_JOINTS]):
        viol = limit_violation(rows, dk)  # the limits see the joint rows only
    new_knots = knots - dk
    sampled = 0.0
    if s.limits is not None:
        sampled = sampled_violation(new_knots, T, t_samples, robot, s.limits)
    r = err - M_c @ dk.ravel()
    return dk, new_knots, float(np.sum(qw * r**2)), viol, sampled


def _held(qp_terms: dict) -> dict:
    """The objective's QP terms with every error taken as zero: ||M dk||_Q^2 each, a step
    that keeps the fitted rope states where the model predicts them."""

    def zero(pairs):
        return [(M, np.zeros_like(e)) for M, e in pairs]

    held = {k: zero(v) for k, v in qp_terms.items() if k in ("equal", "points")}
    if "err_crit" in qp_terms:
        held |= {"M_crit": qp_terms["M_crit"], "err_crit": np.zeros_like(qp_terms["err_crit"])}
    return held


def _held_follow(follow: FollowThrough | None) -> FollowThrough | None:
    """The follow-through terms with their errors taken as zero (None stays None)."""
    return None if follow is None else replace(follow, e=np.zeros_like(follow.e))


def _generated(
    qp_terms: dict,
    follow: FollowThrough | None,
    rows: LimitRows | None,
    s: UpdateSettings,
    timings: dict[str, float],
    center: np.ndarray | None = None,
) -> GeneratedSolve:
    """The inverse-model QP of ``qp_terms`` (its control term pulled toward ``center``) built
    and solved with the limit rows generated as they are violated
    (:func:`learner.limit_rows.generate_constraints`); build and solve times added to
    ``timings``."""

    def solve(lim: LimitRows | None) -> QPResult:
        with _timed(timings, "qp_build"):
            qp = build_inverse_qp(
                **qp_terms,
                weights=s.weights,
                follow=follow,
                limits=lim,
                base_update=s.base_update,
                trust_region=s.trust_region,
                center=center,
            )
        with _timed(timings, "qp_solve"):
            return solve_qp(qp, s.backend, **dict(s.solver_settings))

    return generate_constraints(rows, solve, s.margin, s.max_rounds)


def ilc_update(
    record: TrialRecord,
    command: BezierCommand,
    demo_target: DemoTarget,
    robot: RobotModel,
    rope_params: RopeModelParams,
    settings: UpdateSettings | None = None,
    *,
    extra_records: Sequence[TrialRecord] = (),
    jacobian: Mapping[float, np.ndarray] | None = None,
    correct: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    explore: np.ndarray | None = None,
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
        settings: Objective, weights, limits and solver (default :class:`UpdateSettings()`:
            the paper's).
        extra_records: Earlier plays of the same command: the critical-point error is the
            mean over ``record`` and those of them that kept tracking to t_c (the
            follow-through term uses ``record`` alone).
        jacobian: ``{t [s]: M(t)}``, M(t) = dx(t)/dkappa (66, 80) [m/unit, m/s/unit] at
            the objective's fitted times, used in place of the rope model's linearisation
            there (:mod:`learner.jacobians`: an oracle's taken in a simulated lab); the
            model's at any time it lacks (e.g. a fallback critical point). Objectives that
            fit the critical point only. None: the model's everywhere.
        correct: ``correct(M_model (66, 80), err (66,)) -> M``, the model's M(t_c) corrected
            (:class:`learner.jacobians.SecantCorrection`) when ``jacobian`` does not give it;
            objectives that fit the critical point only. Called only when the critical error
            is measured at t_c: a record that lost its markers before t_c is fitted at an
            earlier step with the model's M there, and the correction, which maps steps onto
            changes of the error at t_c, neither learns from it nor applies to it.
        explore: An exploring update toward the knot update r (10, 8) [rad]: every fitted
            error taken as zero (the step keeps the objective's rope states, and the
            follow-through, where the model predicts them) and the control term pulled
            toward r, w_control ||dk_arm - r_arm||^2
            (:func:`learner.inverse_qp.build_inverse_qp`'s ``center``). None: the update.

    Returns:
        The :class:`UpdateResult`.

    Raises:
        ConfigError: on inconsistent inputs.
        RecordError: if the record lost tracking before t_c - fallback_s (critical
            objective) or has no usable sample (equal objective).
        SolverError: if the rope model fails on the measured motion.
    """
    t_all = time.perf_counter()
    timings = dict.fromkeys(_TIMED, 0.0)
    s = UpdateSettings() if settings is None else settings
    _check_inputs(record, command, demo_target, rope_params, s)
    knots, T, base = command.knots, command.T, command.base_offset
    t_c, grid = demo_target.t_c, demo_target.t
    t_samples = command.sample_times(COMMAND_RATE_HZ)

    # 1. errors
    with _timed(timings, "error"):
        objective = objective_kind(s.objective)
        k_target = critical_step(t_c, demo_target.dt, T)
        records = (record, *extra_records)
        terms = objective.errors(records, base, demo_target, k_target, s.fit, s.fallback_s)
        err, k_c, t_eff, samples = terms.err, terms.k_c, terms.t_eff, terms.samples

    # 2-3. linearisation point and M (or the given Jacobian)
    steps = sorted({k_c, *(k for k, _ in samples)})
    given = {} if jacobian is None else _given_jacobians(jacobian, s.objective, demo_target.dt, T)
    if all(k in given for k in steps):
        dX = [given[k] for k in steps]
    else:
        with _timed(timings, "rollout"):
            ro = rollout_from_joints(
                record.t_joint,
                record.q_meas,
                base,
                robot,
                rope_params,
                T,
                interpolation=s.interpolation,
                n_steps=max(1, steps[-1]),
            )
        with _timed(timings, "linearise"):
            dX = [given.get(k, M) for k, M in zip(steps, linearise(ro, T, steps), strict=True)]
    M_c = dX[steps.index(k_c)]
    if correct is not None and k_c == k_target and k_c not in given:
        M_c = _given_jacobian(correct(M_c, err), s.objective)

    # 4. follow-through
    follow = None
    if s.follow_through:
        with _timed(timings, "follow_through"):
            t_ft = np.concatenate([[t_c], grid[grid > t_c + TIME_TOL]])
            hand = demo_target.hand_at(t_ft)
            follow = follow_through_terms(knots, T, t_ft, t_c, *hand, robot)

    # 5. limit rows on the full 250 Hz grid
    rows = None
    if s.limits is not None:
        with _timed(timings, "limit_rows"):
            rows = limit_rows(knots, T, t_samples, robot, s.limits)

    # 6. solve, with constraint generation
    qp_terms = objective.qp_terms(terms, lambda k: dX[steps.index(k)], M_c)
    if explore is not None:
        qp_terms, follow = _held(qp_terms), _held_follow(follow)
    gen = _generated(qp_terms, follow, rows, s, timings, explore)
    res, viol = gen.result, gen.violation

    # the update, checked
    qw = _q_weights(s.weights)
    dk, new_knots, predicted, viol, sampled = _checked_step(
        res, viol, rows, knots, T, t_samples, robot, s, M_c, err, qw
    )
    timings["total"] = time.perf_counter() - t_all
    return UpdateResult(
        dkappa=dk,
        new_knots=new_knots,
        qp_status=res.status,
        solved=bool(res.solved),
        cost_before=float(np.sum(qw * err**2)),
        predicted_cost_after=predicted,
        err=err,
        timings=timings,
        objective=s.objective,
        backend=s.backend,
        n_error_samples=len(samples) or 1,
        limit_rounds=gen.rounds,
        n_limit_rows=0 if gen.active is None else int(gen.active.size),
        n_limit_rows_total=0 if rows is None else rows.n_rows,
        limit_violation=float(viol.max()) if (res.solved and viol.size) else 0.0,
        qp_objective=float(res.objective),
        sampled_violation=sampled,
        t_eff=t_eff,
    )


__all__ = ["OBJECTIVES", "UpdateResult", "UpdateSettings", "ilc_update"]

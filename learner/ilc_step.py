"""One step of the ILC loop: assess a trial, then decide what the loop does next.

:func:`assess` turns a trial's record into its ledger line and the update (the critical-point
error, the inverse-model QP: :func:`learner.update.ilc_update`). :func:`decide` takes that
and the loop's state and returns the :class:`Step`: the line as written, the next command or
why the loop stops. The stop rules (:mod:`learner.stops`) rule on every attempt; their memory
lives in :class:`LoopState`, and a resumed run rebuilds it by replaying its ledger through the
same rules (:mod:`learner.ilc`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from flyknot.errors import RecordError, SolverError
from flyknot.judge import KnotJudge
from flyknot.limits import JointLimits
from flyknot.record import TrialRecord
from learner.bezier import BezierCommand
from learner.ilc_params import ILCParams
from learner.inverse_qp import InverseModelWeights
from learner.jacobians import (
    JacobianProvider,
    SecantCorrection,
    jacobian_kind,
    provided_jacobian,
)
from learner.kinematics import RobotModel
from learner.limit_rows import sampled_violation
from learner.objectives import error_at, objective_kind
from learner.run_directory import TrialSummary
from learner.stops import REPLAY, RETRY, STEP, StopRules
from learner.target import DemoTarget
from learner.trial_view import Trial
from learner.update import UpdateResult, ilc_update

UPDATE_FAILED = "update failed"
"""The start of a ledger line's ``update_status`` when the update raised (the learner's model
failed on the trial's measured motion): the trial counts, its command is played again."""


def critical_cost(err: np.ndarray, weights: InverseModelWeights) -> float:
    """||err||_Q^2 with Q = diag(w_crit_pos I_33, w_crit_vel I_33); err (66,) [m, m/s]."""
    err = np.asarray(err, dtype=float)
    half = err.size // 2
    return float(
        weights.w_crit_pos * err[:half] @ err[:half] + weights.w_crit_vel * err[half:] @ err[half:]
    )


@dataclass
class LoopState:
    """Algorithm 1's state between trials.

    Attributes:
        k: The trial being played (0-based, counted trials).
        knots: kappa_k, the command of trial k, (10, 8).
        prev_knots: kappa_{k-1}, or None before the first update.
        trials: Every attempt's ledger line so far.
        rules: The stop rules and their memories (:class:`learner.stops.StopRules`: the
            confirmation, the safeguard, the plays being averaged, the damped step's).
        secant: The secant Jacobian's memory (``jacobian = "secant"``), or None.
        stop: Why the loop stops, once it does.
    """

    k: int
    knots: np.ndarray
    prev_knots: np.ndarray | None
    trials: list[TrialSummary]
    rules: StopRules
    secant: SecantCorrection | None = None
    stop: str | None = None

    @classmethod
    def initial(cls, knots0: np.ndarray, params: ILCParams) -> LoopState:
        """Before the first trial: kappa_0 and empty memories."""
        knots = np.asarray(knots0, dtype=float)
        learns = jacobian_kind(params.update.jacobian).learns
        secant = SecantCorrection() if learns else None
        return cls(0, knots, None, [], StopRules(params), secant=secant)

    def correct(self, knots: np.ndarray, *, learn: bool = True):
        """The model-Jacobian correction of an update about ``knots`` (the secant source's,
        learning from this trial when ``learn``), or None."""
        if self.secant is None:
            return None
        return partial(self.secant.corrected, knots, learn=learn)

    def w_control(self) -> float | None:
        """The QP's control weight of the next update: the damped step's lambda, or None
        (the run's own weights)."""
        return self.rules.w_control()

    def attempts(self, params: ILCParams) -> list[int]:
        """The attempts of trial k still to play (a resumed run skips the ledger's)."""
        done = {s.attempt for s in self.trials if s.trial == self.k}
        return [a for a in range(params.tracking_retries + 1) if a not in done]

    def advance(self, step: Step) -> None:
        """After trial k's last attempt: stop, or kappa_{k+1} = the step's command."""
        if step.stop is not None:
            self.stop = step.stop
        else:
            self.prev_knots, self.knots = self.knots, step.new
            self.k += 1


@dataclass(frozen=True)
class Step:
    """What the loop does after one attempt.

    Attributes:
        summary: The attempt's ledger line, as written.
        update: The update computed from it (None: none), as written.
        new: The next trial's command (None: none yet, or the loop stops).
        stop: Why the loop stops now, or None.
        last: Whether this was the trial's last attempt.
    """

    summary: TrialSummary
    update: UpdateResult | None
    new: np.ndarray | None
    stop: str | None
    last: bool


@dataclass(frozen=True)
class Context:
    """What every step is decided against: the target, the learner's models and settings,
    and a measured Jacobian's provider when the run's ``jacobian`` source needs one."""

    target: DemoTarget
    robot: RobotModel
    params: ILCParams
    limits: JointLimits
    judge: KnotJudge
    jacobian: JacobianProvider | None = None


class PlayedTrial(Trial):
    """The attempt the loop just played, as its rules see it: record and update in hand."""

    def __init__(
        self,
        state: LoopState,
        summary: TrialSummary,
        update: UpdateResult | None,
        record: TrialRecord,
        command: BezierCommand,
        ctx: Context,
    ) -> None:
        super().__init__(summary, state.knots, state.prev_knots)
        self.update = update
        self._record, self._command, self._ctx = record, command, ctx
        self._own = (summary.update_solved, None if update is None else update.dkappa)
        self._correct = state.correct(state.knots, learn=False)
        self._w_control = state.w_control()  # what the loop's own update of this play used

    def record(self) -> TrialRecord:
        """What the trial measured."""
        return self._record

    def cost_at(self, t: float) -> float | None:
        """The critical cost of this play's record at ``t`` (:func:`cost_at`)."""
        return cost_at(self._record, self.knots, self._ctx, t)

    def own_update(self) -> tuple[bool | None, np.ndarray | None]:
        """(solved, dkappa) of the update assessed from this play alone."""
        return self._own

    def average_over(self, group: Sequence[Trial]) -> bool | None:
        """The update on the mean error of this play and ``group``'s, taken as its update (the
        secant source's correction as this play left it, without learning again)."""
        extra = tuple(t.record() for t in group)
        s = self.summary
        _, self.update = assess(
            self._record,
            self._command,
            self._ctx,
            s.trial,
            s.attempt,
            extra,
            w_control=self._w_control,
            correct=self._correct,
        )
        return None if self.update is None else self.update.solved


@dataclass(frozen=True)
class LoopMoves:
    """The loop's :class:`learner.stops.Moves`: steps and updates against its context."""

    state: LoopState
    ctx: Context

    def step(self, knots: np.ndarray, dkappa: np.ndarray) -> np.ndarray:
        """kappa - gain dkappa from ``knots``, limit-safe (:func:`safe_step`)."""
        p, ctx = self.ctx.params, self.ctx
        dk = p.gain * np.asarray(dkappa)
        return safe_step(knots, dk, ctx.target.T, ctx.robot, ctx.limits, p.step_halvings)

    def update_about(
        self, trial: Trial, w_control: float, explore: np.ndarray | None = None
    ) -> UpdateResult | None:
        """The update about ``trial``'s record and command again at control weight
        ``w_control``, or the exploring update toward ``explore`` (already judged; the secant
        source's correction without learning)."""
        command = BezierCommand(trial.knots, self.ctx.target.T)
        _, update = assess(
            trial.record(),
            command,
            self.ctx,
            trial.summary.trial,
            0,
            tuple(t.record() for t in trial.group),
            w_control=w_control,
            judged=False,
            correct=self.state.correct(trial.knots, learn=False),
            explore=explore,
        )
        return update


def decide(
    state: LoopState,
    summary: TrialSummary,
    update: UpdateResult | None,
    record: TrialRecord,
    command: BezierCommand,
    ctx: Context,
) -> Step:
    """The loop's next move after one attempt of trial ``state.k`` (module docstring).

    The run's stop rules (:class:`learner.stops.StopRules`, in order: a tracking loss with
    retries left repeats the trial; a knot stops the paper's loop; a confirmation in progress
    replays the command; a safeguard rejection returns to the best command with a shrunk
    step; an averaging group still filling replays the command, a full one updates on its
    mean error; the damped or the gain step gives kappa_{k+1}) rule on it and update their
    memory in ``state``; a step's move computes the new command.
    """
    trial = PlayedTrial(state, summary, update, record, command, ctx)
    ruling = state.rules.verdict(trial)
    new = None
    if ruling.kind == REPLAY:
        new = state.knots
    elif ruling.kind == STEP:
        new = ruling.move(LoopMoves(state, ctx))
    return Step(trial.summary, trial.update, new, ruling.stop, ruling.kind != RETRY)


def cost_at(record: TrialRecord, knots: np.ndarray, ctx: Context, t: float) -> float | None:
    """||x(t) - x_demo(t)||_Q^2 of ``record`` (played with ``knots``) at ``t`` [s], None where
    its markers were lost (:func:`learner.objectives.error_at`)."""
    base = BezierCommand(knots, ctx.target.T).base_offset
    try:
        err = error_at(record, ctx.target, base, ctx.params.update.fit, t)
    except RecordError:
        return None
    return critical_cost(err, ctx.params.update.weights)


def safe_step(
    knots: np.ndarray,
    dkappa: np.ndarray,
    T: float,
    robot: RobotModel,
    limits: JointLimits,
    halvings: int = 4,
) -> np.ndarray:
    """kappa - alpha dkappa with the largest alpha in 1, 1/2, ..., 1/2^halvings whose command
    keeps every limit on its 250 Hz samples (torque by the robot model's inverse dynamics).

    The QP holds the limits only to first order (torque is linearised); a step that breaks a
    limit would fault the robot and teach nothing. If even the smallest breaks one, that step
    is taken anyway and the lab's controller decides.
    """
    t = BezierCommand(knots, T).sample_times()
    alpha = 1.0
    for _ in range(halvings + 1):
        new = knots - alpha * dkappa
        if sampled_violation(new, T, t, robot, limits) <= 1e-9:
            return new
        alpha *= 0.5
    return knots - 2 * alpha * dkappa


def _fit_times(objective: str, target: DemoTarget) -> tuple[float, ...]:
    """The times [s] whose rope state ``objective`` fits, where a measured Jacobian is taken;
    none for an objective that takes no Jacobian."""
    kind = objective_kind(objective)
    return kind.fit_times(target) if kind.takes_jacobian else ()


def assess(
    record: TrialRecord,
    command: BezierCommand,
    ctx: Context,
    k: int,
    attempt: int,
    extra_records: tuple[TrialRecord, ...] = (),
    *,
    w_control: float | None = None,
    judged: bool = True,
    correct=None,
    explore: np.ndarray | None = None,
) -> tuple[TrialSummary, UpdateResult | None]:
    """Trial ``k``'s ledger line and update: the judge's verdict, then (no fault) the
    critical-point error and the inverse-model QP (on the mean error with ``extra_records``,
    earlier plays of the same command); lost tracking gives no update. ``w_control``: the
    QP's control weight instead of the run's (the damped step's lambda); ``judged=False``
    skips the judge (a trial already judged, stepped from again); ``correct``: the model
    Jacobian's correction (:meth:`LoopState.correct`); ``explore``: the exploring update
    toward that knot update (:func:`learner.update.ilc_update`; None: the update)."""
    target, robot, params, limits = ctx.target, ctx.robot, ctx.params, ctx.limits
    verdict = ctx.judge(record) if judged else None
    settings = params.update_settings(limits)
    if w_control is not None:
        settings = replace(settings, weights=replace(settings.weights, w_control=w_control))
    base = dict(
        trial=k,
        attempt=attempt,
        fault=record.fault,
        knot=None if verdict is None else verdict.knot,
        verdict=None if verdict is None else verdict.to_json(),
        wall_s=0.0,
    )
    if record.fault is not None:
        return TrialSummary(
            **base,
            tracking_lost=False,
            cost=None,
            update_solved=None,
            update_status=None,
            predicted_cost_after=None,
            action="fault: step halfway back",
        ), None
    try:
        res = ilc_update(
            record,
            command,
            target,
            robot,
            params.rope_model,
            settings,
            extra_records=extra_records,
            jacobian=provided_jacobian(
                params.update.jacobian,
                ctx.jacobian,
                command.knots,
                command.T,
                _fit_times(settings.objective, target),
            ),
            correct=correct,
            explore=explore,
        )
    except SolverError as e:  # the model failed on the measured motion: no update
        return TrialSummary(
            **base,
            tracking_lost=False,
            cost=None,
            update_solved=False,
            update_status=f"{UPDATE_FAILED}: {e}",
            predicted_cost_after=None,
            action="update failed: command unchanged",
        ), None
    except RecordError as e:
        return TrialSummary(
            **base,
            tracking_lost=True,
            cost=None,
            update_solved=None,
            update_status=f"no error: {e}",
            predicted_cost_after=None,
            action="repeat (tracking lost before t_c)",
        ), None
    cost = critical_cost(res.err, params.update.weights) if np.all(np.isfinite(res.err)) else None
    return TrialSummary(
        **base,
        tracking_lost=False,
        cost=cost,
        update_solved=res.solved,
        update_status=res.qp_status,
        predicted_cost_after=res.predicted_cost_after if res.solved else None,
        t_eff=res.t_eff,
        action=("update" if res.solved else "QP failed: command unchanged")
        + (
            ""
            if abs(res.t_eff - target.t_c) < 1e-9
            else f" (critical point at {res.t_eff:.3f} s: tracking lost before t_c)"
        ),
    ), res

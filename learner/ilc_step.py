"""One step of the ILC loop: assess a trial, then decide what the loop does next.

:func:`assess` turns a trial's record into its ledger line and the update (the critical-point
error, the inverse-model QP: :func:`learner.update.ilc_update`). :func:`decide` takes that
and the loop's state and returns the :class:`Step`: the line as written, the next command or
why the loop stops. The stop rules' memory (:class:`Confirmation`, :class:`Safeguard`, the
plays being averaged) lives in :class:`LoopState`; a resumed run rebuilds it by replaying its
ledger through the same rules (:mod:`learner.ilc`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
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
from learner.run_directory import TrialSummary
from learner.steps import Damping
from learner.target import DemoTarget
from learner.update import UpdateResult, ilc_update

DAMPED_ACTIONS = ("update (damped", "cost rose: from the best command")
"""How a ledger line the damped step took begins (a resumed run feeds the rule those)."""
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


class Safeguard:
    """The safeguarded update's state: the best measured trial and the rejections since."""

    def __init__(self, on: bool):
        self.on = on
        self.best: tuple[float, np.ndarray, np.ndarray] | None = None
        self.rejects = 0

    def observe(
        self, summary: TrialSummary, dkappa: np.ndarray | None, knots: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Take a counted trial; return (best knots, shrunk best dkappa) when its cost rose
        above the best's, else None (and it may be the new best)."""
        if not self.on or summary.cost is None or not summary.update_solved or dkappa is None:
            return None
        if self.best is None or summary.cost <= self.best[0]:
            self.best = (summary.cost, np.array(knots, dtype=float), np.asarray(dkappa))
            self.rejects = 0
            return None
        self.rejects += 1
        _, best_knots, best_dk = self.best
        return best_knots, best_dk * 0.5**self.rejects


class Confirmation:
    """The confirmed-success rule's state: the outcomes of the current command's repeats."""

    def __init__(self, rule: tuple[int, int] | None):
        self.rule = rule
        self.streak: list[bool] = []

    @property
    def active(self) -> bool:
        """A confirmation is under way (started, not yet decided)."""
        return bool(self.streak) and self.outcome is None

    @property
    def outcome(self) -> str | None:
        """``"confirmed"``, ``"failed"`` (k can no longer be reached, or n ran short) or None."""
        if not self.streak or self.rule is None:
            return None
        k, n = self.rule
        ties = sum(self.streak)
        if ties >= k:
            return "confirmed"
        if ties + (n - len(self.streak)) < k:
            return "failed"
        return None

    def observe(self, success: bool) -> int | None:
        """Take a counted trial; return its position in the confirmation (None: not in one)."""
        if self.rule is None:
            return None
        if self.active:
            self.streak.append(bool(success))
            return len(self.streak)
        if success:
            self.streak = [True]
            return 1
        return None

    def reset_if_failed(self) -> None:
        """Forget a confirmation that can no longer succeed."""
        if self.outcome == "failed":
            self.streak = []


@dataclass
class LoopState:
    """Algorithm 1's state between trials.

    Attributes:
        k: The trial being played (0-based, counted trials).
        knots: kappa_k, the command of trial k, (10, 8).
        prev_knots: kappa_{k-1}, or None before the first update.
        trials: Every attempt's ledger line so far.
        conf: The confirmed-success rule's memory.
        guard: The safeguard's memory.
        damping: The damped step's memory (``step = "damped"``).
        group: Earlier plays of the current command (averaging).
        best: The damped step's best trial: (its knots, its record), or None.
        secant: The secant Jacobian's memory (``jacobian = "secant"``), or None.
        stop: Why the loop stops, once it does.
    """

    k: int
    knots: np.ndarray
    prev_knots: np.ndarray | None
    trials: list[TrialSummary]
    conf: Confirmation
    guard: Safeguard
    damping: Damping
    group: list[TrialRecord] = field(default_factory=list)
    best: tuple[np.ndarray, TrialRecord] | None = None
    secant: SecantCorrection | None = None
    stop: str | None = None

    @classmethod
    def initial(cls, knots0: np.ndarray, params: ILCParams) -> LoopState:
        """Before the first trial: kappa_0 and empty memories."""
        knots = np.asarray(knots0, dtype=float)
        learns = jacobian_kind(params.update.jacobian).learns
        return cls(
            0,
            knots,
            None,
            [],
            Confirmation(params.confirm),
            Safeguard(params.safeguard),
            Damping(params.damping),
            secant=SecantCorrection() if learns else None,
        )

    def correct(self, knots: np.ndarray, *, learn: bool = True):
        """The model-Jacobian correction of an update about ``knots`` (the secant source's,
        learning from this trial when ``learn``), or None."""
        if self.secant is None:
            return None
        return partial(self.secant.corrected, knots, learn=learn)

    def w_control(self, params: ILCParams) -> float | None:
        """The QP's control weight of the next update: the damped step's lambda, or None
        (the run's own weights)."""
        return self.damping.lam if params.step == "damped" else None

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


def decide(
    state: LoopState,
    summary: TrialSummary,
    update: UpdateResult | None,
    record: TrialRecord,
    command: BezierCommand,
    ctx: Context,
) -> Step:
    """The loop's next move after one attempt of trial ``state.k`` (module docstring).

    In order: a tracking loss with retries left repeats the trial; a knot stops the paper's
    loop; a confirmation in progress replays the command; a safeguard rejection returns to
    the best command with a shrunk step; an averaging group still filling replays the
    command; otherwise the update (on the group's mean error when averaging) gives
    kappa_{k+1} (:func:`next_knots`). Updates the stop rules' memory in ``state``.
    """
    params = ctx.params
    last = (
        not summary.tracking_lost
        or summary.success
        or summary.fault is not None
        or summary.attempt == params.tracking_retries
    )
    if not last:
        return Step(summary, update, None, None, False)
    conf, guard, group, knots = state.conf, state.guard, state.group, state.knots
    back = guard.observe(summary, None if update is None else update.dkappa, knots)
    position = conf.observe(summary.success)
    if position is not None:
        action = f"confirm {position}/{params.confirm[1]}: " + summary.action
        summary = replace(summary, confirm=position, action=action)
    if params.confirm is None and summary.success and params.stop_at_success:
        return Step(summary, update, None, "success", True)
    if conf.outcome == "confirmed":
        return Step(summary, update, None, "confirmed", True)
    if conf.active:
        return Step(summary, update, knots, None, True)  # the same command, to confirm it
    conf.reset_if_failed()
    if back is not None:
        group.clear()
        action = f"cost rose: back to the best command, step x0.5^{guard.rejects}"
        dk = params.gain * back[1]
        new = safe_step(back[0], dk, ctx.target.T, ctx.robot, ctx.limits, params.step_halvings)
        return Step(replace(summary, action=action), update, new, None, True)
    measured = summary.fault is None and not summary.tracking_lost
    if params.average > 1 and len(group) + 1 < params.average and measured:
        group.append(record)
        action = f"play {len(group)}/{params.average} of the command"
        return Step(replace(summary, average=len(group), action=action), update, knots, None, True)
    if group and measured:  # the update on the mean error of the group's plays
        n_plays = len(group) + 1
        _, update = assess(record, command, ctx, state.k, summary.attempt, tuple(group))
        summary = replace(
            summary,
            average=n_plays,
            update_solved=update.solved if update else None,
            action=f"update on the mean error of {n_plays} plays",
        )
    group.clear()
    if params.step == "damped" and measured and summary.update_solved:
        return _damped(state, summary, update, record, ctx)
    new, stop = next_knots(summary, update, knots, state.prev_knots, ctx)
    return Step(summary, update, new, stop, True)


def _damped(
    state: LoopState, summary: TrialSummary, update: UpdateResult, record: TrialRecord, ctx
) -> Step:
    """The damped step (:mod:`learner.steps`): the full step from a new best trial, else a
    more damped one from the best trial's command and record."""
    params, lam_used = ctx.params, state.damping.lam
    if state.damping.observe(summary.cost, state.k):
        state.best = (np.array(state.knots), record)
        base, step = state.knots, update
        action = f"{DAMPED_ACTIONS[0]}, lambda {lam_used:.3g})"
    else:
        base, best_record = state.best
        best_trial = state.damping.best[1]
        command = BezierCommand(base, ctx.target.T)
        _, step = assess(
            best_record,
            command,
            ctx,
            best_trial,
            0,
            w_control=state.damping.lam,
            judged=False,
            correct=state.correct(base, learn=False),
        )
        action = f"{DAMPED_ACTIONS[1]} (trial {best_trial + 1}), lambda {state.damping.lam:.3g}"
    if step is None or not step.solved:
        return Step(replace(summary, action=action + ": QP failed"), update, base, None, True)
    dk = params.gain * np.asarray(step.dkappa)
    new = safe_step(base, dk, ctx.target.T, ctx.robot, ctx.limits, params.step_halvings)
    return Step(replace(summary, action=action), update, new, None, True)


def next_knots(
    summary: TrialSummary,
    update: UpdateResult | None,
    knots: np.ndarray,
    prev_knots: np.ndarray | None,
    ctx: Context,
) -> tuple[np.ndarray | None, str | None]:
    """The next trial's knots after ``summary``, or (None, why the loop stops).

    A fault or lost tracking halves the step back toward the previous command (stops if there
    is none); a solved update takes kappa - gain dkappa (limit-safe); a failed QP keeps the
    command.
    """
    if summary.fault is not None or summary.tracking_lost:
        if prev_knots is None:
            why = "initial command faults" if summary.fault else "tracking lost before t_c"
            return None, why
        return prev_knots + 0.5 * (knots - prev_knots), None
    if summary.update_solved:
        dk = ctx.params.gain * np.asarray(update.dkappa)
        halvings = ctx.params.step_halvings
        return safe_step(knots, dk, ctx.target.T, ctx.robot, ctx.limits, halvings), None
    return knots, None  # failed QP: command unchanged (reported in the ledger)


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
) -> tuple[TrialSummary, UpdateResult | None]:
    """Trial ``k``'s ledger line and update: the judge's verdict, then (no fault) the
    critical-point error and the inverse-model QP (on the mean error with ``extra_records``,
    earlier plays of the same command); lost tracking gives no update. ``w_control``: the
    QP's control weight instead of the run's (the damped step's lambda); ``judged=False``
    skips the judge (a trial already judged, stepped from again); ``correct``: the model
    Jacobian's correction (:meth:`LoopState.correct`)."""
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
                params.update.jacobian, ctx.jacobian, command.knots, command.T
            ),
            correct=correct,
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

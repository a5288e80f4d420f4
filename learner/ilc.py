"""Task-Level ILC (paper, Algorithm 1) against any :class:`flyknot.record.Cell`.

    kappa_0 from the demonstration (initial guess)
    for k = 0 .. K-1:
        record_k = cell.run(Bezier(kappa_k))              # a trial
        err_k    = x_k(t_c) - x_demo(t_c)                # critical-point error
        dkappa_k = inverse-model QP(err_k)               # learner.update.ilc_update
        kappa_{k+1} = kappa_k - dkappa_k
    stop at the first knot (default; continued updates can degrade a command)

Handling of what a lab throws at the loop:

* A trial whose markers are lost before t_c is repeated with the same command, at most
  ``tracking_retries`` times (the paper repeats such trials); repeats are recorded but do
  not count towards ``max_trials``.
* A trial that faults gives no error to learn from: the next command goes halfway back to
  the last one that measured an error (or, on the first trial, the run stops: the initial
  command is unusable); under the damped step it is a failed step, taken again from the best
  command with more damping (:mod:`learner.steps`).
* A QP that fails leaves the command unchanged and the status is recorded.

Everything is written to the run directory as it happens (see
:class:`learner.run_directory.RunDirectory`), so a run interrupted at any point resumes without
losing or repeating a trial.

:func:`learn` is the algorithm above line by line; one step (assess a trial, decide the next
command) is :mod:`learner.ilc_step`, the rules it decides by :mod:`learner.stops` (a resumed run
replays its ledger through the same rules), the options :mod:`learner.ilc_params`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError
from flyknot.judge import CellVerdict, KnotJudge
from flyknot.limits import JointLimits
from flyknot.record import Cell, TrialRecord
from learner.bezier import BezierCommand
from learner.ilc_params import ILCParams, parse_confirm
from learner.ilc_step import (
    UPDATE_FAILED,
    Context,
    LoopState,
    Step,
    assess,
    cost_at,
    critical_cost,
    decide,
)
from learner.jacobians import JacobianProvider
from learner.kinematics import RobotModel
from learner.knot_stops import StopAtSuccess
from learner.run_directory import RunDirectory, TrialSummary, written_record
from learner.stops import RETRY
from learner.target import DemoTarget
from learner.trial_view import Trial

__all__ = [
    "ILCParams",
    "LearnResult",
    "critical_cost",
    "learn",
    "parse_confirm",
]


@dataclass(frozen=True)
class LearnResult:
    """What a learning run produced."""

    trials: tuple[TrialSummary, ...]
    first_success_trial: int | None
    final_knots: np.ndarray
    stopped_because: str

    @property
    def costs(self) -> list[float | None]:
        """Critical-point cost of each counted trial (last attempt), None if unmeasured."""
        return [s.cost for s in _counted(self.trials)]

    @property
    def knots(self) -> list[bool]:
        """Whether each counted trial tied the knot."""
        return [s.success for s in _counted(self.trials)]


def _counted(trials: tuple[TrialSummary, ...]) -> list[TrialSummary]:
    """The last attempt of every trial, in trial order (the ones a run counts)."""
    last: dict[int, TrialSummary] = {}
    for s in trials:
        last[s.trial] = s
    return [last[k] for k in sorted(last)]


def learn(
    cell: Cell,
    target: DemoTarget,
    knots0: np.ndarray,
    robot: RobotModel,
    params: ILCParams = ILCParams(),  # noqa: B008 - frozen value
    *,
    run_dir: str | Path | None = None,
    resume: bool = False,
    limits: JointLimits = JointLimits(),  # noqa: B008 - frozen value
    on_trial: Callable[[TrialSummary], None] | None = None,
    judge: KnotJudge = CellVerdict(),  # noqa: B008 - frozen value
    jacobian: JacobianProvider | None = None,
) -> LearnResult:
    """Run Task-Level ILC from ``knots0`` on ``cell`` until a knot or ``max_trials``.

    Args:
        cell: Where trials run (simulated or real lab).
        target: The demonstration target (critical state, t_c, hand).
        knots0: Initial command knots (10, 8).
        robot: The learner's robot model.
        params: Loop parameters.
        run_dir: Where to write everything (None: keep nothing on disk).
        resume: Continue the run found in ``run_dir`` instead of starting anew.
        limits: Joint limits for the updated commands.
        on_trial: Called after every attempt (progress display).
        judge: Who says whether a trial tied the knot (:mod:`flyknot.judge`); the stop rule
            asks it, never the cell's internals. Default: the verdict the cell recorded.
        jacobian: The measured M(t_c) for a run whose ``jacobian`` option names a source
            that needs one (:mod:`learner.jacobians`); None otherwise.

    Returns:
        Per-attempt summaries, the first successful trial (0-based) or None, the last
        knots, and why the loop stopped.
    """
    rd = RunDirectory(run_dir) if run_dir is not None else None
    ctx = Context(target, robot, params, limits, judge, jacobian)
    state = LoopState.initial(knots0, params)
    if rd is not None:
        state = _open_run(rd, state, cell, ctx, resume)
    if resume and rd is not None and state.secant is not None:
        _relearn_secant(rd, state, ctx)
    while state.stop is None and state.k < params.trials:
        command = BezierCommand(state.knots, target.T)  # kappa_k
        joint_cmd = command.joint_command()
        for attempt in state.attempts(params):
            t0 = time.perf_counter()
            record = _play(cell, joint_cmd, rd, state.k, attempt, resume)  # the trial
            w_control = state.w_control()  # the damped step's lambda, or None
            correct = state.correct(state.knots)  # the secant Jacobian's, or None
            summary, update = assess(
                record, command, ctx, state.k, attempt, w_control=w_control, correct=correct
            )
            summary = replace(summary, wall_s=time.perf_counter() - t0)
            step = decide(state, summary, update, record, command, ctx)  # kappa_{k+1}
            _commit(rd, state, step, on_trial)
            if step.last:
                break
        state.advance(step)
    return _finish(state, params, knots0)


def _open_run(
    rd: RunDirectory, state: LoopState, cell: Cell, ctx: Context, resume: bool
) -> LoopState:
    """A new run's directory (kappa_0 on disk), or the state a resumed run left: its ledger
    replayed through the stop rules, the cell's trial index continued."""
    if not resume and rd.ledger():
        raise ConfigError("run_dir", f"{str(rd.path)!r} already holds a run; use resume")
    if resume:
        state = _restore(rd, state, ctx)
        if state.stop is not None:
            return state
        if hasattr(cell, "trial_index"):
            # Every ledger line is one trial on the cell: continue its sequence (a cell seeds
            # its trial-to-trial variation by this index), as the uninterrupted run would have.
            cell.trial_index = len(state.trials)
    if state.k == 0:
        rd.save_knots(0, state.knots)
    return state


class WrittenTrial(Trial):
    """A ledger line as the stop rules see it when a resumed run replays it: its record and
    update read from the run directory (the loop's :class:`learner.ilc_step.PlayedTrial`
    had them in hand)."""

    def __init__(self, line: TrialSummary, state: LoopState, rd: RunDirectory, ctx: Context):
        super().__init__(line, state.knots, state.prev_knots)
        self._line, self._rd, self._ctx = line, rd, ctx
        self._record: TrialRecord | None = None

    def record(self) -> TrialRecord:
        """The trial's record, read once."""
        if self._record is None:
            self._record = TrialRecord.load(
                self._rd.record_stem(self._line.trial, self._line.attempt)
            )
        return self._record

    def cost_at(self, t: float) -> float | None:
        """The critical cost of the trial's record at ``t`` (:func:`learner.ilc_step.cost_at`)."""
        return cost_at(self.record(), self.knots, self._ctx, t)

    def own_update(self) -> tuple[bool | None, np.ndarray | None]:
        """The update written after the trial; the last play of an averaging group wrote the
        update on the group's mean error, so its own is computed again from its record."""
        line, plays = self._line, self._ctx.params.average
        if plays > 1 and line.average == plays:
            command = BezierCommand(self.knots, self._ctx.target.T)
            own, update = assess(
                self.record(), command, self._ctx, line.trial, line.attempt, judged=False
            )
            return own.update_solved, None if update is None else update.dkappa
        saved = self._rd.load_update(line.trial)
        return line.update_solved, None if saved is None else np.asarray(saved["dkappa"])

    def average_over(self, group: Sequence[Trial]) -> bool | None:
        """The line holds the update on the group's mean error already."""
        return self._line.update_solved


def _restore(rd: RunDirectory, state: LoopState, ctx: Context) -> LoopState:
    """The loop's state after the ledger: every line replayed through the run's stop rules
    (the loop's own, :meth:`learner.stops.StopRules.verdict`), the commands read from the
    run directory; stopped when the ledger ends on a stop.

    Raises:
        ConfigError: A line does not follow the rules (another trial, or after a stop), or
            the knots of the next trial are missing.
    """
    lines = rd.ledger()
    if lines and rd.knots_path(0).is_file():
        state.knots = rd.load_knots(0)  # what trial 0 played
    for n, line in enumerate(lines, start=1):
        if state.stop is not None or line.trial != state.k:
            where = f"after a stop ({state.stop})" if state.stop else f"at trial {state.k}"
            raise ConfigError(
                "run_dir",
                f"{str(rd.path)!r}: ledger line {n} (trial {line.trial}) does not follow the "
                f"run's rules: the loop was {where}",
            )
        ruling = state.rules.verdict(WrittenTrial(line, state, rd, ctx))
        state.trials.append(line)
        if ruling.kind == RETRY:
            continue
        if ruling.stop is not None:
            state.stop = ruling.stop
            continue
        state.k += 1
        if not rd.knots_path(state.k).is_file():
            raise ConfigError(
                "run_dir", f"{str(rd.path)!r}: the knots of trial {state.k} are missing"
            )
        state.prev_knots, state.knots = state.knots, rd.load_knots(state.k)
    return state


def _relearn_secant(rd: RunDirectory, state: LoopState, ctx: Context) -> None:
    """The secant Jacobian's memory as the loop left it: every ledger line whose update
    linearised the model (no fault, tracking kept) learned from again, in order."""
    for s in state.trials:
        if s.update_solved is None or (s.update_status or "").startswith(UPDATE_FAILED):
            continue
        knots = rd.load_knots(s.trial)
        record = TrialRecord.load(rd.record_stem(s.trial, s.attempt))
        command = BezierCommand(knots, ctx.target.T)
        assess(record, command, ctx, s.trial, s.attempt, judged=False, correct=state.correct(knots))


def _play(cell: Cell, joint_cmd, rd: RunDirectory | None, k: int, attempt: int, resume: bool):
    """Trial ``k``'s attempt on the cell, saved; on resume, the record a kill left instead
    (it used the cell's next trial index)."""
    stem = rd.record_stem(k, attempt) if rd is not None else None
    record = written_record(stem) if resume else None
    if record is not None:
        if hasattr(cell, "trial_index"):
            cell.trial_index += 1
        return record
    record = cell.run(joint_cmd)
    if stem is not None:
        record.save(stem)
    return record


def _commit(
    rd: RunDirectory | None,
    state: LoopState,
    step: Step,
    on_trial: Callable[[TrialSummary], None] | None,
) -> None:
    """The attempt's line into the ledger, after its update and the next knots: the ledger
    line is the commit point a resumed run continues from."""
    state.trials.append(step.summary)
    if rd is not None:
        if step.update is not None:
            rd.save_update(state.k, step.update)
        if step.new is not None:
            rd.save_knots(state.k + 1, step.new)
        rd.append_ledger(step.summary)
    if on_trial is not None:
        on_trial(step.summary)


def _finish(state: LoopState, params: ILCParams, knots0: np.ndarray) -> LearnResult:
    """The run's result; tracking alone (``max_trials`` 0) keeps the initial command (its
    one trial's update is never played); a ``converged_knot`` run that tied but ran out of
    trials before it converged keeps the command of its last tie."""
    t = tuple(state.trials)
    first = next((s.trial for s in _counted(t) if s.success), None)
    why = state.stop or ("max_trials" if first is None else "max_trials (knot tied)")
    final = knots0 if params.max_trials == 0 else state.knots
    tied = next((r.tied for r in state.rules.rules if isinstance(r, StopAtSuccess)), None)
    if state.stop is None and tied is not None:
        final = tied.knots
    return LearnResult(t, first, np.asarray(final), why)

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
  the previous one (or, on the first trial, the run stops: the initial command is unusable).
* A QP that fails leaves the command unchanged and the status is recorded.

Everything is written to the run directory as it happens (see
:class:`learner.run_directory.RunDirectory`), so a run interrupted at any point resumes without
losing or repeating a trial.

:func:`learn` is the algorithm above line by line; one step (assess a trial, decide the next
command, the stop rules) is :mod:`learner.ilc_step`, the options :mod:`learner.ilc_params`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
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
    DAMPED_ACTIONS,
    UPDATE_FAILED,
    Context,
    LoopState,
    Step,
    assess,
    critical_cost,
    decide,
)
from learner.jacobians import JacobianProvider
from learner.kinematics import RobotModel
from learner.run_directory import RunDirectory, TrialSummary, written_record
from learner.target import DemoTarget

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
    state = LoopState.initial(knots0, params)
    if rd is not None:
        state = _open_run(rd, state, cell, params, resume)
    ctx = Context(target, robot, params, limits, judge, jacobian)
    if resume and rd is not None and state.secant is not None:
        _relearn_secant(rd, state, ctx)
    while state.stop is None and state.k < params.trials:
        command = BezierCommand(state.knots, target.T)  # kappa_k
        joint_cmd = command.joint_command()
        for attempt in state.attempts(params):
            t0 = time.perf_counter()
            record = _play(cell, joint_cmd, rd, state.k, attempt, resume)  # the trial
            w_control = state.w_control(params)  # the damped step's lambda, or None
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
    rd: RunDirectory, state: LoopState, cell: Cell, params: ILCParams, resume: bool
) -> LoopState:
    """A new run's directory (kappa_0 on disk), or the state a resumed run left: its ledger
    replayed through the stop rules, the cell's trial index continued."""
    if not resume and rd.ledger():
        raise ConfigError("run_dir", f"{str(rd.path)!r} already holds a run; use resume")
    if resume:
        state = _restore(rd, state, params)
        if state.stop is not None:
            return state
        if hasattr(cell, "trial_index"):
            # Every ledger line is one trial on the cell: continue its sequence (a cell seeds
            # its trial-to-trial variation by this index), as the uninterrupted run would have.
            cell.trial_index = len(state.trials)
    if state.k == 0:
        rd.save_knots(0, state.knots)
    return state


def _restore(rd: RunDirectory, state: LoopState, params: ILCParams) -> LoopState:
    """The loop's state after the ledger's counted trials (the stop rules' memory as the
    loop left it), stopped when the ledger ends on a stop."""
    state.trials = rd.ledger()
    done = _counted(tuple(state.trials))
    for s in done:  # the confirmation, safeguard and averaging states, as the loop left them
        if s.average is not None and s.average < params.average:
            state.group.append(TrialRecord.load(rd.record_stem(s.trial, s.attempt)))
        else:
            state.group.clear()
        state.conf.observe(s.success)
        if params.safeguard:
            saved = rd.load_update(s.trial)
            dkappa = None if saved is None else np.asarray(saved["dkappa"])
            state.guard.observe(s, dkappa, rd.load_knots(s.trial))
        damped = params.step == "damped" and s.action.startswith(DAMPED_ACTIONS)
        if damped and state.damping.observe(s.cost, s.trial):
            stem = rd.record_stem(s.trial, s.attempt)
            state.best = (rd.load_knots(s.trial), TrialRecord.load(stem))
        if state.conf.outcome != "confirmed":
            state.conf.reset_if_failed()
    if not done:
        return state
    last = done[-1]
    if state.conf.outcome == "confirmed":
        state.knots, state.stop = rd.load_knots(last.trial), "confirmed"
        return state
    if params.confirm is None and last.success and params.stop_at_success:
        if rd.knots_path(last.trial).is_file():
            state.knots = rd.load_knots(last.trial)
        state.stop = "success"
        return state
    state.k = last.trial + 1
    if not rd.knots_path(state.k).is_file():
        raise ConfigError("run_dir", f"{str(rd.path)!r}: the knots of trial {state.k} are missing")
    state.knots, state.prev_knots = rd.load_knots(state.k), rd.load_knots(state.k - 1)
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
    one trial's update is never played)."""
    t = tuple(state.trials)
    first = next((s.trial for s in _counted(t) if s.success), None)
    why = state.stop or ("max_trials" if first is None else "max_trials (knot tied)")
    final = knots0 if params.max_trials == 0 else state.knots
    return LearnResult(t, first, np.asarray(final), why)

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
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, RecordError, check_choice, check_positive
from flyknot.judge import CellVerdict, KnotJudge
from flyknot.limits import JointLimits
from flyknot.record import Cell, TrialRecord
from learner.bezier import BezierCommand
from learner.inverse_qp import BACKENDS, InverseModelWeights
from learner.kinematics import RobotModel
from learner.limit_rows import sampled_violation
from learner.rope_model import RopeModelParams
from learner.run_directory import RunDirectory, TrialSummary, written_record
from learner.target import DemoTarget
from learner.update import OBJECTIVES, UpdateSettings, ilc_update


def parse_confirm(value: object, stop_at_success: bool = True) -> tuple[int, int] | None:
    """The confirmed-success rule ``(k, n)`` from ``[k, n]``, ``(k, n)`` or ``"k/n"`` (or None).

    Raises:
        ConfigError: Not two integers with 1 <= k <= n, or ``stop_at_success`` is off.
    """
    if value is None:
        return None
    c = value
    if isinstance(c, str) and "/" in c:
        try:
            c = tuple(int(v) for v in c.split("/"))
        except ValueError:
            c = value
    if isinstance(c, list | tuple):
        c = tuple(c)
    ok = isinstance(c, tuple) and len(c) == 2
    ok = ok and all(isinstance(v, int) and not isinstance(v, bool) for v in c)
    if not ok or not 1 <= c[0] <= c[1]:
        raise ConfigError("confirm", f"must be [k, n] (or k/n) with 1 <= k <= n, got {value!r}")
    if not stop_at_success:
        raise ConfigError("confirm", "needs stop_at_success = true")
    return c


@dataclass(frozen=True)
class ILCParams:
    """How the learning loop runs.

    Attributes:
        max_trials: Trials at most (tracking-failure repeats not counted).
        stop_at_success: Stop at the first tied knot (the paper does).
        objective: ``"critical"`` (the paper's) or ``"equal"`` (equally weighted baseline).
        backend: QP solver, ``"clarabel"`` or ``"osqp"``.
        tracking_retries: Repeats of a trial whose markers were lost before t_c.
        follow_through: Include the follow-through fingertip tracking term.
        gain: ILC learning gain alpha in (0, 1]: the command moves by alpha dkappa (the
            paper: 1).
        weights: Inverse-model weights (default: the paper's).
        rope_model: The learner's rope model (default: the paper's).
        trust_region: Largest change of any arm knot per update [rad] (a box in the QP),
            or None for none (the paper's).
        confirm: Confirmed-success stop rule ``(k, n)``, or None for the paper's (stop at the
            first knot). With it, a command that ties is played again until n trials of it
            have run (the tying one included; every repeat is a trial and counts towards
            ``max_trials``); the run stops when k of them tie, and otherwise learns on from the
            last of them. Needs ``stop_at_success``.
        safeguard: Reject an update whose trial measured a higher critical-point cost than
            the best trial so far: the next command is the best trial's command moved by its
            own update, shrunk by 1/2 per consecutive rejection (the paper has none).
        average: Plays of each command before an update (>= 1; the paper: 1); the update
            uses the mean critical-point error of the plays (each play is a trial).
    """

    max_trials: int = 10
    stop_at_success: bool = True
    objective: str = "critical"
    backend: str = "clarabel"
    tracking_retries: int = 2
    follow_through: bool = True
    gain: float = 1.0
    weights: InverseModelWeights = field(default_factory=InverseModelWeights)
    rope_model: RopeModelParams = field(default_factory=RopeModelParams)
    trust_region: float | None = None
    confirm: tuple[int, int] | None = None
    safeguard: bool = False
    average: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.max_trials, int) or self.max_trials < 1:
            raise ConfigError("max_trials", f"must be an integer >= 1, got {self.max_trials!r}")
        if not isinstance(self.tracking_retries, int) or self.tracking_retries < 0:
            raise ConfigError(
                "tracking_retries", f"must be an integer >= 0, got {self.tracking_retries!r}"
            )
        check_choice("objective", self.objective, OBJECTIVES)
        check_choice("backend", self.backend, BACKENDS)
        if not (isinstance(self.gain, (int, float)) and 0 < self.gain <= 1):
            raise ConfigError("gain", f"must lie in (0, 1], got {self.gain!r}")
        if self.trust_region is not None:
            check_positive("trust_region", self.trust_region)
        if isinstance(self.average, bool) or not isinstance(self.average, int) or self.average < 1:
            raise ConfigError("average", f"must be an integer >= 1, got {self.average!r}")
        if not isinstance(self.safeguard, bool):
            raise ConfigError("safeguard", f"must be true or false, got {self.safeguard!r}")
        object.__setattr__(self, "confirm", parse_confirm(self.confirm, self.stop_at_success))

    def update_settings(self, limits: JointLimits | None) -> UpdateSettings:
        """The settings of every update of the run, with ``limits`` on the updated commands."""
        return UpdateSettings(
            objective=self.objective,
            weights=self.weights,
            limits=limits,
            follow_through=self.follow_through,
            trust_region=self.trust_region,
            backend=self.backend,
        )


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
    last: dict[int, TrialSummary] = {}
    for s in trials:
        last[s.trial] = s
    return [last[k] for k in sorted(last)]


def critical_cost(err: np.ndarray, weights: InverseModelWeights) -> float:
    """||err||_Q^2 with Q = diag(w_crit_pos I_33, w_crit_vel I_33); err (66,) [m, m/s]."""
    err = np.asarray(err, dtype=float)
    half = err.size // 2
    return float(
        weights.w_crit_pos * err[:half] @ err[:half] + weights.w_crit_vel * err[half:] @ err[half:]
    )


def learn(
    cell: Cell,
    target: DemoTarget,
    knots0: np.ndarray,
    robot: RobotModel,
    params: ILCParams = ILCParams(),
    *,
    run_dir: str | Path | None = None,
    resume: bool = False,
    limits: JointLimits = JointLimits(),  # noqa: B008 - frozen value
    on_trial: Callable[[TrialSummary], None] | None = None,
    judge: KnotJudge = CellVerdict(),  # noqa: B008 - frozen value
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

    Returns:
        Per-attempt summaries, the first successful trial (0-based) or None, the last
        knots, and why the loop stopped.
    """
    rd = RunDirectory(run_dir) if run_dir is not None else None
    trials: list[TrialSummary] = []
    knots = np.asarray(knots0, dtype=float)
    prev_knots: np.ndarray | None = None
    k = 0
    conf = _Confirmation(params.confirm)
    guard = _Safeguard(params.safeguard)
    group: list[TrialRecord] = []  # earlier plays of the current command (averaging)
    if rd is not None and resume:
        trials = rd.ledger()
        done = _counted(tuple(trials))
        for s in done:  # the confirmation, safeguard and averaging states, as the loop left them
            if s.average is not None and s.average < params.average:
                group.append(TrialRecord.load(rd.record_stem(s.trial, s.attempt)))
            else:
                group.clear()
            conf.observe(s.success)
            if params.safeguard:
                guard.observe(s, rd.load_update(s.trial), rd.load_knots(s.trial))
            if conf.outcome != "confirmed":
                conf.reset_if_failed()
        if done:
            last = done[-1]
            if conf.outcome == "confirmed":
                return _finish(trials, rd.load_knots(last.trial), params, "confirmed")
            if params.confirm is None and last.success and params.stop_at_success:
                return _finish(
                    trials,
                    knots if not rd.knots_path(last.trial).is_file() else rd.load_knots(last.trial),
                    params,
                    "success",
                )
            k = last.trial + 1
            if not rd.knots_path(k).is_file():
                raise ConfigError(
                    "run_dir", f"{str(rd.path)!r}: the knots of trial {k} are missing"
                )
            knots = rd.load_knots(k)
            prev_knots = rd.load_knots(k - 1)
    elif rd is not None and rd.ledger():
        raise ConfigError("run_dir", f"{str(rd.path)!r} already holds a run; use resume")

    if rd is not None and resume and hasattr(cell, "trial_index"):
        # Every ledger line is one trial on the cell: continue its sequence (a cell seeds its
        # trial-to-trial variation by this index), as the uninterrupted run would have.
        cell.trial_index = len(trials)
    if rd is not None and k == 0:
        rd.save_knots(0, knots)
    while k < params.max_trials:
        command = BezierCommand(knots, target.T)
        joint_cmd = command.joint_command()
        attempts_done = {s.attempt for s in trials if s.trial == k}
        for attempt in range(params.tracking_retries + 1):
            if attempt in attempts_done:
                continue
            t0 = time.perf_counter()
            stem = rd.record_stem(k, attempt) if rd is not None else None
            record = written_record(stem) if resume else None
            if record is not None:
                # Interrupted after the trial ran but before it was assessed: keep it (it
                # used the cell's next trial index).
                if hasattr(cell, "trial_index"):
                    cell.trial_index += 1
            else:
                record = cell.run(joint_cmd)
                if stem is not None:
                    record.save(stem)
            summary, update = _assess(
                record, command, target, robot, params, limits, k, attempt, judge=judge
            )
            summary = replace(summary, wall_s=time.perf_counter() - t0)
            last = (
                not summary.tracking_lost
                or summary.success
                or summary.fault is not None
                or attempt == params.tracking_retries
            )
            new, stop = None, None
            if last:
                back = guard.observe(summary, update, knots)
                position = conf.observe(summary.success)
                if position is not None:
                    summary = replace(
                        summary,
                        confirm=position,
                        action=f"confirm {position}/{params.confirm[1]}: " + summary.action,
                    )
                if params.confirm is None and summary.success and params.stop_at_success:
                    stop = "success"
                elif conf.outcome == "confirmed":
                    stop = "confirmed"
                elif conf.active:
                    new = knots  # the same command again, to confirm it
                elif back is not None:
                    conf.reset_if_failed()
                    group.clear()
                    summary = replace(
                        summary,
                        action=f"cost rose: back to the best command, step x0.5^{guard.rejects}",
                    )
                    new = _safe_step(back[0], params.gain * back[1], target.T, robot, limits)
                elif (
                    params.average > 1
                    and len(group) + 1 < params.average
                    and summary.fault is None
                    and not summary.tracking_lost
                ):
                    conf.reset_if_failed()
                    group.append(record)
                    summary = replace(
                        summary,
                        average=len(group),
                        action=f"play {len(group)}/{params.average} of the command",
                    )
                    new = knots  # the same command again, to average its error
                else:
                    conf.reset_if_failed()
                    if group and summary.fault is None and not summary.tracking_lost:
                        n_plays = len(group) + 1
                        _, update = _assess(
                            record,
                            command,
                            target,
                            robot,
                            params,
                            limits,
                            k,
                            attempt,
                            extra_records=tuple(group),
                            judge=judge,
                        )
                        summary = replace(
                            summary,
                            average=n_plays,
                            update_solved=update["solved"] if update else None,
                            action=f"update on the mean error of {n_plays} plays",
                        )
                    group.clear()
                    new, stop = _next_knots(
                        summary, update, knots, prev_knots, target, robot, params, limits
                    )
            trials.append(summary)
            if rd is not None:
                if update is not None:
                    rd.save_update(k, update)
                if new is not None:
                    # The next trial's knots go to disk before the ledger line: the line is
                    # the commit point a resumed run continues from.
                    rd.save_knots(k + 1, new)
                rd.append_ledger(summary)
            if on_trial is not None:
                on_trial(summary)
            if last:
                break
        if stop is not None:
            return _finish(trials, knots, params, stop)
        prev_knots, knots = knots, new
        k += 1
    first = next((s.trial for s in _counted(tuple(trials)) if s.success), None)
    return _finish(
        trials, knots, params, "max_trials" if first is None else "max_trials (knot tied)"
    )


class _Safeguard:
    """The safeguarded update's state: the best measured trial and the rejections since."""

    def __init__(self, on: bool):
        self.on = on
        self.best: tuple[float, np.ndarray, np.ndarray] | None = None
        self.rejects = 0

    def observe(
        self, summary: TrialSummary, update: dict[str, Any] | None, knots: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Take a counted trial; return (best knots, shrunk best dkappa) when its cost rose
        above the best's, else None (and it may be the new best)."""
        if not self.on or summary.cost is None or not summary.update_solved or update is None:
            return None
        if self.best is None or summary.cost <= self.best[0]:
            self.best = (summary.cost, np.array(knots, dtype=float), np.asarray(update["dkappa"]))
            self.rejects = 0
            return None
        self.rejects += 1
        _, best_knots, best_dk = self.best
        return best_knots, best_dk * 0.5**self.rejects


class _Confirmation:
    """The confirmed-success rule's state: the outcomes of the current command's repeats."""

    def __init__(self, rule: tuple[int, int] | None):
        self.rule = rule
        self.streak: list[bool] = []

    @property
    def active(self) -> bool:
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
        if self.outcome == "failed":
            self.streak = []


def _next_knots(
    summary: TrialSummary,
    update: dict | None,
    knots: np.ndarray,
    prev_knots: np.ndarray | None,
    target: DemoTarget,
    robot: RobotModel,
    params: ILCParams,
    limits: JointLimits,
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
        dk = params.gain * np.asarray(update["dkappa"])
        return _safe_step(knots, dk, target.T, robot, limits), None
    return knots, None  # failed QP: command unchanged (reported in the ledger)


MAX_HALVINGS = 4


def _safe_step(
    knots: np.ndarray, dkappa: np.ndarray, T: float, robot: RobotModel, limits: JointLimits
) -> np.ndarray:
    """kappa - alpha dkappa with the largest alpha in 1, 1/2, ..., 1/16 whose command keeps
    every limit on its 250 Hz samples (torque by the robot model's inverse dynamics).

    The QP holds the limits only to first order (torque is linearised); a step that breaks a
    limit would fault the robot and teach nothing. If even 1/16 breaks one, that step is
    taken anyway and the lab's controller decides.
    """
    t = BezierCommand(knots, T).sample_times()
    alpha = 1.0
    for _ in range(MAX_HALVINGS + 1):
        new = knots - alpha * dkappa
        if sampled_violation(new, T, t, robot, limits) <= 1e-9:
            return new
        alpha *= 0.5
    return knots - 2 * alpha * dkappa


def _finish(trials, knots, params, why) -> LearnResult:
    t = tuple(trials)
    first = next((s.trial for s in _counted(t) if s.success), None)
    return LearnResult(t, first, np.asarray(knots), why)


def _assess(
    record: TrialRecord,
    command: BezierCommand,
    target: DemoTarget,
    robot: RobotModel,
    params: ILCParams,
    limits: JointLimits,
    k: int,
    attempt: int,
    extra_records: tuple[TrialRecord, ...] = (),
    judge: KnotJudge = CellVerdict(),  # noqa: B008 - frozen value
) -> tuple[TrialSummary, dict[str, Any] | None]:
    verdict = judge(record)
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
            params.update_settings(limits),
            extra_records=extra_records,
        )
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
    update = {
        "trial": k,
        "solved": res.solved,
        "status": res.qp_status,
        "cost_before": res.cost_before,
        "predicted_cost_after": res.predicted_cost_after,
        "err": res.err.tolist(),
        "dkappa": res.dkappa.tolist(),
        "new_knots": res.new_knots.tolist(),
        "timings": dict(res.timings),
        "limit_rounds": res.limit_rounds,
        "t_eff": res.t_eff,
        "sampled_violation": res.sampled_violation,
    }
    cost = critical_cost(res.err, params.weights) if np.all(np.isfinite(res.err)) else None
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
    ), update

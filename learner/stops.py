"""What the ILC loop does after a trial: its stop rules, a registry.

After each attempt the loop (:func:`learner.ilc_step.decide`) asks its rules, in the order of
:data:`STOPS`, what comes next; the first that rules decides:

* ``"retry"`` (:class:`Retry`): tracking lost before t_c with retries left: the trial again
  (the attempt does not count).
* ``"success"`` (:class:`StopAtSuccess`, the paper's): stop at the first knot (option
  ``converged_knot``: at the first knot whose cost no longer fell beyond the noise floor).
* ``"confirm"`` (:class:`Confirmation`): a command that ties is played again until k of n of
  its trials tie (option ``confirm``).
* ``"plateau"`` (:class:`Plateau`): stop when the best measured cost has not fallen by more
  than the trial-to-trial noise floor in ``plateau.patience`` counted trials.
* ``"safeguard"`` (:class:`Safeguard`): a cost above the best trial's: back to the best
  command, its own step shrunk (option ``safeguard``).
* ``"average"`` (:class:`Averaging`): each command played ``average`` times (the initial one
  ``average_first`` times), the update on the mean error of its plays.
* ``"explore"`` (:class:`Explore`): at the noise floor, a step from the best command toward a
  random offset the model says keeps the objective's rope states (option ``explore``).
* ``"damped"`` (:class:`DampedStep`): the damped step (:mod:`learner.steps`, ``step``).
* ``"gain"`` (:class:`GainStep`, the paper's): kappa - gain dkappa; a fault or lost tracking
  halfway back to the previous command, or stop when there is none.

A :class:`Ruling` says: another attempt (``RETRY``), stop and why (``STOP``), the same command
again as the next trial (``REPLAY``) or a new command (``STEP``, which its ``move`` computes).
A rule keeps its own memory (the confirmation's outcomes, the safeguard's best trial, the
plays being averaged, the damped step's lambda and best trial). The loop and a resumed run
feed it alike: :mod:`learner.ilc` replays the ledger's lines through the same
:class:`StopRules`, so a run resumed after any line holds the memory the loop held there. Only
a step's move (the new command: a QP solve, the limit checks) is the loop's alone; a resumed
run reads the commands from the run directory.

A rule's hooks, in the order :meth:`StopRules.verdict` calls them (each optional):

    screen(trial) -> Ruling | None    every rule, before any memory (an attempt not counted)
    observe(trial)                    every rule, every counted trial
    verdict(trial) -> Ruling | None   in order, until one rules
    settle(trial, ruling)             every rule, once the ruling is known

Adding a rule is one :class:`StopRule` subclass and one line in :data:`STOPS`, at its place in
the order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from flyknot.constants import N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import ConfigError
from learner.knot_stops import Confirmation, StopAtSuccess
from learner.rule_base import REPLAY, RETRY, STEP, STOP, Moves, Ruling, StopRule
from learner.steps import Damping
from learner.trial_view import Trial

if TYPE_CHECKING:
    from learner.ilc_params import ILCParams
    from learner.update import UpdateResult


class Retry(StopRule):
    """Tracking lost before t_c: the same trial again, at most ``tracking_retries`` times."""

    name = "retry"
    description = "tracking lost before t_c: the trial again (not counted)"

    def __init__(self, params: ILCParams) -> None:
        self.retries = params.tracking_retries

    def screen(self, trial: Trial) -> Ruling | None:
        """Another attempt when tracking was lost, without fault or knot, and retries
        remain."""
        s = trial.summary
        if s.tracking_lost and s.fault is None and not s.success and s.attempt < self.retries:
            return Ruling(RETRY, self.name)
        return None


class Plateau(StopRule):
    """Stop at the noise floor (``plateau``): no counted trial in the last ``patience`` lowered
    the best measured cost c* by more than ``noise``, c_k >= c* - noise (a fault or a trial
    without a cost makes no progress either)."""

    name = "plateau"
    description = "stop when the best cost has not fallen by more than the noise floor"

    def __init__(self, params: ILCParams) -> None:
        self.patience, self.noise = params.plateau.patience, params.plateau.noise
        self.best: float | None = None
        """c*, the best cost that made progress."""
        self.since = 0
        """Counted trials since the last progress."""

    def observe(self, trial: Trial) -> None:
        """Progress resets the count; any other counted trial adds one."""
        cost = trial.summary.cost
        if cost is not None and (self.best is None or cost < self.best - self.noise):
            self.best, self.since = cost, 0
        else:
            self.since += 1

    def verdict(self, trial: Trial) -> Ruling | None:
        """Stop when ``patience`` counted trials in a row made no progress."""
        if self.patience and self.since >= self.patience:
            return Ruling(STOP, self.name, "plateau")
        return None


class Safeguard(StopRule):
    """The safeguarded update (``safeguard``): after a trial that measured a higher cost than
    the best trial so far, the next command is the best trial's command moved by its own
    update, shrunk by 1/2 per consecutive rejection."""

    name = "safeguard"
    description = "a cost above the best trial's: back to the best command, step shrunk"

    def __init__(self, params: ILCParams) -> None:
        self.on = params.safeguard
        self.best: tuple[float, np.ndarray, np.ndarray] | None = None
        """(cost, knots, dkappa) of the best measured trial."""
        self.rejects = 0
        self._back: tuple[np.ndarray, np.ndarray] | None = None

    def observe(self, trial: Trial) -> None:
        """Keep the trial when it is the best so far; count a rejection when its cost rose."""
        self._back = None
        s = trial.summary
        if not self.on or s.cost is None:
            return
        solved, dkappa = trial.own_update()
        if not solved or dkappa is None:
            return
        if self.best is None or s.cost <= self.best[0]:
            self.best = (s.cost, np.array(trial.knots, dtype=float), np.asarray(dkappa))
            self.rejects = 0
            return
        self.rejects += 1
        self._back = (self.best[1], self.best[2] * 0.5**self.rejects)

    def verdict(self, trial: Trial) -> Ruling | None:
        """Back to the best command, when the trial's cost rose above the best's."""
        if self._back is None:
            return None
        knots, dkappa = self._back
        action = f"cost rose: back to the best command, step x0.5^{self.rejects}"
        trial.summary = replace(trial.summary, action=action)
        return Ruling(STEP, self.name, move=lambda moves: moves.step(knots, dkappa))


class Averaging(StopRule):
    """``average`` plays of each command (``average_first`` of the initial one); the update
    on the mean error of the plays."""

    name = "average"
    description = "each command played `average` times, the update on their mean error"

    def __init__(self, params: ILCParams) -> None:
        self.each = params.average
        self.first = params.average if params.average_first is None else params.average_first
        self.stepped = False
        """A new command has been stepped to (the initial one's group is behind)."""
        self.group: list[Trial] = []
        """The earlier plays of the current command."""

    @property
    def plays(self) -> int:
        """Plays of the current command before its update."""
        return self.each if self.stepped else self.first

    def verdict(self, trial: Trial) -> Ruling | None:
        """Play the command again while the group fills; the last play takes the update on
        the group's mean error (the next rule steps by it) and keeps the group."""
        if not trial.measured:
            return None
        s = trial.summary
        if len(self.group) + 1 < self.plays:
            self.group.append(trial)
            n = len(self.group)
            action = f"play {n}/{self.plays} of the command"
            trial.summary = replace(s, average=n, action=action)
            return Ruling(REPLAY, self.name)
        if self.group:
            n = len(self.group) + 1
            trial.group = tuple(self.group)
            solved = trial.average_over(self.group)
            action = f"update on the mean error of {n} plays"
            trial.summary = replace(s, average=n, update_solved=solved, action=action)
        return None

    def settle(self, trial: Trial, ruling: Ruling) -> None:
        """A new command empties the group (a replay or a stop leaves it)."""
        if ruling.kind == STEP:
            self.group.clear()
            self.stepped = True


def exploration_offset(size: float, seed: int, trial: int) -> np.ndarray:
    """r (10, 8) [rad]: standard normal on the 56 arm knot entries drawn from ``(seed,
    trial)``, scaled to an RMS of ``size``; zero on the base rows."""
    r = np.zeros((N_ROWS, N_KNOTS))
    z = np.random.default_rng([seed, trial]).standard_normal((N_JOINTS, N_KNOTS))
    r[:N_JOINTS] = size * z / np.sqrt(np.mean(z**2))
    return r


class Explore(StopRule):
    """The exploring step (``explore``), a step toward a random offset at the noise floor.

    After ``explore.patience`` counted trials in a row whose costs stay within (1 +
    ``explore.band``) of the lowest without lowering it, the next command is the best trial's
    command moved by the exploring update about its record toward a random offset r
    (:func:`exploration_offset`, a new one each trial), every fitted error taken as zero:

        min_dk ||M dk||_Q^2 (+ the objective's other points) + w ||dk_arm - r_arm||^2

    The step keeps the rope states the objective fits where the model predicts them and
    spends the freedom they leave on r: another throw to the same rope state at t_c, where
    the damped step would play nearly the same command again (the knot is decided after t_c,
    docs/measuring-sticks.md). A trial that lowers the best cost hands the step back to the
    other rules; a larger rise too. The rule sees only measured costs."""

    name = "explore"
    description = "at the noise floor, a step from the best command toward a random offset"

    def __init__(self, params: ILCParams) -> None:
        self._p = params.explore
        self.best: Trial | None = None
        """The counted trial with the lowest measured cost."""
        self.best_cost: float | None = None
        self.since = 0
        """Counted trials since the last new lowest cost."""

    def observe(self, trial: Trial) -> None:
        """A new lowest cost, a larger rise than the band or a trial without a cost resets
        the count; a cost within the band adds one."""
        if self._p.size <= 0:
            return
        cost = trial.summary.cost if trial.measured else None
        if cost is not None and (self.best_cost is None or cost < self.best_cost):
            self.best, self.best_cost, self.since = trial, float(cost), 0
        elif cost is not None and cost <= (1.0 + self._p.band) * self.best_cost:
            self.since += 1
        else:
            self.since = 0

    def verdict(self, trial: Trial) -> Ruling | None:
        """An exploring step from the best command once ``patience`` trials made no
        progress."""
        p, best = self._p, self.best
        if p.size <= 0 or best is None or self.since < p.patience:
            return None
        r = exploration_offset(p.size, p.seed, trial.summary.trial)
        action = (
            f"explore: from the best command (trial {best.summary.trial + 1}) toward a "
            f"{p.size:g} rad offset"
        )

        def move(moves: Moves) -> np.ndarray:
            step = moves.update_about(best, p.w_control, r)
            done = step is not None and step.solved
            trial.summary = replace(trial.summary, action=action + ("" if done else ": QP failed"))
            return moves.step(best.knots, step.dkappa) if done else best.knots

        return Ruling(STEP, self.name, move=move)


class DampedStep(StopRule):
    """The damped step (``step = "damped"``, :mod:`learner.steps`): the full step from a new
    best trial, else a more damped one from the best trial's command and record."""

    name = "damped"
    description = "Levenberg-Marquardt on the measured cost: back to the best when it rose"

    def __init__(self, params: ILCParams) -> None:
        self.on = params.step == "damped"
        self.damping = Damping(params.damping)
        self.best: Trial | None = None
        """The trial of ``damping.best``: its command and record."""

    def w_control(self) -> float | None:
        """lambda, the next update's control weight."""
        return self.damping.lam if self.on else None

    def verdict(self, trial: Trial) -> Ruling | None:
        """The damped step after a trial with a solved update, or after one that measured
        nothing once a best exists (a failed step: from the best, more damped)."""
        s = trial.summary
        if not self.on:
            return None
        if not trial.measured:
            return self._failed(trial) if self.best is not None else None
        if not s.update_solved:
            return None
        lam_used = self.damping.lam
        weighed = self._weighed(trial)
        took = self.damping.observe(*weighed, own=weighed[0] if trial.group else s.cost)
        if took and self.damping.is_best(s.trial):
            self.best = trial
        if took or self.best is None:
            within = took and self.best is not trial
            base = trial.knots
            mean = f", on the mean error of {len(trial.group) + 1} plays" if trial.group else ""
            action = f"update (damped, lambda {lam_used:.3g}{mean}" + (
                f"; within the noise of the best, trial {self.best.summary.trial + 1})"
                if within
                else ")"
            )

            def step_of(moves: Moves) -> UpdateResult | None:
                return trial.update
        else:
            best, lam = self.best, self.damping.lam
            base = best.knots
            action = (
                f"cost rose: from the best command (trial {best.summary.trial + 1}), "
                f"lambda {lam:.3g}"
            )

            def step_of(moves: Moves) -> UpdateResult | None:
                return moves.update_about(best, lam)

        return self._ruling(trial, base, action, step_of)

    def _weighed(self, trial: Trial) -> tuple[float | None, int, float | None]:
        """(cost, trial, the best's cost) as the rule weighs them: each at its own critical
        point, or (``damping.common_time``) both at the earlier of the two when they differ
        (a trial whose markers were lost before t_c is fitted earlier)."""
        s, best = trial.summary, self.best
        if trial.group:  # an averaged command: the mean cost of its plays
            costs = [p.summary.cost for p in (*trial.group, trial) if p.summary.cost is not None]
            return (float(np.mean(costs)) if costs else None), s.trial, None
        if not self.damping.params.common_time or best is None or s.cost is None:
            return s.cost, s.trial, None
        t_k, t_b = s.t_eff, best.summary.t_eff
        if t_k is None or t_b is None or abs(t_k - t_b) < 1e-9:
            return s.cost, s.trial, None
        t = min(t_k, t_b)
        cost = s.cost if t == t_k else trial.cost_at(t)
        against = best.summary.cost if t == t_b else best.cost_at(t)
        return cost, s.trial, against

    def _failed(self, trial: Trial) -> Ruling:
        """A trial that measured nothing (a fault or lost tracking): its step failed, so the
        next one is from the best command with lambda grown (cost +inf in :class:`Damping`)."""
        self.damping.observe(math.inf, trial.summary.trial)
        best, lam = self.best, self.damping.lam
        why = "fault" if trial.summary.fault is not None else "tracking lost"
        action = f"{why}: from the best command (trial {best.summary.trial + 1}), lambda {lam:.3g}"
        return self._ruling(trial, best.knots, action, lambda moves: moves.update_about(best, lam))

    def _ruling(
        self,
        trial: Trial,
        base: np.ndarray,
        action: str,
        step_of: Callable[[Moves], UpdateResult | None],
    ) -> Ruling:
        """A step from ``base`` by ``step_of(moves)``'s update (``base`` itself when the QP
        fails), ``action`` written on the trial's ledger line."""

        def move(moves: Moves) -> np.ndarray:
            step = step_of(moves)
            done = step is not None and step.solved
            trial.summary = replace(trial.summary, action=action + ("" if done else ": QP failed"))
            return moves.step(base, step.dkappa) if done else base

        return Ruling(STEP, self.name, move=move)


class GainStep(StopRule):
    """The paper's step, the last rule: kappa - gain dkappa (limit-safe) after a solved
    update, the same command after a failed QP; a fault or lost tracking halves the step back
    toward the last command that measured an error, or stops the loop when there is none."""

    name = "gain"
    description = "kappa - gain dkappa (the paper's); a fault halfway back"

    def __init__(self, params: ILCParams) -> None:
        self.good: np.ndarray | None = None
        """The command of the last trial that measured an error (where a fault steps back
        toward: a run of faults halves the distance to it each time)."""

    def observe(self, trial: Trial) -> None:
        """Keep the command of a trial that measured an error."""
        if trial.measured:
            self.good = trial.knots

    def verdict(self, trial: Trial) -> Ruling | None:
        """Always rules (a step or a stop)."""
        s, knots, good = trial.summary, trial.knots, self.good
        if not trial.measured:
            if good is None:
                why = "initial command faults" if s.fault else "tracking lost before t_c"
                return Ruling(STOP, self.name, why)
            return Ruling(STEP, self.name, move=lambda moves: good + 0.5 * (knots - good))
        if s.update_solved:

            def move(moves: Moves) -> np.ndarray:
                return moves.step(knots, trial.update.dkappa)

            return Ruling(STEP, self.name, move=move)
        return Ruling(STEP, self.name, move=lambda moves: knots)  # failed QP: unchanged


STOPS: dict[str, type[StopRule]] = {
    r.name: r
    for r in (
        Retry,
        StopAtSuccess,
        Confirmation,
        Plateau,
        Safeguard,
        Averaging,
        Explore,
        DampedStep,
        GainStep,
    )
}
"""Every rule of the loop by name, in the order the loop asks them."""


def stop_rule(name: object) -> type[StopRule]:
    """The registered rule ``name``; the error lists the valid ones."""
    if not isinstance(name, str) or name not in STOPS:
        raise ConfigError("stop_rule", f"unknown stop rule {name!r}", list(STOPS))
    return STOPS[name]


class StopRules:
    """A run's rules in their order, with their memories: what the loop asks after every
    attempt and what a resumed run replays its ledger through."""

    def __init__(self, params: ILCParams, names: Sequence[str] | None = None) -> None:
        self.rules = tuple(stop_rule(n)(params) for n in (STOPS if names is None else names))
        """The rules, in the order they are asked (``names``; default: all of :data:`STOPS`)."""

    def __getitem__(self, name: str) -> StopRule:
        """The rule ``name`` of this run."""
        for rule in self.rules:
            if rule.name == name:
                return rule
        raise ConfigError("stop_rule", f"no stop rule {name!r}", [r.name for r in self.rules])

    def verdict(self, trial: Trial) -> Ruling:
        """The ruling on ``trial``, every rule's memory updated (module docstring).

        Raises:
            ConfigError: No rule ruled (the last must always rule, as ``"gain"`` does).
        """
        for rule in self.rules:
            ruling = rule.screen(trial)
            if ruling is not None:
                return ruling
        for rule in self.rules:
            rule.observe(trial)
        for rule in self.rules:
            ruling = rule.verdict(trial)
            if ruling is not None:
                break
        else:
            raise ConfigError(
                "stop_rule",
                f"no rule ruled on trial {trial.summary.trial}: the last must always rule, as "
                "'gain' does",
            )
        for rule in self.rules:
            rule.settle(trial, ruling)
        return ruling

    def w_control(self) -> float | None:
        """The next update's control weight a rule sets (the damped step's lambda), or None."""
        return next((w for r in self.rules if (w := r.w_control()) is not None), None)

    def memory(self) -> dict[str, dict[str, Any]]:
        """Every rule's memory as plain data, by name."""
        return {r.name: r.memory() for r in self.rules}


__all__ = [
    "REPLAY",
    "RETRY",
    "STEP",
    "STOP",
    "STOPS",
    "Averaging",
    "Confirmation",
    "DampedStep",
    "Explore",
    "GainStep",
    "Moves",
    "Plateau",
    "Retry",
    "Ruling",
    "Safeguard",
    "StopAtSuccess",
    "StopRule",
    "StopRules",
    "exploration_offset",
    "stop_rule",
]

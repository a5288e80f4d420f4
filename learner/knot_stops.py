"""The loop's stops at a knot (rules of :data:`learner.stops.STOPS`): the paper's first knot,
a knot the learner has converged on (``converged_knot``) and a confirmed one (``confirm``)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

from learner.rule_base import REPLAY, STOP, Ruling, StopRule
from learner.trial_view import Trial

if TYPE_CHECKING:
    from learner.ilc_params import ILCParams


class StopAtSuccess(StopRule):
    """The paper's: stop at the first knot (``stop_at_success``, no ``confirm`` rule); with
    ``converged_knot``, at a knot whose trial's cost c_k no longer fell beyond the noise
    band below the lowest cost measured before it, c_k >= (1 - nu) min_{j<k} c_j (nu
    ``damping.noise``), or on the last trial."""

    name = "success"
    description = "stop at the first knot (the paper's), or at a converged one"

    def __init__(self, params: ILCParams) -> None:
        self.on = params.stop_at_success and params.confirm is None
        self.converged = params.converged_knot
        self.nu = params.damping.noise
        self.last = params.trials - 1
        self.lowest: float | None = None
        """min c_j over the counted trials before the current one."""
        self.before: float | None = None
        """``lowest`` as it was before the current trial."""
        self.tied: Trial | None = None
        """The last trial that tied (``converged_knot``): the run's learned command when it
        ends at ``max_trials`` without a converged knot."""

    def observe(self, trial: Trial) -> None:
        """Keep the lowest cost measured so far, the one before this trial, and the last
        tie."""
        self.before = self.lowest
        if self.on and self.converged and trial.summary.success:
            self.tied = trial
        cost = trial.summary.cost if trial.measured else None
        if cost is not None and (self.lowest is None or cost < self.lowest):
            self.lowest = float(cost)

    def verdict(self, trial: Trial) -> Ruling | None:
        """Stop when the trial tied the knot (and, with ``converged_knot``, the learner had
        converged on it); after a knot not yet converged the next rule steps."""
        s = trial.summary
        if not (self.on and s.success):
            return None
        if not self.converged:
            return Ruling(STOP, self.name, "success")
        cost, before = (s.cost if trial.measured else None), self.before
        if cost is not None and before is not None and cost >= (1.0 - self.nu) * before:
            return Ruling(STOP, self.name, "success (converged)")
        return Ruling(STOP, self.name, "success") if s.trial >= self.last else None


class Confirmation(StopRule):
    """The confirmed-success rule ``confirm = (k, n)``: a tie is played again until n trials
    of its command have run; stop when k tie, learn on once k can no longer be reached."""

    name = "confirm"
    description = "a tie played again until k of n tie (confirm = k/n)"

    def __init__(self, params: ILCParams) -> None:
        self.k_of_n = params.confirm
        self.streak: list[bool] = []
        """The outcomes of the current command's trials since its first tie."""

    @property
    def active(self) -> bool:
        """A confirmation is under way (started, not yet decided)."""
        return bool(self.streak) and self.outcome is None

    @property
    def outcome(self) -> str | None:
        """``"confirmed"``, ``"failed"`` (k can no longer be reached, or n ran short) or None."""
        if not self.streak or self.k_of_n is None:
            return None
        k, n = self.k_of_n
        ties = sum(self.streak)
        if ties >= k:
            return "confirmed"
        if ties + (n - len(self.streak)) < k:
            return "failed"
        return None

    def observe(self, trial: Trial) -> None:
        """A tie starts a confirmation; a trial inside one adds its outcome and its position
        to the line (``confirm``, the action's prefix)."""
        if self.k_of_n is None:
            return
        s = trial.summary
        if self.active:
            self.streak.append(bool(s.success))
        elif s.success:
            self.streak = [True]
        else:
            return
        position = len(self.streak)
        action = f"confirm {position}/{self.k_of_n[1]}: " + s.action
        trial.summary = replace(s, confirm=position, action=action)

    def verdict(self, trial: Trial) -> Ruling | None:
        """Stop when confirmed; play the command again while the confirmation runs."""
        if self.outcome == "confirmed":
            return Ruling(STOP, self.name, "confirmed")
        if self.active:
            return Ruling(REPLAY, self.name)
        return None

    def settle(self, trial: Trial, ruling: Ruling) -> None:
        """Forget a confirmation that can no longer succeed."""
        if self.outcome == "failed":
            self.streak = []


__all__ = ["Confirmation", "StopAtSuccess"]

"""A trial as the loop's rules see it (:mod:`learner.stops`): its ledger line, the command it
played, its record and updates. The loop's just-played trial
(:class:`learner.ilc_step.PlayedTrial`) and a resumed run's ledger line
(:class:`learner.ilc.WrittenTrial`) are the two kinds.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from flyknot.record import TrialRecord
from learner.run_directory import TrialSummary

if TYPE_CHECKING:
    from learner.update import UpdateResult


class Trial(ABC):
    """One attempt as the rules see it: the loop's (just played) or a resumed run's (a line
    of its ledger).

    Attributes:
        summary: Its ledger line; the rules complete it (``confirm``, ``average``,
            ``action``) as the loop writes it.
        knots: The command it played (10, 8).
        prev_knots: The command of the trial before, or None (the first trial).
        update: The update computed from it, which the loop's moves step by (a resumed run
            never moves: None there).
        group: The earlier plays of its command whose mean error its update is on (set by the
            averaging rule on a group's last play; empty otherwise).
    """

    update: UpdateResult | None = None
    group: tuple[Trial, ...] = ()

    def __init__(
        self, summary: TrialSummary, knots: np.ndarray, prev_knots: np.ndarray | None
    ) -> None:
        self.summary = summary
        self.knots = knots
        self.prev_knots = prev_knots

    @property
    def measured(self) -> bool:
        """The trial measured an error to learn from: no fault, tracking kept to t_c."""
        return self.summary.fault is None and not self.summary.tracking_lost

    @abstractmethod
    def record(self) -> TrialRecord:
        """What the trial measured."""

    @abstractmethod
    def cost_at(self, t: float) -> float | None:
        """The critical cost of its record at time ``t`` [s] (t_c or an earlier model step),
        None where its markers were lost."""

    @abstractmethod
    def own_update(self) -> tuple[bool | None, np.ndarray | None]:
        """(solved, dkappa) of the update computed from this trial alone (not from the
        mean of an averaging group); dkappa None when there is none."""

    @abstractmethod
    def average_over(self, group: Sequence[Trial]) -> bool | None:
        """Take the update on the mean error of this trial and ``group`` (earlier plays of
        its command) as its update; return whether that QP was solved (None: no update)."""


__all__ = ["Trial"]

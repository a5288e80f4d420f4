"""The base of the ILC loop's stop rules (:mod:`learner.stops`): what a rule rules
(:class:`Ruling`), its hooks and memory (:class:`StopRule`) and what a step's move may ask of
the loop (:class:`Moves`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, is_dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from learner.trial_view import Trial

if TYPE_CHECKING:
    from learner.ilc_params import ILCParams
    from learner.update import UpdateResult

RETRY, STOP, REPLAY, STEP = "retry", "stop", "replay", "step"
"""The kinds of :class:`Ruling`."""


class Moves(Protocol):
    """What a step's move may ask of the loop (:mod:`learner.ilc_step` gives it)."""

    def step(self, knots: np.ndarray, dkappa: np.ndarray) -> np.ndarray:
        """kappa - gain dkappa from ``knots`` (10, 8), halved while it breaks a limit."""
        ...

    def update_about(
        self, trial: Trial, w_control: float, explore: np.ndarray | None = None
    ) -> UpdateResult | None:
        """The update about ``trial``'s record and command again, with the QP's control
        weight ``w_control``, or the exploring update toward ``explore``
        (:func:`learner.update.ilc_update`; None: the model failed on it)."""
        ...


@dataclass(frozen=True)
class Ruling:
    """What a rule says about a trial.

    Attributes:
        kind: ``RETRY``, ``STOP``, ``REPLAY`` or ``STEP``.
        rule: The name of the rule that ruled.
        why: Why the loop stops (``STOP``), else None.
        move: The new command (``STEP``), from the loop's :class:`Moves`; it may complete the
            trial's ledger line (e.g. the QP failed). Only the loop calls it.
    """

    kind: str
    rule: str
    why: str | None = None
    move: Callable[[Moves], np.ndarray] | None = None

    @property
    def stop(self) -> str | None:
        """Why the loop stops, or None (it goes on)."""
        return self.why if self.kind == STOP else None


class StopRule:
    """One rule of the loop and its memory; the hooks do nothing unless overridden."""

    name: ClassVar[str]
    description: ClassVar[str]

    def __init__(self, params: ILCParams) -> None:
        pass

    def screen(self, trial: Trial) -> Ruling | None:
        """Before any memory: a ruling on an attempt that does not count, or None."""
        return None

    def observe(self, trial: Trial) -> None:
        """Take a counted trial into the memory (every rule sees every counted trial)."""

    def verdict(self, trial: Trial) -> Ruling | None:
        """This rule's ruling on the trial, or None (the next rule's turn)."""
        return None

    def settle(self, trial: Trial, ruling: Ruling) -> None:
        """Update the memory once the trial's ruling (maybe another rule's) is known."""

    def w_control(self) -> float | None:
        """The QP's control weight for the next update, or None (the run's own)."""
        return None

    def memory(self) -> dict[str, Any]:
        """The memory as plain data (a trial by its (trial, attempt)): its public
        attributes."""
        return {k: _plain(v) for k, v in vars(self).items() if not k.startswith("_")}


def _plain(v: Any) -> Any:
    """``v`` as lists, dicts and scalars (a trial as its (trial, attempt))."""
    if isinstance(v, Trial):
        return [v.summary.trial, v.summary.attempt]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if hasattr(v, "__dict__") and not is_dataclass(v):
        return {k: _plain(x) for k, x in vars(v).items()}
    return v


__all__ = ["REPLAY", "RETRY", "STEP", "STOP", "Moves", "Ruling", "StopRule"]

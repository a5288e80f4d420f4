"""Who says whether a trial tied the knot: one small interface, three answers.

A :class:`KnotJudge` maps a :class:`~flyknot.record.TrialRecord` to a knot name (``"trefoil"``,
``"unknot"``, another knot's name) or None (not judged). The learner's stop rule asks a judge,
never a cell's internals:

- :class:`CellVerdict` (``"cell"``, the default): the verdict the cell wrote into the record
  when it judged the rope at rest: the simulated lab's ground truth classified with
  :mod:`flyknot.knot`, or the real lab's operator answer.
- :class:`MarkerJudge` (``"markers"``): the rope polyline the motion capture saw at the end
  (fingertip, then the 11 markers of the last frame where all are tracked) classified with
  :func:`flyknot.knot.classify_centreline`. Eleven markers ~0.1 m apart resolve a loose knot
  only: the real lab offers it to the operator as a suggestion.
- :class:`OperatorJudge`: a person's answer (``ask(record, suggestion)`` -> True/False/None),
  shown the markers' suggestion first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from flyknot.errors import ConfigError
from flyknot.knot import DEFAULT_DIRECTIONS, TREFOIL, UNKNOT, classify_centreline
from flyknot.record import TrialRecord


@runtime_checkable
class KnotJudge(Protocol):
    """Anything that judges a trial's knot."""

    def __call__(self, record: TrialRecord) -> str | None:
        """The knot the trial left: a knot name, or None when it cannot be judged."""
        ...


@dataclass(frozen=True)
class CellVerdict:
    """The cell's own verdict, ``record.knot`` (a faulted trial never counts as a success,
    whatever its knot: see :attr:`flyknot.record.TrialRecord.succeeded`)."""

    def __call__(self, record: TrialRecord) -> str | None:
        """``record.knot``."""
        return record.knot


def final_polyline(record: TrialRecord) -> np.ndarray | None:
    """The rope as the markers saw it last: fingertip then markers 0-10, (12, 3) [m].

    The last marker frame with every marker tracked, and the fingertip sample nearest its
    time; None when no frame has all 11 markers.
    """
    ok = np.all(np.isfinite(record.markers), axis=(1, 2))
    if not np.any(ok):
        return None
    k = int(np.flatnonzero(ok)[-1])
    j = int(np.argmin(np.abs(record.t_joint - record.t_marker[k])))
    return np.vstack([record.fingertip_pos[j][None, :], record.markers[k]])


@dataclass(frozen=True)
class MarkerJudge:
    """The knot of the final marker polyline (:func:`final_polyline`).

    Attributes:
        n_directions: Closure directions voted over (:func:`flyknot.knot.classify_centreline`).
    """

    n_directions: int = DEFAULT_DIRECTIONS

    def __call__(self, record: TrialRecord) -> str | None:
        """The polyline's knot, or None when faulted or no frame is fully tracked."""
        if record.fault is not None:
            return None
        line = final_polyline(record)
        if line is None:
            return None
        return classify_centreline(line, n_directions=self.n_directions)


@dataclass(frozen=True)
class OperatorJudge:
    """A person's answer.

    Attributes:
        ask: Called with the record and the suggestion (a knot name or None); returns True
            (knot tied), False (no knot) or None (cannot tell).
        suggest: The judge whose verdict is shown as a suggestion, or None.
    """

    ask: Callable[[TrialRecord, str | None], bool | None]
    suggest: KnotJudge | None = MarkerJudge()

    def __call__(self, record: TrialRecord) -> str | None:
        """``"trefoil"``, ``"unknot"`` or None, as the person answers."""
        if record.fault is not None:
            return None
        hint = self.suggest(record) if self.suggest is not None else None
        answer = self.ask(record, hint)
        if answer is None:
            return None
        return TREFOIL if answer else UNKNOT


JUDGES: dict[str, Callable[[], KnotJudge]] = {"cell": CellVerdict, "markers": MarkerJudge}
"""Judges that need no person, by name (an operator judge is built with its prompt)."""


def get_judge(name: str) -> KnotJudge:
    """The judge called ``name``; the error lists the valid names."""
    if name not in JUDGES:
        raise ConfigError("judge", f"unknown knot judge {name!r}", sorted(JUDGES))
    return JUDGES[name]()

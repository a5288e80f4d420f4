"""Who says whether a trial tied the knot: one small interface, three answers.

A :class:`KnotJudge` maps a :class:`~flyknot.record.TrialRecord` to a
:class:`~flyknot.verdict.Verdict` (the class, the knot, the closure vote and where the knot
sits) or None (not judged). The learner's stop rule, the repeats, the anatomy, the baselines
and the gym envs ask a judge, never a cell's internals, and count ``verdict.success`` only:

- :class:`CellVerdict` (``"cell"``, the default): the verdict the cell wrote into the record
  when it judged the rope at rest: the simulated lab's ground truth judged with
  :func:`flyknot.verdict.judge_centreline`, or the real lab's operator answer.
- :class:`MarkerJudge` (``"markers"``): the rope polyline the motion capture saw at the end
  (fingertip, then the 11 markers of the last frame where all are tracked) judged with
  :func:`flyknot.verdict.judge_centreline`, the tube's axis from the fingertip's orientation.
  Eleven markers ~0.1 m apart resolve a loose knot only: the real lab offers it to the
  operator as a suggestion.
- :class:`OperatorJudge`: a person's answer, one of :data:`flyknot.verdict.OPERATOR_ANSWERS`
  (``"knot"`` in the hanging rope, ``"wrapped"`` round the held end or tube, ``"floor"`` a
  knot lying on the floor, ``"none"``) or
  None (cannot tell), shown the markers' suggestion first.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from flyknot.errors import ConfigError
from flyknot.record import TrialRecord
from flyknot.verdict import JudgeParams, Verdict, judge_centreline, operator_verdict, tube_axis_of


@runtime_checkable
class KnotJudge(Protocol):
    """Anything that judges a trial's knot."""

    def __call__(self, record: TrialRecord) -> Verdict | None:
        """The trial's verdict, or None when it cannot be judged."""
        ...


@dataclass(frozen=True)
class CellVerdict:
    """The cell's own verdict, ``record.verdict`` (a faulted trial never counts as a success,
    whatever its verdict: see :attr:`flyknot.record.TrialRecord.succeeded`)."""

    def __call__(self, record: TrialRecord) -> Verdict | None:
        """``record.verdict``."""
        return record.verdict


def final_polyline(record: TrialRecord) -> tuple[np.ndarray, np.ndarray] | None:
    """The rope as the markers saw it last: fingertip then markers 0-10, (12, 3) [m], and the
    tube's axis (the fingertip's z axis) at that time, (3,).

    The last marker frame with every marker tracked, and the fingertip sample nearest its
    time; None when no frame has all 11 markers.
    """
    ok = np.all(np.isfinite(record.markers), axis=(1, 2))
    if not np.any(ok):
        return None
    k = int(np.flatnonzero(ok)[-1])
    j = int(np.argmin(np.abs(record.t_joint - record.t_marker[k])))
    line = np.vstack([record.fingertip_pos[j][None, :], record.markers[k]])
    return line, tube_axis_of(record.fingertip_quat[j])


ROPE_DIAMETER_KEY = "rope_diameter_m"
"""The record metadata key of the rope's diameter [m] (the lab's records carry it)."""


def judge_params_for(metadata: Mapping[str, Any], params: JudgeParams | None = None) -> JudgeParams:
    """``params`` for the rope a record's metadata names by its diameter
    (``ROPE_DIAMETER_KEY``, :func:`with_rope_diameter`); unchanged when the metadata has no
    diameter (a record of the real lab: its operator decides)."""
    diameter = metadata.get(ROPE_DIAMETER_KEY)
    if not isinstance(diameter, (int, float)) or isinstance(diameter, bool):
        return JudgeParams() if params is None else params
    return with_rope_diameter(float(diameter), params)


def with_rope_diameter(diameter: float, params: JudgeParams | None = None) -> JudgeParams:
    """``params`` with the radius ``r = d / 2`` of a rope of diameter ``d`` [m], by which the
    judge tells a knot lying on the floor (:func:`flyknot.verdict.on_the_floor`)."""
    params = JudgeParams() if params is None else params
    return dataclasses.replace(params, rope_radius_m=0.5 * diameter)


@dataclass(frozen=True)
class MarkerJudge:
    """The verdict on the final marker polyline (:func:`final_polyline`).

    Attributes:
        params: How the polyline is judged (:class:`flyknot.verdict.JudgeParams`).
    """

    params: JudgeParams = field(default_factory=JudgeParams)

    def __call__(self, record: TrialRecord) -> Verdict | None:
        """The polyline's verdict, or None when faulted or no frame is fully tracked."""
        if record.fault is not None:
            return None
        seen = final_polyline(record)
        if seen is None:
            return None
        line, axis = seen
        params = judge_params_for(record.metadata, self.params)
        return judge_centreline(line, axis, params, source="markers")


@dataclass(frozen=True)
class OperatorJudge:
    """A person's answer.

    Attributes:
        ask: Called with the record and the suggestion (a verdict or None); returns
            ``"knot"`` (an overhand knot in the hanging rope), ``"wrapped"`` (looped round the
            held end or the tube), ``"none"`` or None (cannot tell).
        suggest: The judge whose verdict is shown as a suggestion, or None.
    """

    ask: Callable[[TrialRecord, Verdict | None], str | None]
    suggest: KnotJudge | None = MarkerJudge()

    def __call__(self, record: TrialRecord) -> Verdict | None:
        """The operator's verdict (:func:`flyknot.verdict.operator_verdict`), or None."""
        if record.fault is not None:
            return None
        hint = self.suggest(record) if self.suggest is not None else None
        answer = self.ask(record, hint)
        return None if answer is None else operator_verdict(answer)


JUDGES: dict[str, Callable[[], KnotJudge]] = {"cell": CellVerdict, "markers": MarkerJudge}
"""Judges that need no person, by name (an operator judge is built with its prompt)."""


def get_judge(name: str) -> KnotJudge:
    """The judge called ``name``; the error lists the valid names."""
    if name not in JUDGES:
        raise ConfigError("judge", f"unknown knot judge {name!r}", sorted(JUDGES))
    return JUDGES[name]()

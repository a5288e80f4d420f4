"""The knot verdict a person would agree with: the knot, its vote, where it sits, and a class.

The paper's success is "a topological overhand knot in a rope hanging down at the end of
motion". A rope centreline is open, so its knot type depends on how its ends are closed
(:mod:`flyknot.knot`). Two facts of a held rope fix the closure and the verdict here:

**The held end continues into the tube.** The rope is clamped in the fingertip tube, so its
physical continuation at the held end is the tube and the arm, not free space. The held end
is extended by a straight segment of ``tube_length_m`` along the tube's axis (into the arm);
the end of that segment and the free end are then closed by parallel rays, voted over
``n_directions`` directions (:func:`flyknot.knot.closure_votes`). With the held end free
instead (both ends on rays), a rope looped round its own held end is threaded by the held
end's ray in about half the directions: the vote is a coin flip (measured on the lab's
wrapped trials: 15-16 of 31 either way, against 31 of 31 with the tube closure;
``docs/judge.md``).

**A knot must sit in the hanging rope.** The shortest knotted sub-arc (the knot's "core",
after the knotted-core idea of Millett, Dobay & Stasiak, Macromolecules 38 (2005) 601-606)
is found by trimming the rope from the free end, then from the held end, while the trimmed
arc still has the knot (:func:`knot_core`). If the knot needs the tube, or its core starts
within ``clearance_m`` of the held end, the rope is looped round its held end or the tube:
``wrapped_at_grip``, not a flying knot. If the rope lies on the floor and the core on the
floor or on the rope lying there (:func:`on_the_floor`), the knot is not in a rope hanging
down, and the floor may have helped tie it: ``on_floor``, not a flying knot either.

Classes (:data:`CLASSES`):

===================  =====================================================================
``knot``             an overhand knot (trefoil), a supermajority of closures, core clear
                     of the held end: the only success
``wrapped_at_grip``  a knot whose core reaches the held end or needs the tube, or a rope
                     that is unknotted with the tube but whose free-ray closures of the
                     held end thread a loop (a loop round the held end), or a rope that
                     lies round the tube (:func:`round_the_tube`)
``ambiguous``        no knot type has a supermajority of closures
``on_floor``         a knot (any type) with a supermajority lying on the floor (on it or on
                     the rope lying there)
``other_knot``       another knot (figure-eight, ...) with a supermajority, clear of the grip
``unknot``           a supermajority of closures say unknot
===================  =====================================================================

Nothing ambiguous counts: :attr:`Verdict.success` is True for ``knot`` only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flyknot.errors import (
    ConfigError,
    RecordError,
    check_choice,
    check_int,
    check_nonnegative,
    check_positive,
)
from flyknot.geometry import quat_to_matrix
from flyknot.knot import (
    DEFAULT_DIRECTIONS,
    TREFOIL,
    UNKNOT,
    check_points,
    closure_votes,
    plurality,
)

KNOT = "knot"
WRAPPED_AT_GRIP = "wrapped_at_grip"
AMBIGUOUS = "ambiguous"
OTHER_KNOT = "other_knot"
ON_FLOOR = "on_floor"
UNKNOTTED = "unknot"

CLASSES = (KNOT, WRAPPED_AT_GRIP, AMBIGUOUS, ON_FLOOR, OTHER_KNOT, UNKNOTTED)
"""Every verdict class; ``knot`` is the only success."""

SOURCES = ("truth", "markers", "operator")
"""Where a verdict's centreline came from: the simulator's rope, the motion capture, a person."""

JUDGE_NAME = "verdict"
"""How run summaries name this judge (``"judge"``): their counts are verdicts' classes."""

OPERATOR_ANSWERS = {"knot": KNOT, "wrapped": WRAPPED_AT_GRIP, "floor": ON_FLOOR, "none": UNKNOTTED}
"""What an operator of the real lab answers, and the class each answer gives."""


@dataclass(frozen=True)
class JudgeParams:
    """How a rope is judged (``docs/judge.md`` for the measured distributions behind them).

    Attributes:
        n_directions: Closure directions of the whole-rope vote (odd: no ties).
        supermajority: Smallest fraction of the whole-rope vote a knot type needs to count,
            in (0.5, 1]. Over the recorded trials of ``docs/judge.md`` the tube-closure vote
            is 31 of 31 in all but a few and never below 21; 2/3 (21 of 31) leaves room for
            the threading directions of a knot low in the rope (the lowest counted knot votes
            24 of 31) while a coin flip (about half) never passes.
        clearance_m: Smallest arc length from the held end to the knot's core [m]: 0.10 m,
            the first marker's distance from the fingertip, so that a counted knot lies in the
            rope the motion capture sees and a loop round the tube (which sits above the first
            marker) never counts.
        tube_length_m: Length of the straight continuation of the held end along the tube's
            axis [m]; the arm's scale (about 1 m), several times the rope's knots.
        core_directions: Closure directions of each trimmed-arc test of :func:`knot_core`.
        wrap_radius_m: A rope point behind the tube's tip (on the arm's side) and within this
            distance of the tube's axis lies round the tube [m]. A rope lying on the tube has
            its centreline at the tube's radius (10 mm, ``assets/xarm7/xarm7.xml``) plus its
            own (3.5-12.5 mm for the paper's ropes): 14-23 mm; 0.05 m also takes a loose turn
            of about twice that.
        floor_z_m: Height of the floor in the centreline's frame [m]: 0 in the lab frame,
            whose origin lies on the floor (``flyknot.record``: the base's z is its height
            above the floor); None: no floor (a bench rope hanging in free space).
        rope_radius_m: The rope's radius [m] (half its diameter; the lab's records carry
            it as ``metadata["rope_diameter_m"]``: :func:`flyknot.judge.judge_params_for`).
        floor_clearance_m: A rope whose centreline comes within ``rope_radius_m +
            floor_clearance_m`` of the floor touches it [m]. A rope resting on the lab's floor
            lies with its centreline at its radius or up to 1 mm below it (MuJoCo's soft
            contact; measured over the lab's knots on the floor: -0.9 to 0 mm); 5 mm above
            that is clear of the floor by several times what a resting rope sinks into it
            (``docs/judge.md``: the knots of the paper's runs by height, and the clearance
            across a bracket).
    """

    n_directions: int = DEFAULT_DIRECTIONS
    supermajority: float = 2 / 3
    clearance_m: float = 0.10
    tube_length_m: float = 1.0
    core_directions: int = 15
    wrap_radius_m: float = 0.05
    floor_z_m: float | None = 0.0
    rope_radius_m: float = 0.0
    floor_clearance_m: float = 0.005

    def __post_init__(self) -> None:
        check_int("n_directions", self.n_directions, minimum=1)
        check_int("core_directions", self.core_directions, minimum=1)
        if not (0.5 < self.supermajority <= 1.0):
            raise ConfigError("supermajority", f"must be in (0.5, 1], got {self.supermajority!r}")
        check_positive("clearance_m", self.clearance_m)
        check_positive("tube_length_m", self.tube_length_m)
        check_positive("wrap_radius_m", self.wrap_radius_m)
        check_nonnegative("rope_radius_m", self.rope_radius_m)
        check_positive("floor_clearance_m", self.floor_clearance_m)
        if self.floor_z_m is not None and not math.isfinite(self.floor_z_m):
            raise ConfigError(
                "floor_z_m", f"must be a finite height or None, got {self.floor_z_m!r}"
            )


@dataclass(frozen=True)
class Verdict:
    """A judged rope with its evidence.

    Attributes:
        klass: One of :data:`CLASSES`.
        knot: The knot type with the most closure votes (``"trefoil"``, ``"unknot"``, ...).
        votes: Closure votes per knot type (empty for an operator's verdict).
        core: First and last vertex of the knot's shortest knotted sub-arc (0 = held end),
            or None (no knot, or an operator's verdict).
        core_from_held_m: Arc length from the held end to the core's first vertex [m]; 0 when
            the knot needs the tube; None without a core.
        source: One of :data:`SOURCES`.
    """

    klass: str
    knot: str
    votes: Mapping[str, int] = field(default_factory=dict)
    core: tuple[int, int] | None = None
    core_from_held_m: float | None = None
    source: str = "truth"

    def __post_init__(self) -> None:
        check_choice("klass", self.klass, CLASSES)
        check_choice("source", self.source, SOURCES)
        if not isinstance(self.knot, str) or not self.knot:
            raise RecordError(f"Verdict.knot must be a knot name, got {self.knot!r}")
        object.__setattr__(self, "votes", {str(k): int(v) for k, v in dict(self.votes).items()})
        if self.core is not None:
            object.__setattr__(self, "core", (int(self.core[0]), int(self.core[1])))

    @property
    def success(self) -> bool:
        """An overhand knot in the hanging rope: class ``knot``, nothing else."""
        return self.klass == KNOT

    @property
    def share(self) -> float | None:
        """Fraction of the closure votes for :attr:`knot`, or None without votes."""
        total = sum(self.votes.values())
        return self.votes.get(self.knot, 0) / total if total else None

    def to_json(self) -> dict[str, Any]:
        """Plain data for a record's or a ledger's JSON."""
        return {
            "klass": self.klass,
            "knot": self.knot,
            "votes": dict(self.votes),
            "core": list(self.core) if self.core is not None else None,
            "core_from_held_m": self.core_from_held_m,
            "source": self.source,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Verdict:
        """Inverse of :meth:`to_json`; unknown or missing keys raise :class:`RecordError`."""
        keys = {"klass", "knot", "votes", "core", "core_from_held_m", "source"}
        if not isinstance(data, Mapping) or set(data) != keys:
            got = sorted(data) if isinstance(data, Mapping) else type(data).__name__
            raise RecordError(f"verdict: expected keys {sorted(keys)}, got {got}")
        core = data["core"]
        return cls(
            klass=data["klass"],
            knot=data["knot"],
            votes=data["votes"],
            core=tuple(core) if core is not None else None,
            core_from_held_m=data["core_from_held_m"],
            source=data["source"],
        )

    def describe(self) -> str:
        """One line: class, knot, vote and where the knot sits."""
        vote = f"{self.votes.get(self.knot, 0)}/{sum(self.votes.values())}" if self.votes else "-"
        where = "" if self.core_from_held_m is None else f", {self.core_from_held_m:.2f} m down"
        return f"{self.klass} ({self.knot} {vote}{where})"


def operator_verdict(answer: str) -> Verdict:
    """The verdict of a person's answer: ``"knot"`` (in the hanging rope), ``"wrapped"``,
    ``"floor"`` (a knot lying on the floor) or ``"none"``; the error lists the valid answers."""
    check_choice("answer", answer, tuple(OPERATOR_ANSWERS))
    klass = OPERATOR_ANSWERS[answer]
    return Verdict(klass=klass, knot=UNKNOT if klass == UNKNOTTED else TREFOIL, source="operator")


# --------------------------------------------------------------------------------------------
# Closure and core


def with_tube(points: np.ndarray, tube_axis: np.ndarray | None, length: float) -> np.ndarray:
    """The centreline with its held end continued into the tube, shape (n + 1, 3) [m].

    ``p_tube = p_0 - length * a``, with ``a`` the unit tube axis pointing out of the tube (the
    direction the rope leaves it); without ``a`` the first segment's direction
    ``(p_1 - p_0) / |p_1 - p_0|`` is used (the lab clamps the first segment in the tube).

    Args:
        points: Centreline, held end first, shape (n, 3) [m].
        tube_axis: Out of the tube, shape (3,) [-], or None.
        length: Length of the continuation [m].
    """
    p = np.asarray(points, dtype=float)
    a = p[1] - p[0] if tube_axis is None else np.asarray(tube_axis, dtype=float)
    norm = float(np.linalg.norm(a))
    if not np.isfinite(norm) or norm == 0.0:
        raise RecordError("tube_axis: must be a finite, non-zero vector")
    return np.vstack([p[0] - length * a / norm, p])


def _has_knot(arc: np.ndarray, knot: str, n_directions: int) -> bool:
    """Whether ``knot`` has the most closure votes of ``arc`` (ties: not)."""
    if arc.shape[0] < 4:
        return False
    votes = closure_votes(arc, n_directions=n_directions, stop_early=True)
    best = max(votes.values())
    return votes.get(knot, 0) == best and sum(v == best for v in votes.values()) == 1


def _continued(arc: np.ndarray, length: float) -> np.ndarray:
    """``arc`` with its first point continued straight back along its first segment by
    ``length`` [m]: the trimmed rope replaced by a straight one, as the tube does for the
    held end."""
    return with_tube(arc, arc[1] - arc[0], length)


def knot_core(
    tubed: np.ndarray, knot: str, n_directions: int, length: float = 1.0
) -> tuple[int, int]:
    """Shortest knotted sub-arc of a tube-continued centreline, by trimming.

    ``j* = min { j : P[0..j] has knot }`` (trim from the free end), then
    ``i* = max { i <= j* : P[i..j*] has knot }`` (trim from the held end), where ``P`` is
    :func:`with_tube`'s output (index 0 the tube's end) and "has knot" is the most votes over
    ``n_directions`` ray closures; an arc trimmed at the held end is continued straight back
    along its first segment by ``length`` first, as the tube continues the whole rope (free
    rays from a point just above a loose knot would thread it). Each bound is found by
    bisection, which assumes that trimming past the knot's end unties it and trimming less
    does not (true of a single knot; for anything else the result is one knotted sub-arc,
    not necessarily the shortest).

    Args:
        tubed: Tube-continued centreline, shape (n + 1, 3) [m].
        knot: The knot type looked for.
        n_directions: Closure directions per test.
        length: Straight continuation of a trimmed held end [m].

    Returns:
        ``(i*, j*)`` in the indices of ``tubed``; ``i* = 0`` means the knot needs the tube.
    """
    lo, hi = 3, tubed.shape[0] - 1  # P[0..hi] has the knot
    while lo < hi:
        mid = (lo + hi) // 2
        if _has_knot(tubed[: mid + 1], knot, n_directions):
            hi = mid
        else:
            lo = mid + 1
    j = hi
    lo, hi = 0, max(j - 3, 0)  # P[lo..j] has the knot
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if _has_knot(_continued(tubed[mid : j + 1], length), knot, n_directions):
            lo = mid
        else:
            hi = mid - 1
    return lo, j


def round_the_tube(points: np.ndarray, tubed: np.ndarray, radius: float) -> bool:
    """Whether the rope lies round the tube: a point p_k, k >= 2, behind the tip,
    ``(p_k - p_0) . a < 0``, within ``radius`` [m] of the axis line, ``a`` the unit axis out
    of the tube (from ``tubed``, :func:`with_tube`'s output)."""
    a = points[0] - tubed[0]
    a = a / np.linalg.norm(a)
    rel = points[2:] - points[0]
    along = rel @ a
    off = np.linalg.norm(rel - along[:, None] * a, axis=1)
    return bool(np.any((along < 0.0) & (off < radius)))


def on_the_floor(points: np.ndarray, core: tuple[int, int], params: JudgeParams) -> bool:
    """Whether a knot lies on the floor: the rope touches the floor, ``min_k z_k - z_f < r +
    c``, and the knot's core lies on it or on the rope lying there, ``min_{k in core} z_k -
    z_f < 3 r + c`` (a strand on a strand on the floor has its centreline 3 r up), with ``r``
    the rope's radius, ``c`` ``floor_clearance_m`` and ``z_f`` the floor's height; never
    without a floor (``floor_z_m`` None).

    Args:
        points: Centreline, held end first, shape (n, 3) [m].
        core: First and last vertex of the knot's core in ``points``.
        params: The floor's height, the rope's radius and the clearance.
    """
    if params.floor_z_m is None:
        return False
    r, c = params.rope_radius_m, params.floor_clearance_m
    height = points[:, 2] - params.floor_z_m
    return bool(height.min() < r + c and height[core[0] : core[1] + 1].min() < 3 * r + c)


def _held_end_threaded(points: np.ndarray, params: JudgeParams) -> bool:
    """Whether a loop surrounds the held end: with the held end closed by free rays instead of
    the tube, the unknot loses its supermajority (only the held end's closure differs)."""
    votes = closure_votes(points, n_directions=params.n_directions)
    return votes.get(UNKNOT, 0) < params.supermajority * sum(votes.values())


def judge_centreline(
    points: object,
    tube_axis: np.ndarray | None = None,
    params: JudgeParams = JudgeParams(),
    source: str = "truth",
) -> Verdict:
    """The verdict on a rope hanging from the tube (module docstring).

    Args:
        points: Centreline, held end first, shape (n, 3) [m], n >= 4, finite.
        tube_axis: Unit vector out of the tube (fingertip z axis), shape (3,); None: the
            first segment's direction.
        params: Thresholds and closure settings.
        source: One of :data:`SOURCES`.

    Returns:
        The :class:`Verdict`.

    Raises:
        RecordError: Bad centreline or tube axis.
    """
    p = check_points(points)
    tubed = with_tube(p, tube_axis, params.tube_length_m)
    votes = closure_votes(tubed, n_directions=params.n_directions)
    total = sum(votes.values())
    ranked = sorted(votes, key=lambda k: (-votes[k], k != UNKNOT))
    top = ranked[0]
    decisive = votes[top] >= params.supermajority * total
    if top == UNKNOT and decisive:
        if round_the_tube(p, tubed, params.wrap_radius_m) or _held_end_threaded(p, params):
            return Verdict(WRAPPED_AT_GRIP, UNKNOT, votes, None, 0.0, source)
        return Verdict(UNKNOTTED, UNKNOT, votes, source=source)
    knot = top if top != UNKNOT else ranked[1]
    i, j = knot_core(tubed, knot, params.core_directions, params.tube_length_m)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    core = (max(i - 1, 0), j - 1)
    from_held = 0.0 if i == 0 else float(arc[i - 1])
    if from_held < params.clearance_m or round_the_tube(p, tubed, params.wrap_radius_m):
        klass = WRAPPED_AT_GRIP
    elif not decisive:
        klass = AMBIGUOUS
    elif on_the_floor(p, core, params):
        klass = ON_FLOOR
    else:
        klass = KNOT if knot == TREFOIL else OTHER_KNOT
    return Verdict(klass, top, votes, core, from_held, source)


def tube_knot(
    points: object,
    tube_axis: np.ndarray | None = None,
    params: JudgeParams = JudgeParams(),
) -> str:
    """The knot type with the most tube-closure votes (no core, no class): the cheap check of
    a rope's shape over time (settling, knot histories, search scores).

    Args:
        points: Centreline, held end first, shape (n, 3) [m].
        tube_axis: Unit vector out of the tube, or None (the first segment's direction).
        params: Closure settings (``n_directions``, ``tube_length_m``).
    """
    tubed = with_tube(check_points(points), tube_axis, params.tube_length_m)
    return plurality(closure_votes(tubed, n_directions=params.n_directions, stop_early=True))


def tube_axis_of(quat: np.ndarray) -> np.ndarray:
    """The fingertip's z axis (out of the tube) from its quaternion (w, x, y, z), shape (3,)."""
    return quat_to_matrix(np.asarray(quat, dtype=float))[:, 2]

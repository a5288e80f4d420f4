"""Failure anatomy: why each trial of a set failed, read from its record alone.

Every trial gets one label (:data:`LABELS`, in order of precedence; the first that applies):

=================  ==========================================================================
``success``        the verdict at the end is a knot in the hanging rope (class ``knot`` of
                   :mod:`flyknot.verdict`) and no fault
``faulted``        the controller aborted the trial (``record.fault`` set)
``markers_lost``   motion capture lost the rope at or before the critical time t_c (given by
                   the caller, from the demonstration), so the learner cannot measure it
``no_contact``     the rope never touched itself (``first_contact_time`` None)
``wrapped_at_grip`` the rope is looped round its held end or the tube: a knot type that
                   needs the tube or sits within the judge's clearance of the held end
``ambiguous``      no knot type has a supermajority of the closure vote
``on_floor``       a knot lying on the floor, not in the hanging rope
``not_through``    it touched itself, but no trefoil appears after the contact: the free end
                   never went through the loop
``slipped_out``    a trefoil appears after the contact but never lasts ``PERSIST_S``: the end
                   passed through the loop and slipped out again
``shaken_loose``   a trefoil lasted ``PERSIST_S`` or longer and was lost before the end
``other_knot``     another knot at the end (e.g. ``4_1``, the figure-eight, or ``other``)
``unknown``        the record cannot tell (see below)
=================  ==========================================================================

A trial labelled ``markers_lost`` also keeps the label its outcome alone gives
(:attr:`Diagnosis.outcome`), so a table can say what happened to the rope as well.

**Knot history.** ``not_through``, ``slipped_out`` and ``shaken_loose`` need the knot type of
the rope over time. It comes from the simulator's truth centreline when the record has one:
frames from the first contact on, every ``HISTORY_STEP_S`` (and the last frame), each judged
by :func:`flyknot.verdict.tube_knot`: the held end continued along the tube, the free end
closed by rays in 31 directions (never "free end down", the closure that invents knots while
the free end is above the held end); so frames are judged whatever the height of the free
end and none is dropped. Without truth, the
lab's own verdict history is used if the record has one (``metadata["knot_history"]`` or
``metadata["settle"]["knot_history"]``: ``{"t": [...], "verdict": [...]}``). It shows a knot
and how long it held, but only rules out a slip when its verdicts, from the first contact on,
are no further apart than ``HISTORY_STEP_S``: the lab's history starts at the end of the
command and has a verdict every 0.25 s, so without a trefoil in it the trial is ``unknown``.
A record from the real lab without either history ends as ``unknown`` whenever the history
decides.

**Contact.** In the simulated lab (``metadata["cell"] == "sim"``, a replay, or any record with
truth) ``first_contact_time`` None means "no contact". The real lab leaves it None unless an
operator annotates it, so there None means "not known" and a failure without a knot history is
``unknown``.

**Duration of a trefoil.** A run of consecutive trefoil frames lasts from halfway between its
first frame and the frame before it to halfway between its last frame and the frame after it
(its first or last frame at either end of the history): ``n`` frames ``dt`` apart last
``n dt``.

**Tracking lost.** A marker frame is lost when any of the 11 markers is NaN; tracking is lost
at the first frame of the first run of lost frames that lasts ``MIN_LOSS_S`` or reaches the
end of the record (shorter dropouts are bridged).

The end verdict is ``record.verdict``; when it is None (not judged, or a record written
before verdicts carried their evidence) the last finite truth frame is judged with
:func:`flyknot.verdict.judge_centreline`. ``metadata["settle"]`` (``settled``,
``contact_free``, ``knot_set``, ``settle_s`` or ``settle_time_s``, ``free_end_speed_m_s``),
when present, adds a note to the reason of a rope judged before it was at rest.

Reading trials (records, replay files, directories): :mod:`flyknot_app.anatomy.trials`; the
anatomy of a set of trials, its tables and figures: :mod:`flyknot_app.anatomy.report`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
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
from flyknot.knot import TREFOIL, UNKNOT
from flyknot.record import TrialRecord
from flyknot.verdict import AMBIGUOUS as AMBIGUOUS_CLASS
from flyknot.verdict import ON_FLOOR as ON_FLOOR_CLASS
from flyknot.verdict import OTHER_KNOT as OTHER_CLASS
from flyknot.verdict import WRAPPED_AT_GRIP, JudgeParams, Verdict, judge_centreline
from flyknot_app.anatomy.trials import TrialEvidence, judge_params_of

# --- labels ----------------------------------------------------------------------------------
SUCCESS = "success"
FAULTED = "faulted"
MARKERS_LOST = "markers_lost"
NO_CONTACT = "no_contact"
WRAPPED = "wrapped_at_grip"
AMBIGUOUS = "ambiguous"
ON_FLOOR = "on_floor"
NOT_THROUGH = "not_through"
SLIPPED_OUT = "slipped_out"
SHAKEN_LOOSE = "shaken_loose"
OTHER_KNOT = "other_knot"
UNKNOWN = "unknown"

LABELS = (
    SUCCESS,
    FAULTED,
    MARKERS_LOST,
    NO_CONTACT,
    WRAPPED,
    AMBIGUOUS,
    ON_FLOOR,
    NOT_THROUGH,
    SLIPPED_OUT,
    SHAKEN_LOOSE,
    OTHER_KNOT,
    UNKNOWN,
)
"""Every label, in order of precedence."""

DESCRIPTIONS = {
    SUCCESS: "knot in the hanging rope, no fault",
    FAULTED: "the controller aborted the trial",
    MARKERS_LOST: "mocap lost the rope at or before t_c",
    NO_CONTACT: "the rope never touched itself",
    WRAPPED: "looped round the held end or tube",
    AMBIGUOUS: "no knot type has a supermajority",
    ON_FLOOR: "a knot lying on the floor, not hanging",
    NOT_THROUGH: "touched, but the end never went through",
    SLIPPED_OUT: "end went through the loop, slipped out",
    SHAKEN_LOOSE: "knot tied, then shaken loose",
    OTHER_KNOT: "a different knot at the end",
    UNKNOWN: "the record cannot tell",
}
"""One line per label, for tables."""

COLOURS = {
    SUCCESS: "#2ca02c",
    FAULTED: "#404040",
    MARKERS_LOST: "#9467bd",
    NO_CONTACT: "#c7c7c7",
    WRAPPED: "#8c564b",
    AMBIGUOUS: "#e377c2",
    ON_FLOOR: "#17becf",
    NOT_THROUGH: "#ff7f0e",
    SLIPPED_OUT: "#e6c229",
    SHAKEN_LOOSE: "#d62728",
    OTHER_KNOT: "#1f77b4",
    UNKNOWN: "#f0f0f0",
}
"""Bar colour of each label in :func:`plot_anatomy`."""

# --- thresholds ------------------------------------------------------------------------------
PERSIST_S = 0.2
"""[s] A trefoil lasting this long was tied, not passing through: the free end moves at
2-3 m/s when the knot forms (rope 1, measured), so it crosses a 0.2 m loop in under 0.1 s."""

HISTORY_STEP_S = 0.04
"""[s] Spacing of the judged truth frames: 5 frames per ``PERSIST_S`` (a knot that persists
is never one frame), at about 25 ms of classification per frame."""

MIN_LOSS_S = 0.015
"""[s] Shortest marker dropout that counts as tracking lost: shorter gaps are bridged by the
learner's critical-point fit (``MarkerFitParams.max_extrapolation``)."""

_TIME_TOL = 1e-9  # [s] float rounding of sample times

_VERDICT_LABELS = {
    WRAPPED_AT_GRIP: WRAPPED,
    AMBIGUOUS_CLASS: AMBIGUOUS,
    ON_FLOOR_CLASS: ON_FLOOR,
    OTHER_CLASS: OTHER_KNOT,
}
"""Verdict classes that are their own failure label."""


@dataclass(frozen=True)
class AnatomyParams:
    """Thresholds of :func:`diagnose` (module constants by default).

    Attributes:
        persist_s: A trefoil lasting at least this long was tied (``shaken_loose`` when lost),
            a shorter one slipped (``slipped_out``) [s].
        history_step_s: Spacing of the truth frames judged for the knot history [s].
        min_loss_s: Shortest marker dropout that counts as tracking lost [s].
        n_directions: Closure directions of each knot verdict.
    """

    persist_s: float = PERSIST_S
    history_step_s: float = HISTORY_STEP_S
    min_loss_s: float = MIN_LOSS_S
    n_directions: int = 31

    def __post_init__(self) -> None:
        check_positive("persist_s", self.persist_s)
        check_positive("history_step_s", self.history_step_s)
        check_nonnegative("min_loss_s", self.min_loss_s)
        check_int("n_directions", self.n_directions, minimum=1)


@dataclass(frozen=True)
class KnotHistory:
    """Knot verdicts of a rope over time.

    Attributes:
        t: Times of the verdicts [s], increasing.
        verdicts: One knot name per time (``"unknot"``, ``"trefoil"``, ...).
        source: ``"truth"`` (judged here from the truth centreline) or ``"metadata"`` (the
            lab's own verdicts).
    """

    t: tuple[float, ...]
    verdicts: tuple[str, ...]
    source: str

    def __post_init__(self) -> None:
        t = tuple(float(x) for x in self.t)
        verdicts = tuple(str(v) for v in self.verdicts)
        if len(t) != len(verdicts):
            raise RecordError(
                f"knot history: {len(t)} times but {len(verdicts)} verdicts (need one each)"
            )
        if not all(math.isfinite(x) for x in t) or any(b <= a for a, b in itertools.pairwise(t)):
            raise RecordError("knot history: times must be finite and increasing")
        check_choice("KnotHistory.source", self.source, ("truth", "metadata"))
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "verdicts", verdicts)

    def trefoil_runs(self) -> tuple[tuple[float, float], ...]:
        """(start, end) [s] of each run of consecutive trefoil verdicts (module docstring)."""
        t, v = self.t, self.verdicts
        runs = []
        i = 0
        while i < len(v):
            if v[i] != TREFOIL:
                i += 1
                continue
            j = i
            while j + 1 < len(v) and v[j + 1] == TREFOIL:
                j += 1
            start = t[i] if i == 0 else 0.5 * (t[i - 1] + t[i])
            end = t[j] if j == len(v) - 1 else 0.5 * (t[j] + t[j + 1])
            runs.append((start, end))
            i = j + 1
        return tuple(runs)


@dataclass(frozen=True)
class Diagnosis:
    """Why one trial ended as it did.

    Attributes:
        name: The trial's name.
        label: One of :data:`LABELS`.
        reason: One line with the numbers behind the label.
        outcome: The label the outcome alone gives when ``label`` is ``markers_lost`` (what
            happened to the rope), else equal to ``label``.
        knot: The end verdict used (None: not judged).
        first_contact_time: First self-contact [s] or None.
        tracking_lost_time: When motion capture lost the rope [s], or None.
        t_c: The critical time the trial was checked against [s], or None.
        trefoil_runs: (start, end) [s] of each trefoil in the knot history (empty without one).
        history_source: ``"truth"``, ``"metadata"`` or None (no history was needed or found).
        group: Group of the trial in tables (a run or a rope), "" if none.
    """

    name: str
    label: str
    reason: str
    outcome: str
    knot: str | None = None
    first_contact_time: float | None = None
    tracking_lost_time: float | None = None
    t_c: float | None = None
    trefoil_runs: tuple[tuple[float, float], ...] = ()
    history_source: str | None = None
    group: str = ""

    def __post_init__(self) -> None:
        check_choice("Diagnosis.label", self.label, LABELS)
        check_choice("Diagnosis.outcome", self.outcome, LABELS)

    def as_dict(self) -> dict[str, Any]:
        """Plain data (JSON-ready)."""
        d = asdict(self)
        d["trefoil_runs"] = [list(r) for r in self.trefoil_runs]
        return d


# --- evidence helpers ------------------------------------------------------------------------


def tracking_lost_time(
    t_marker: np.ndarray, markers: np.ndarray, min_loss_s: float = MIN_LOSS_S
) -> float | None:
    """When motion capture lost the rope, from the markers alone.

    A frame is lost when any marker is NaN; the result is the time of the first frame of the
    first run of lost frames that lasts at least ``min_loss_s`` (last lost frame minus first,
    plus one frame interval) or reaches the last frame.

    Args:
        t_marker: Marker times, shape (m,) [s].
        markers: Markers, shape (m, 11, 3) [m], NaN where lost.
        min_loss_s: Shortest dropout that counts [s].

    Returns:
        The time [s], or None if tracking is never lost.
    """
    t = np.asarray(t_marker, dtype=float)
    lost = np.isnan(np.asarray(markers, dtype=float)).reshape(len(t), -1).any(axis=1)
    if not lost.any():
        return None
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    edges = np.diff(np.concatenate([[0], lost.astype(int), [0]]))
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        last = stop - 1
        if stop == len(t) or t[last] - t[start] + dt >= min_loss_s - _TIME_TOL:
            return float(t[start])
    return None


def knot_history_from_truth(
    t_truth: np.ndarray,
    centreline: np.ndarray,
    *,
    start: float | None = None,
    step: float = HISTORY_STEP_S,
    n_directions: int = 31,
) -> KnotHistory:
    """Knot verdicts of truth centreline frames, one every ``step`` from ``start`` on.

    Frames are taken greedily: the first at or after ``start``, then each first frame at least
    ``step`` after the last one taken, and the last frame; frames with NaN are skipped.

    Args:
        t_truth: Frame times, shape (k,) [s] (need not be uniform).
        centreline: Frames, shape (k, n, 3) [m], held end first.
        start: Earliest frame time [s] (None: the first frame).
        step: Spacing of the judged frames [s].
        n_directions: Closure directions per verdict.

    Returns:
        The history (``source="truth"``); empty if no finite frame is in range.
    """
    from flyknot.verdict import JudgeParams, tube_knot

    judge = JudgeParams(n_directions=n_directions)
    check_positive("step", step)
    t = np.asarray(t_truth, dtype=float)
    frames = np.asarray(centreline, dtype=float)
    picked: list[int] = []
    next_t = -math.inf if start is None else start - _TIME_TOL
    for k, tk in enumerate(t):
        if tk >= next_t:
            picked.append(k)
            next_t = tk + step - _TIME_TOL
    if picked and picked[-1] != len(t) - 1:
        picked.append(len(t) - 1)
    times, verdicts = [], []
    for k in picked:
        if not np.all(np.isfinite(frames[k])):
            continue
        times.append(float(t[k]))
        verdicts.append(tube_knot(frames[k], params=judge))
    return KnotHistory(tuple(times), tuple(verdicts), "truth")


def metadata_history(metadata: Mapping[str, Any]) -> KnotHistory | None:
    """The lab's own knot history from a record's metadata, or None if it has none.

    Read from ``metadata["knot_history"]`` or ``metadata["settle"]["knot_history"]``, each
    ``{"t": [...], "verdict": [...]}``.

    Raises:
        RecordError: The history is malformed (lengths differ, times not increasing).
    """
    hist = metadata.get("knot_history")
    settle = metadata.get("settle")
    if hist is None and isinstance(settle, Mapping):
        hist = settle.get("knot_history")
    if not isinstance(hist, Mapping) or "t" not in hist or "verdict" not in hist:
        return None
    return KnotHistory(tuple(hist["t"]), tuple(hist["verdict"]), "metadata")


def _settle_note(metadata: Mapping[str, Any]) -> str:
    settle = metadata.get("settle")
    if not isinstance(settle, Mapping) or settle.get("settled", True):
        return ""
    waited = settle.get("settle_time_s", settle.get("settle_s"))
    speed = settle.get("free_end_speed_m_s")
    parts = []
    if isinstance(waited, (int, float)):
        parts.append(f"after {waited:.1f} s")
    if isinstance(speed, (int, float)) and math.isfinite(speed):
        parts.append(f"free end up to {speed:.2f} m/s")
    if settle.get("contact_free"):
        why = "unknotted and free of self-contact"
    elif settle.get("knot_set"):
        why = "with its knot set"
    elif settle.get("unknot_held"):
        why = "unknotted at every verdict of the last "
        why += f"{settle.get('criterion', {}).get('unknot_held_s', float('nan')):g} s"
    else:
        why = "not at rest"
    return f"; judged {why}" + (f" ({', '.join(parts)})" if parts else "")


def _end_verdict(ev: TrialEvidence, n_directions: int) -> Verdict | None:
    """The trial's verdict, or the truth's last finite frame judged, or None."""
    if ev.verdict is not None:
        return ev.verdict
    if ev.fault is None and ev.has_truth:
        for frame in ev.centreline[::-1]:
            if np.all(np.isfinite(frame)):
                params = judge_params_of(ev.metadata, JudgeParams(n_directions=n_directions))
                return judge_centreline(frame, params=params)
    return None


def _history(ev: TrialEvidence, params: AnatomyParams) -> KnotHistory | None:
    if ev.has_truth:
        return knot_history_from_truth(
            ev.t_truth,
            ev.centreline,
            start=ev.first_contact_time,
            step=params.history_step_s,
            n_directions=params.n_directions,
        )
    hist = metadata_history(ev.metadata)
    if hist is not None and ev.first_contact_time is not None:
        keep = [i for i, t in enumerate(hist.t) if t >= ev.first_contact_time - _TIME_TOL]
        hist = KnotHistory(
            tuple(hist.t[i] for i in keep), tuple(hist.verdicts[i] for i in keep), hist.source
        )
    return hist


def _widest_gap(hist: KnotHistory, contact: float | None) -> float:
    """Largest interval [s] without a verdict from the contact (inf if unknown) on."""
    if contact is None:
        return math.inf
    times = (contact, *hist.t)
    return max(b - a for a, b in itertools.pairwise(times))


def _runs_text(runs: Sequence[tuple[float, float]]) -> str:
    shown = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in runs[:3])
    return shown + (f" (+{len(runs) - 3} more)" if len(runs) > 3 else "")


def _outcome(
    ev: TrialEvidence, verdict: Verdict | None, params: AnatomyParams
) -> tuple[str, str, KnotHistory | None]:
    """(label, reason, history) from the outcome alone (no fault, not a success)."""
    contact = ev.first_contact_time
    if contact is None and ev.contact_known and (verdict is None or verdict.klass == UNKNOT):
        return NO_CONTACT, "no self-contact", None
    if verdict is not None and verdict.klass in _VERDICT_LABELS:
        return _VERDICT_LABELS[verdict.klass], verdict.describe(), None
    if verdict is None:
        return UNKNOWN, "no knot verdict at the end and no truth to judge", None
    hist = _history(ev, params)
    touched = "no contact time" if contact is None else f"contact at {contact:.3f} s"
    if hist is None or not hist.t:
        return UNKNOWN, f"{touched}; unknot at the end; no knot history (needs truth)", hist
    runs = hist.trefoil_runs()
    if not runs:
        gap = _widest_gap(hist, contact)
        if hist.source == "truth" or gap <= params.history_step_s + _TIME_TOL:
            return (
                NOT_THROUGH,
                f"{touched}; no trefoil in {len(hist.t)} verdicts ({hist.source}) after it",
                hist,
            )
        why = (
            "without a contact time a slip before it cannot be ruled out"
            if contact is None
            else f"its verdicts are up to {gap:.2f} s apart from the contact on, a slip could "
            "fall between them"
        )
        return UNKNOWN, f"{touched}; no trefoil in the {hist.source} history ({why})", hist
    longest = max(b - a for a, b in runs)
    lost = runs[-1][1]
    text = f"{touched}; trefoil {_runs_text(runs)} ({hist.source}), longest {longest:.2f} s"
    if longest >= params.persist_s - _TIME_TOL:
        return SHAKEN_LOOSE, f"{text} >= {params.persist_s:g} s; lost at {lost:.2f} s", hist
    return SLIPPED_OUT, f"{text} < {params.persist_s:g} s", hist


def diagnose(
    trial: TrialRecord | TrialEvidence,
    *,
    t_c: float | None = None,
    params: AnatomyParams | None = None,
    name: str | None = None,
    group: str = "",
) -> Diagnosis:
    """Label one trial with why it failed (or ``success``); see the module docstring.

    Args:
        trial: A trial record (load it with ``with_truth=True`` for the full anatomy) or
            evidence from :func:`load_replay`.
        t_c: Critical time of the demonstration [s] on the record's marker clock; None skips
            the ``markers_lost`` check.
        params: Thresholds (default :class:`AnatomyParams()`).
        name: Name in tables (default: the evidence's name, or "trial").
        group: Group in tables.

    Returns:
        The :class:`Diagnosis`.

    Raises:
        ConfigError: ``t_c`` is not a finite number >= 0, or ``trial`` has the wrong type.
        RecordError: The record's markers, truth or knot history are malformed.
    """
    params = AnatomyParams() if params is None else params
    if t_c is not None:
        check_nonnegative("t_c", t_c)
    if isinstance(trial, TrialRecord):
        ev = TrialEvidence.from_record(trial, name or "trial")
    elif isinstance(trial, TrialEvidence):
        ev = trial
    else:
        raise ConfigError(
            "trial", f"must be a TrialRecord or TrialEvidence, got {type(trial).__name__}"
        )
    verdict = _end_verdict(ev, params.n_directions)
    end = None if verdict is None else verdict.knot
    lost_at = tracking_lost_time(ev.t_marker, ev.markers, params.min_loss_s)
    common = dict(
        name=name or ev.name,
        knot=end,
        first_contact_time=ev.first_contact_time,
        tracking_lost_time=lost_at,
        t_c=t_c,
        group=group,
    )
    if ev.fault is None and verdict is not None and verdict.success:
        return Diagnosis(label=SUCCESS, outcome=SUCCESS, reason=verdict.describe(), **common)
    if ev.fault is not None:
        return Diagnosis(label=FAULTED, outcome=FAULTED, reason=f"fault: {ev.fault}", **common)
    label, reason, hist = _outcome(ev, verdict, params)
    reason += _settle_note(ev.metadata)
    extra = dict(
        trefoil_runs=() if hist is None else hist.trefoil_runs(),
        history_source=None if hist is None else hist.source,
    )
    if t_c is not None and lost_at is not None and lost_at <= t_c + _TIME_TOL:
        return Diagnosis(
            label=MARKERS_LOST,
            outcome=label,
            reason=f"tracking lost at {lost_at:.3f} s <= t_c {t_c:.3f} s; then {label}: {reason}",
            **common,
            **extra,
        )
    return Diagnosis(label=label, outcome=label, reason=reason, **common, **extra)

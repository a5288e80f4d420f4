"""Failure anatomy: why each trial of a set failed, read from its record alone.

Every trial gets one label (:data:`LABELS`, in order of precedence; the first that applies):

=================  ==========================================================================
``success``        a trefoil at the end and no fault
``faulted``        the controller aborted the trial (``record.fault`` set)
``markers_lost``   motion capture lost the rope at or before the critical time t_c (given by
                   the caller, from the demonstration), so the learner cannot measure it
``no_contact``     the rope never touched itself (``first_contact_time`` None)
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
by :func:`flyknot.knot.classify_centreline`. That classifier votes over ray closures in
31 directions rather than closing the rope "held end up, free end down", which is the closure
that invents knots while the free end is above the held end (``flyknot/knot.py``); so
frames are judged whatever the height of the free end and none is dropped. Without truth, the
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

The end verdict is ``record.knot``; when it is None (not judged) the last finite truth frame
is judged instead. ``metadata["settle"]`` (``settled``, ``contact_free``, ``settle_s`` or
``settle_time_s``, ``free_end_speed_m_s``), when present, adds a note to the reason of a rope
judged before it was at rest.

Directories (:func:`explain_directory`): a run directory of ``flyknot run`` (every trial record
``<stem>.json`` + ``<stem>.npz`` under it, recursively; t_c from each run's ``result.json`` or
the run directory's ``summary.json``) or a directory of ``flyknot demo replay --out``
(``replay_*.npz``; t_c from the replayed demonstration named in each file's metadata, if it is
found).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import N_MARKERS, REPO_ROOT
from flyknot.errors import (
    ConfigError,
    FlyknotError,
    RecordError,
    check_choice,
    check_int,
    check_nonnegative,
    check_positive,
)
from flyknot.record import TrialRecord

# --- labels ----------------------------------------------------------------------------------
SUCCESS = "success"
FAULTED = "faulted"
MARKERS_LOST = "markers_lost"
NO_CONTACT = "no_contact"
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
    NOT_THROUGH,
    SLIPPED_OUT,
    SHAKEN_LOOSE,
    OTHER_KNOT,
    UNKNOWN,
)
"""Every label, in order of precedence."""

DESCRIPTIONS = {
    SUCCESS: "trefoil at the end, no fault",
    FAULTED: "the controller aborted the trial",
    MARKERS_LOST: "mocap lost the rope at or before t_c",
    NO_CONTACT: "the rope never touched itself",
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

TREFOIL = "trefoil"
UNKNOT = "unknot"

_TIME_TOL = 1e-9  # [s] float rounding of sample times


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
class TrialEvidence:
    """What :func:`diagnose` reads from one trial (a :class:`TrialRecord` or a replay file).

    Attributes:
        name: Name of the trial in tables (a relative path).
        fault: The controller's fault, or None.
        knot: Knot verdict at the end, or None if not judged.
        first_contact_time: First self-contact [s], or None.
        contact_known: Whether None in ``first_contact_time`` means "no contact" (simulated
            lab) rather than "not annotated" (real lab).
        t_marker: Marker times, shape (m,) [s].
        markers: Markers, shape (m, 11, 3) [m], NaN where tracking is lost.
        t_truth: Times of the truth centreline, shape (k,) [s], or None (no truth).
        centreline: Truth centreline, shape (k, n, 3) [m], or None.
        metadata: The record's metadata (``rope``, ``settle``, ``knot_history``, ...).
    """

    name: str
    fault: str | None
    knot: str | None
    first_contact_time: float | None
    contact_known: bool
    t_marker: np.ndarray
    markers: np.ndarray
    t_truth: np.ndarray | None = None
    centreline: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t_marker = np.asarray(self.t_marker, dtype=float)
        markers = np.asarray(self.markers, dtype=float)
        if t_marker.ndim != 1 or markers.shape != (len(t_marker), N_MARKERS, 3):
            raise RecordError(
                f"{self.name}: markers must have shape (m, {N_MARKERS}, 3) with m = "
                f"len(t_marker) = {len(t_marker)}, got {markers.shape}"
            )
        object.__setattr__(self, "t_marker", t_marker)
        object.__setattr__(self, "markers", markers)
        if (self.t_truth is None) != (self.centreline is None):
            raise RecordError(f"{self.name}: truth needs both t_truth and centreline")
        if self.t_truth is not None:
            t_truth = np.asarray(self.t_truth, dtype=float)
            centreline = np.asarray(self.centreline, dtype=float)
            if t_truth.ndim != 1 or centreline.ndim != 3 or centreline.shape[0] != len(t_truth):
                raise RecordError(
                    f"{self.name}: truth centreline must have shape (k, n, 3) with k = "
                    f"len(t_truth) = {len(t_truth)}, got {centreline.shape}"
                )
            object.__setattr__(self, "t_truth", t_truth)
            object.__setattr__(self, "centreline", centreline)
        object.__setattr__(self, "metadata", dict(self.metadata))

    @property
    def has_truth(self) -> bool:
        """Whether the truth centreline is present."""
        return self.t_truth is not None and len(self.t_truth) > 0

    @classmethod
    def from_record(cls, record: TrialRecord, name: str = "trial") -> TrialEvidence:
        """The evidence of a :class:`TrialRecord` (its truth, if loaded, included)."""
        truth = record.truth
        has_truth = "centreline" in truth and "t_truth" in truth
        return cls(
            name=name,
            fault=record.fault,
            knot=record.knot,
            first_contact_time=record.first_contact_time,
            contact_known=(
                record.first_contact_time is not None
                or has_truth
                or record.metadata.get("cell") == "sim"
            ),
            t_marker=record.t_marker,
            markers=record.markers,
            t_truth=truth["t_truth"] if has_truth else None,
            centreline=truth["centreline"] if has_truth else None,
            metadata=record.metadata,
        )


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
    from flyknot.knot import classify_centreline

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
        verdicts.append(classify_centreline(frames[k], n_directions=n_directions))
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
    why = "unknotted and free of self-contact" if settle.get("contact_free") else "not at rest"
    return f"; judged {why}" + (f" ({', '.join(parts)})" if parts else "")


def _end_verdict(ev: TrialEvidence, n_directions: int) -> str | None:
    if ev.knot is not None:
        return ev.knot
    if ev.fault is None and ev.has_truth:
        from flyknot.knot import classify_centreline

        for frame in ev.centreline[::-1]:
            if np.all(np.isfinite(frame)):
                return classify_centreline(frame, n_directions=n_directions)
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
    ev: TrialEvidence, end: str | None, params: AnatomyParams
) -> tuple[str, str, KnotHistory | None]:
    """(label, reason, history) from the outcome alone (no fault, not a success)."""
    if end is not None and end not in (UNKNOT, TREFOIL):
        return OTHER_KNOT, f"knot {end!r} at the end", None
    contact = ev.first_contact_time
    if contact is None and ev.contact_known:
        return NO_CONTACT, "no self-contact", None
    if end is None:
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
    end = _end_verdict(ev, params.n_directions)
    lost_at = tracking_lost_time(ev.t_marker, ev.markers, params.min_loss_s)
    common = dict(
        name=name or ev.name,
        knot=end,
        first_contact_time=ev.first_contact_time,
        tracking_lost_time=lost_at,
        t_c=t_c,
        group=group,
    )
    if ev.fault is None and end == TREFOIL:
        return Diagnosis(label=SUCCESS, outcome=SUCCESS, reason="trefoil at the end", **common)
    if ev.fault is not None:
        return Diagnosis(label=FAULTED, outcome=FAULTED, reason=f"fault: {ev.fault}", **common)
    label, reason, hist = _outcome(ev, end, params)
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


# --- files and directories -------------------------------------------------------------------


@dataclass(frozen=True)
class TrialFile:
    """One trial found under a directory.

    Attributes:
        path: The record's ``.json`` or the replay's ``.npz``.
        kind: ``"record"`` or ``"replay"``.
        name: Path of the trial relative to the directory, without the suffix.
        group: Its run (the record's directory relative to the directory, ``runs/`` and
            ``/learning`` dropped) or ``""`` for trials directly in the directory.
        t_c: Critical time [s] of the run or the replayed demonstration, or None.
    """

    path: Path
    kind: str
    name: str
    group: str
    t_c: float | None


def load_replay(path: str | Path) -> TrialEvidence:
    """Read a replay file of ``flyknot demo replay --out`` (format: ``assets/demos/README.md``).

    Args:
        path: A ``replay_*.npz`` file.

    Returns:
        The evidence: no fault, knot = the replay's ``outcome``, first contact = its ``t_c``,
        markers, truth centreline if the file has one, and ``metadata`` = the file's
        ``meta.metadata`` plus ``rope``.

    Raises:
        RecordError: Missing file or arrays, or unreadable ``meta``.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"replay file {str(path)!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("t", "markers", "meta") if k not in z.files]
            if missing:
                raise RecordError(f"replay file {str(path)!r} lacks arrays: {', '.join(missing)}")
            meta = json.loads(str(z["meta"]))
            has_truth = "t_truth" in z.files and "centreline" in z.files
            t, markers = z["t"], z["markers"]
            t_truth = z["t_truth"] if has_truth else None
            centreline = z["centreline"] if has_truth else None
    except (OSError, ValueError) as exc:  # not an npz, or bad JSON (JSONDecodeError)
        raise RecordError(f"replay file {str(path)!r} is not readable: {exc}") from exc
    if not isinstance(meta, dict):
        raise RecordError(f"replay file {str(path)!r}: meta must be a JSON object")
    inner = dict(meta.get("metadata") or {})
    inner.setdefault("rope", meta.get("rope"))
    return TrialEvidence(
        name=path.stem,
        fault=None,
        knot=inner.get("outcome"),
        first_contact_time=meta.get("t_c"),
        contact_known=True,
        t_marker=t,
        markers=markers,
        t_truth=t_truth,
        centreline=centreline,
        metadata=inner,
    )


def _check_directory(directory: str | Path) -> Path:
    directory = Path(directory)
    if not directory.exists():
        raise ConfigError("directory", f"{str(directory)!r} does not exist")
    if not directory.is_dir():
        raise ConfigError("directory", f"{str(directory)!r} is not a directory")
    return directory


def _group_of(rel_dir: Path) -> str:
    parts = list(rel_dir.parts)
    if parts and parts[0] == "runs":
        parts = parts[1:]
    if parts and parts[-1] == "learning":
        parts = parts[:-1]
    return "/".join(parts)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _run_t_c(record_dir: Path, root: Path) -> float | None:
    """t_c of the run a record belongs to: the nearest ``result.json`` up to ``root`` (or one
    level above a ``root`` named ``learning`` or ``repeats``, a run's own folders), else the
    run's entry in ``root/summary.json``."""
    top = root.parent if root.name in ("learning", "repeats") else root
    run_name = None
    for d in (record_dir, *record_dir.parents):
        res = _read_json(d / "result.json") if (d / "result.json").is_file() else None
        if isinstance(res, dict) and isinstance(res.get("t_c"), (int, float)):
            return float(res["t_c"])
        if d.parent.name == "runs":
            run_name = d.name
        if d == top:
            break
    summary = _read_json(root / "summary.json") if (root / "summary.json").is_file() else None
    if isinstance(summary, dict) and run_name is not None:
        for run in summary.get("runs") or []:
            if isinstance(run, dict) and run.get("name") == run_name:
                tc = run.get("t_c")
                return float(tc) if isinstance(tc, (int, float)) else None
    return None


def _demo_t_c(source: str | None, cache: dict[str, float | None]) -> float | None:
    """t_c of a replayed demonstration, found at ``source`` (as given, or in the repository)."""
    if not source:
        return None
    if source not in cache:
        from flyknot.demo import Demonstration

        cache[source] = None
        for p in (Path(source), REPO_ROOT / source):
            if p.is_file():
                with contextlib.suppress(FlyknotError):
                    cache[source] = Demonstration.load(p).t_c
                break
    return cache[source]


def _replay_source(path: Path) -> str | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
    except (OSError, ValueError):
        return None  # load_replay reports it
    source = (meta.get("metadata") or {}).get("source") if isinstance(meta, dict) else None
    return source if isinstance(source, str) else None


def find_trials(directory: str | Path) -> tuple[TrialFile, ...]:
    """Every trial record and replay file under ``directory`` (recursively), sorted by path.

    A trial record is a ``<stem>.json`` with a ``<stem>.npz`` beside it; a replay is a
    ``replay_*.npz`` without a ``.json`` beside it.

    Args:
        directory: A run directory, a replay directory, or any directory holding either.

    Returns:
        The trials found (possibly none).

    Raises:
        ConfigError: ``directory`` does not exist or is not a directory.
    """
    root = _check_directory(directory)
    found: list[TrialFile] = []
    demo_t_c: dict[str, float | None] = {}
    run_t_c: dict[Path, float | None] = {}
    for path in sorted(root.rglob("*.json")):
        npz = path.with_suffix(".npz")
        if not npz.is_file():
            continue
        if path.parent not in run_t_c:
            run_t_c[path.parent] = _run_t_c(path.parent, root)
        rel = path.relative_to(root)
        found.append(
            TrialFile(
                path,
                "record",
                str(rel.with_suffix("")),
                _group_of(rel.parent),
                run_t_c[path.parent],
            )
        )
    for path in sorted(root.rglob("replay_*.npz")):
        if path.with_suffix(".json").is_file():
            continue
        rel = path.relative_to(root)
        t_c = _demo_t_c(_replay_source(path), demo_t_c)
        found.append(
            TrialFile(path, "replay", str(rel.with_suffix("")), _group_of(rel.parent), t_c)
        )
    return tuple(sorted(found, key=lambda f: str(f.path)))


def _load_evidence(f: TrialFile) -> TrialEvidence:
    if f.kind == "replay":
        return replace(load_replay(f.path), name=f.name)
    try:
        record = TrialRecord.load(f.path, with_truth=True)
    except (OSError, ValueError, KeyError, TypeError) as exc:  # partial or foreign JSON
        raise RecordError(f"trial record {str(f.path)!r} is not readable: {exc}") from exc
    return TrialEvidence.from_record(record, f.name)


@dataclass(frozen=True)
class Anatomy:
    """The diagnoses of every trial of a directory (or any set of trials).

    Attributes:
        source: What was explained (a directory path, or free text).
        diagnoses: One per trial, in file order.
        t_c_sources: How t_c was found, one line per distinct source (for the table).
    """

    source: str
    diagnoses: tuple[Diagnosis, ...]
    t_c_sources: tuple[str, ...] = ()

    def groups(self) -> tuple[str, ...]:
        """Distinct groups, in order of first appearance."""
        return tuple(dict.fromkeys(d.group for d in self.diagnoses))

    def counts(self, group: str | None = None) -> dict[str, int]:
        """Trials per label (every label, in :data:`LABELS` order), of one group or all.

        Raises:
            ConfigError: ``group`` is not one of :meth:`groups`.
        """
        if group is not None:
            check_choice("group", group, self.groups())
        out = dict.fromkeys(LABELS, 0)
        for d in self.diagnoses:
            if group is None or d.group == group:
                out[d.label] += 1
        return out

    def as_dict(self) -> dict[str, Any]:
        """Plain data (JSON-ready): counts overall and per group, and every diagnosis."""
        return {
            "source": self.source,
            "t_c_sources": list(self.t_c_sources),
            "counts": self.counts(),
            "groups": {g: self.counts(g) for g in self.groups()},
            "trials": [d.as_dict() for d in self.diagnoses],
        }


def explain(
    trials: Iterable[TrialRecord | TrialEvidence],
    *,
    t_c: float | None = None,
    params: AnatomyParams | None = None,
    source: str = "trials",
) -> Anatomy:
    """Diagnose a set of trials in memory (all checked against one ``t_c``).

    Args:
        trials: Records (with truth for the full anatomy) or evidence.
        t_c: Critical time [s], or None (no ``markers_lost`` check).
        params: Thresholds.
        source: Name of the set in tables.

    Returns:
        The :class:`Anatomy`; trial names are ``trial_000``, ... unless evidence names them.
    """
    out = []
    for i, trial in enumerate(trials):
        name = trial.name if isinstance(trial, TrialEvidence) else f"trial_{i:03d}"
        out.append(diagnose(trial, t_c=t_c, params=params, name=name))
    return Anatomy(source, tuple(out))


def explain_directory(
    directory: str | Path,
    *,
    t_c: float | None = None,
    params: AnatomyParams | None = None,
    progress: Callable[[Iterable[TrialFile]], Iterable[TrialFile]] | None = None,
) -> Anatomy:
    """Diagnose every trial under a run or replay directory (:func:`find_trials`).

    Groups: the run of each record (``rope1``, ``rope1/repeats``, ...); trials directly in
    ``directory`` are grouped by rope (``rope 1``).

    Args:
        directory: The directory.
        t_c: Critical time [s] for every trial; None: each run's ``t_c`` (``result.json`` or
            ``summary.json``) or each replay's demonstration t_c, where found.
        params: Thresholds.
        progress: Optional wrapper of the file iteration (e.g. ``tqdm``).

    Returns:
        The :class:`Anatomy`.

    Raises:
        ConfigError: ``directory`` does not exist, is not a directory, or holds no trials;
            ``t_c`` is not a finite number >= 0.
        RecordError: A trial file under it is malformed (the message names the file).
    """
    if t_c is not None:
        check_nonnegative("t_c", t_c)
    files = find_trials(directory)
    if not files:
        raise ConfigError(
            "directory",
            f"{str(directory)!r} holds no trial records (<stem>.json with <stem>.npz) "
            "and no replay files (replay_*.npz)",
        )
    diagnoses = []
    for f in progress(files) if progress is not None else files:
        ev = _load_evidence(f)
        group = f.group
        if not group:
            rope = ev.metadata.get("rope")
            group = f"rope {rope}" if rope is not None else Path(directory).name
        diagnoses.append(
            diagnose(ev, t_c=f.t_c if t_c is None else t_c, params=params, group=group)
        )
    if t_c is not None:
        sources = (f"t_c {t_c:.3f} s (given)",)
    else:
        per_group: dict[str, set[float | None]] = {}
        for f, d in zip(files, diagnoses, strict=True):
            per_group.setdefault(d.group, set()).add(f.t_c)
        sources = tuple(
            f"{g}: "
            + ", ".join("none found" if v is None else f"{v:.3f} s" for v in _sorted_t_c(vals))
            for g, vals in per_group.items()
        )
    return Anatomy(str(directory), tuple(diagnoses), sources)


def _sorted_t_c(values: Iterable[float | None]) -> list[float | None]:
    """Values sorted with None last (for listing the t_c of a group)."""
    vals = list(values)
    return sorted(v for v in vals if v is not None) + [None] * sum(v is None for v in vals)


# --- output ----------------------------------------------------------------------------------


def _share(k: int, n: int) -> str:
    return f"{100.0 * k / n:.0f} %" if n else "-"


def _used_labels(anatomy: Anatomy) -> list[str]:
    total = anatomy.counts()
    return [lab for lab in LABELS if total[lab]]


def format_table(anatomy: Anatomy, *, trials: bool = False) -> str:
    """Plain-text table: label -> count and share, per group when there are several.

    Args:
        anatomy: What to print.
        trials: Also list every trial with its label and reason.

    Returns:
        The text (no trailing newline).
    """
    total = anatomy.counts()
    n = len(anatomy.diagnoses)
    lines = [f"failure anatomy of {anatomy.source}: {n} trial{'s' if n != 1 else ''}"]
    lines += [f"  t_c: {s}" for s in anatomy.t_c_sources]
    lines.append("")
    width = max(len(lab) for lab in LABELS)
    lines.append(f"{'class':<{width}}  {'meaning':<42}  {'count':>5}  {'share':>5}")
    for lab in LABELS:
        if total[lab]:
            lines.append(
                f"{lab:<{width}}  {DESCRIPTIONS[lab]:<42}  {total[lab]:>5}  "
                f"{_share(total[lab], n):>5}"
            )
    lines.append(f"{'total':<{width}}  {'':<42}  {n:>5}  {_share(n, n):>5}")
    lost = [d for d in anatomy.diagnoses if d.label == MARKERS_LOST]
    if lost:
        then = {}
        for d in lost:
            then[d.outcome] = then.get(d.outcome, 0) + 1
        lines.append(
            f"  {MARKERS_LOST}, by outcome: "
            + ", ".join(f"{lab} {then[lab]}" for lab in LABELS if lab in then)
        )
    groups = anatomy.groups()
    if len(groups) > 1:
        used = _used_labels(anatomy)
        gw = max(len("group"), *(len(g) for g in groups))
        cw = [max(len(lab), 8) for lab in used]
        lines += ["", "per group (count, share):"]
        lines.append(
            f"{'group':<{gw}}  {'n':>4}  "
            + "  ".join(f"{lab:>{w}}" for lab, w in zip(used, cw, strict=True))
        )
        for g in groups:
            c = anatomy.counts(g)
            m = sum(c.values())
            cells = [f"{c[lab]} {_share(c[lab], m)}" if c[lab] else "-" for lab in used]
            lines.append(
                f"{g:<{gw}}  {m:>4}  "
                + "  ".join(f"{x:>{w}}" for x, w in zip(cells, cw, strict=True))
            )
    if trials:
        nw = max(len(d.name) for d in anatomy.diagnoses)
        lines += ["", "trials:"]
        lines += [f"{d.name:<{nw}}  {d.label:<{width}}  {d.reason}" for d in anatomy.diagnoses]
    return "\n".join(lines)


def plot_anatomy(anatomy: Anatomy, path: str | Path, title: str | None = None) -> Path:
    """Stacked bar chart of the labels' shares: one bar per group (and "all" if several).

    Args:
        anatomy: What to draw.
        path: PNG to write (its directory is created).
        title: Figure title (default: the anatomy's source).

    Returns:
        ``path``.

    Raises:
        ConfigError: The anatomy holds no trials.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not anatomy.diagnoses:
        raise ConfigError("anatomy", "holds no trials to plot")
    groups = list(anatomy.groups())
    bars = [(g, anatomy.counts(g)) for g in groups]
    if len(groups) > 1:
        bars.append(("all", anatomy.counts()))
    used = _used_labels(anatomy)
    fig, ax = plt.subplots(figsize=(0.9 * len(bars) + 5.0, 4.2), constrained_layout=True)
    x = np.arange(len(bars))
    bottom = np.zeros(len(bars))
    for lab in used:
        k = np.array([c[lab] for _, c in bars], dtype=float)
        n = np.array([sum(c.values()) for _, c in bars], dtype=float)
        share = k / n
        ax.bar(
            x,
            share,
            0.7,
            bottom=bottom,
            color=COLOURS[lab],
            edgecolor="k",
            linewidth=0.5,
            label=f"{lab}: {DESCRIPTIONS[lab]}",
        )
        r, g, b_ = matplotlib.colors.to_rgb(COLOURS[lab])
        ink = "w" if 0.299 * r + 0.587 * g + 0.114 * b_ < 0.45 else "k"
        for xi, b, s, ki in zip(x, bottom, share, k, strict=True):
            if s >= 0.06:
                ax.text(
                    xi, b + s / 2, f"{int(ki)}", ha="center", va="center", fontsize=7, color=ink
                )
        bottom += share
    for xi, (_, c) in zip(x, bars, strict=True):
        ax.text(xi, 1.01, f"n={sum(c.values())}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [g for g, _ in bars], rotation=30 if len(bars) > 4 else 0, ha="right")
    ax.set(
        xlim=(-0.75, len(bars) - 0.25),
        ylim=(0, 1.08),
        ylabel="share of trials",
        title=title or f"failure anatomy: {anatomy.source}",
    )
    handles, labels = ax.get_legend_handles_labels()  # top of the stack first
    ax.legend(
        handles[::-1],
        labels[::-1],
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        frameon=False,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def markdown_section(anatomy: Anatomy, figure: str | None = None) -> list[str]:
    """Lines of a report section: label table, per-group table if several, the figure.

    Args:
        anatomy: What to report.
        figure: File name of the figure to link (relative to the report), or None.

    Returns:
        Markdown lines, starting with the section heading.
    """
    total = anatomy.counts()
    n = len(anatomy.diagnoses)
    lines = ["## Failure anatomy", ""]
    lines.append(
        f"Why each of the {n} trials ended as it did (`flyknot_app.anatomy`; a trefoil lasting "
        f"{PERSIST_S:g} s or more was tied, a shorter one slipped out)."
    )
    lines += ["", "| class | meaning | count | share |", "|---|---|---|---|"]
    for lab in LABELS:
        if total[lab]:
            lines.append(
                f"| {lab} | {DESCRIPTIONS[lab]} | {total[lab]} | {_share(total[lab], n)} |"
            )
    groups = anatomy.groups()
    if len(groups) > 1:
        used = _used_labels(anatomy)
        lines += [
            "",
            "| run | n | " + " | ".join(used) + " |",
            "|---|---" + "|---" * len(used) + "|",
        ]
        for g in groups:
            c = anatomy.counts(g)
            lines.append(
                f"| {g} | {sum(c.values())} | " + " | ".join(str(c[lab]) for lab in used) + " |"
            )
    if anatomy.t_c_sources:
        lines += ["", "t_c: " + "; ".join(anatomy.t_c_sources) + "."]
    if figure is not None:
        lines += ["", f"![anatomy]({figure})"]
    return [*lines, ""]


def report_section(run_dir: str | Path, figure_name: str = "anatomy.png") -> list[str]:
    """The anatomy section of a run directory's ``report.md`` (writes its figure there).

    Never raises for a directory without trials or with a malformed record: the section then
    says so.

    Args:
        run_dir: The run directory.
        figure_name: File name of the figure inside ``run_dir``.

    Returns:
        Markdown lines.
    """
    run_dir = Path(run_dir)
    try:
        anatomy = explain_directory(run_dir)
    except FlyknotError as exc:
        return ["## Failure anatomy", "", f"Not available: {exc}", ""]
    plot_anatomy(anatomy, run_dir / figure_name, title=f"failure anatomy: {run_dir.name}")
    return markdown_section(anatomy, figure_name)

"""Reading trials for the failure anatomy (:mod:`flyknot_app.anatomy.diagnosis`): records,
replays, dirs.

:class:`TrialEvidence` is what :func:`flyknot_app.anatomy.diagnosis.diagnose` reads from one
trial, taken from a :class:`TrialRecord` (:meth:`TrialEvidence.from_record`) or a replay file
(:func:`load_replay`).

Directories (:func:`find_trials`, for :func:`flyknot_app.anatomy.report.explain_directory`):
a run directory of ``flyknot run`` (every trial record ``<stem>.json`` + ``<stem>.npz`` under
it, recursively; t_c from each run's ``result.json`` or the run directory's ``summary.json``) or
a directory of ``flyknot demo replay --out`` (``replay_*.npz``; t_c from the replayed
demonstration named in each file's metadata, if it is found).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import N_MARKERS, REPO_ROOT
from flyknot.errors import ConfigError, FlyknotError, RecordError
from flyknot.judge import ROPE_DIAMETER_KEY, with_rope_diameter
from flyknot.record import TrialRecord
from flyknot.verdict import JudgeParams, Verdict


@dataclass(frozen=True)
class TrialEvidence:
    """What :func:`flyknot_app.anatomy.diagnosis.diagnose` reads from one trial (a record or a
    replay).

    Attributes:
        name: Name of the trial in tables (a relative path).
        fault: The controller's fault, or None.
        knot: Knot type at the end, or None if not judged.
        verdict: The judged end (:class:`flyknot.verdict.Verdict`), or None (not judged, or
            judged before verdicts carried their evidence:
            :func:`flyknot_app.anatomy.diagnosis.diagnose` then judges the truth's last frame).
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
    verdict: Verdict | None = None

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
            verdict=record.verdict,
        )


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
    verdict = Verdict.from_json(inner["verdict"]) if inner.get("verdict") else None
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
        verdict=verdict,
    )


def judge_params_of(metadata: Mapping[str, Any], params: JudgeParams | None = None) -> JudgeParams:
    """``params`` with the record's rope radius (:func:`flyknot.judge.judge_params_for`)."""
    diameter = rope_diameter_of(metadata)
    if diameter is None:
        return JudgeParams() if params is None else params
    return with_rope_diameter(diameter, params)


def rope_diameter_of(metadata: Mapping[str, Any]) -> float | None:
    """A record's rope diameter [m]: its ``rope_diameter_m``; for a record written before
    records carried it, a custom rope's stored parameters, else the paper's rope of its id or
    name; None when unknown (a custom rope's name without its file)."""
    for value in (
        metadata.get(ROPE_DIAMETER_KEY),
        (metadata.get("rope_params") or {}).get("diameter"),
    ):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    if metadata.get("rope") is None:
        return None
    from flyknot_sim.rope_custom import resolve_rope

    try:
        return resolve_rope(metadata["rope"]).diameter
    except ConfigError:
        return None


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
        from flyknot.demo_formats import read_demonstration

        cache[source] = None
        for p in (Path(source), REPO_ROOT / source):
            if p.is_file():
                with contextlib.suppress(FlyknotError):
                    cache[source] = read_demonstration(p).t_c
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


def require_trials(directory: str | Path) -> tuple[TrialFile, ...]:
    """:func:`find_trials`, refusing a directory that holds none.

    Raises:
        ConfigError: ``directory`` is missing, not a directory, or holds no trials.
    """
    files = find_trials(directory)
    if not files:
        raise ConfigError(
            "directory",
            f"{str(directory)!r} holds no trial records (<stem>.json with <stem>.npz) "
            "and no replay files (replay_*.npz)",
        )
    return files


def load_evidence(f: TrialFile) -> TrialEvidence:
    """The evidence of a trial found by :func:`find_trials` (named by its path).

    Raises:
        RecordError: The file is malformed (the message names it).
    """
    if f.kind == "replay":
        return replace(load_replay(f.path), name=f.name)
    return TrialEvidence.from_record(load_record(f.path), f.name)


def load_record(path: Path) -> TrialRecord:
    """A trial record with its truth; a malformed one raises :class:`RecordError` naming it."""
    try:
        return TrialRecord.load(path, with_truth=True)
    except (OSError, ValueError, KeyError, TypeError) as exc:  # partial or foreign JSON
        raise RecordError(f"trial record {str(path)!r} is not readable: {exc}") from exc

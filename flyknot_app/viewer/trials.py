"""What ``flyknot view`` shows: the trials of a record or a run directory, and their targets.

A path is one trial record (``<stem>.json`` with ``<stem>.npz``) or a directory; a directory's
trials are those :func:`flyknot_app.anatomy.trials.find_trials` finds (every record under it,
with its run's critical time t_c from ``result.json`` or ``summary.json``).

The demonstration's rope at t_c is the learner's own target: the run's ``result.json`` names
the demonstration, its timing window and the model step, and
:func:`flyknot_app.runner.prepare_target` rebuilds the :class:`learner.target.DemoTarget`
the run learned against. Its 11 marker positions (demonstration frame) are placed in the lab
by the trial's command base offset (``knots_<k>.npy`` beside a learning trial,
``final_knots.npy`` for a repeat) and the record's base pose, the inverse of
:func:`learner.critical_state.to_demo_frame`.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import N_MARKERS
from flyknot.errors import ConfigError, FlyknotError
from flyknot.geometry import quat_to_matrix
from flyknot.record import TrialRecord
from flyknot_app.anatomy.trials import find_trials

_LEARNING_STEM = re.compile(r"trial_(\d+)_a\d+")


@dataclass(frozen=True)
class ViewTrial:
    """One trial the viewer can show.

    Attributes:
        name: Its label: the path relative to the directory given, without the suffix.
        path: The record's ``.json`` file.
        t_c: Critical time of its run [s] (command clock), or None outside a run.
    """

    name: str
    path: Path
    t_c: float | None


def _record_json(path: Path) -> Path:
    """The ``.json`` of a record given as its stem, ``.json``, ``.npz`` or ``.truth.npz``."""
    name = path.name
    for suffix in (".truth.npz", ".json", ".npz"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return path.with_name(name + ".json")


def _run_folder(record_json: Path) -> Path:
    """The run folder of a record: above ``learning/`` or ``repeats/``, else its own."""
    parent = record_json.parent
    return parent.parent if parent.name in ("learning", "repeats") else parent


def run_result(record_json: Path) -> dict[str, Any] | None:
    """The ``result.json`` of the run a record belongs to, or None outside a finished run."""
    path = _run_folder(record_json) / "result.json"
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return result if isinstance(result, dict) else None


def find_view_trials(path: str | Path) -> tuple[ViewTrial, ...]:
    """The trials under ``path``: a trial record or a directory (a ``flyknot run`` output).

    Raises:
        ConfigError: ``path`` does not exist, is neither a record nor a directory, or the
            directory holds no trial records.
    """
    path = Path(path)
    if path.is_dir():
        found = tuple(
            ViewTrial(f.name, f.path, f.t_c) for f in find_trials(path) if f.kind == "record"
        )
        if not found:
            raise ConfigError(
                "PATH", f"{str(path)!r} holds no trial records (<stem>.json with <stem>.npz)"
            )
        return found
    record = _record_json(path)
    if not (record.is_file() and record.with_suffix(".npz").is_file()):
        raise ConfigError(
            "PATH",
            f"{str(path)!r} is neither a run directory nor a trial record "
            "(<stem>.json with <stem>.npz)",
        )
    result = run_result(record)
    t_c = result.get("t_c") if result is not None else None
    return (ViewTrial(record.stem, record, float(t_c) if isinstance(t_c, (int, float)) else None),)


def base_offset(record_json: Path) -> np.ndarray | None:
    """The command base offset b (3,) [m] a run's trial was played with, or None if unknown.

    A learning trial ``trial_<k>_a<i>`` played ``knots_<k>.npy`` beside it; a repeat played
    the run's ``final_knots.npy``. Rows 7..9 of a (10, 8) knot array hold b.
    """
    match = _LEARNING_STEM.fullmatch(record_json.stem)
    if match is not None:
        knots = record_json.parent / f"knots_{int(match.group(1)):04d}.npy"
    elif record_json.parent.name == "repeats":
        knots = record_json.parent.parent / "final_knots.npy"
    else:
        return None
    try:
        k = np.load(knots, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if k.ndim != 2 or k.shape[0] < 10:
        return None
    return np.asarray(k[7:10, 0], dtype=float)


def demo_to_lab(p_demo: np.ndarray, base_pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Demonstration-frame points (..., 3) in the lab frame: R_b (p - b) + t_b.

    The inverse of :func:`learner.critical_state.to_demo_frame` for positions.
    """
    R_b = quat_to_matrix(np.asarray(base_pose[3:], dtype=float))
    return (np.asarray(p_demo, dtype=float) - offset) @ R_b.T + np.asarray(base_pose[:3])


class TargetCache:
    """The demonstration's rope at t_c per run setting, computed once each."""

    def __init__(self) -> None:
        self._demo: dict[tuple[str, float, float, float], np.ndarray | None] = {}

    def demo_markers(self, result: dict[str, Any]) -> np.ndarray | None:
        """The run's target marker positions at t_c, (11, 3) [m], demonstration frame.

        None when the run's summary lacks the fields or its demonstration is not found.
        """
        try:
            key = (
                str(result["demo"]),
                float(result["rope_model"]["dt"]),
                float(result["follow_through_s"]),
                float(result["path_frac"]),
            )
        except (KeyError, TypeError, ValueError):
            return None
        if key not in self._demo:
            from flyknot_app.runner import prepare_target

            try:
                _, target = prepare_target(key[0], key[1], (key[2], key[3]))
                self._demo[key] = target.x_c[: 3 * N_MARKERS].reshape(N_MARKERS, 3)
            except FlyknotError:
                self._demo[key] = None
        return self._demo[key]

    def target_in_lab(self, trial: ViewTrial, record: TrialRecord) -> np.ndarray | None:
        """The demonstration's markers at t_c where this trial's lab put them, (11, 3) [m].

        None outside a finished run or when the command's base offset is unknown.
        """
        result = run_result(trial.path)
        offset = base_offset(trial.path)
        if result is None or offset is None:
            return None
        demo = self.demo_markers(result)
        return None if demo is None else demo_to_lab(demo, record.base_pose, offset)


def markers_at(record: TrialRecord, t: float) -> np.ndarray:
    """The measured markers (finite ones only, (n, 3) [m]) at the marker sample nearest ``t``."""
    i = int(np.argmin(np.abs(record.t_marker - t)))
    m = record.markers[i]
    return m[np.all(np.isfinite(m), axis=1)]


__all__ = [
    "TargetCache",
    "ViewTrial",
    "base_offset",
    "demo_to_lab",
    "find_view_trials",
    "markers_at",
    "run_result",
]

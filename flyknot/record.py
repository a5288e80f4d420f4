"""The seam between a cell (simulated or real lab) and the learner.

A cell runs a :class:`JointCommand` and returns a :class:`TrialRecord`: plain data that
holds only what the real lab measures. Simulator ground truth travels in the separate
``truth`` mapping, which the learner never reads.

On disk a record is ``<stem>.npz`` (arrays) plus ``<stem>.json`` (scalars and metadata);
ground truth, if any, is ``<stem>.truth.npz``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_MARKERS
from flyknot.errors import CommandError, RecordError
from flyknot.geometry import readonly
from flyknot.verdict import Verdict

RECORD_FORMAT_VERSION = 1


@dataclass(frozen=True)
class JointCommand:
    """Joint position targets played at a fixed rate.

    Attributes:
        q: Targets, shape (n, 7) [rad]; row i is played at time i / rate_hz [s].
        rate_hz: Playback rate [Hz]; the xArm streams at 250 Hz.
    """

    q: np.ndarray
    rate_hz: float = COMMAND_RATE_HZ

    def __post_init__(self) -> None:
        q = np.asarray(self.q)
        if q.ndim != 2 or q.shape[1] != N_JOINTS:
            raise CommandError(f"command q must have shape (n, {N_JOINTS}), got {q.shape}")
        if q.shape[0] < 2:
            raise CommandError(f"command q needs at least 2 samples, got {q.shape[0]}")
        if not np.issubdtype(q.dtype, np.number):
            raise CommandError(f"command q must be numeric, got dtype {q.dtype}")
        bad = ~np.isfinite(q.astype(float))
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise CommandError(
                f"command q has {int(bad.sum())} non-finite value(s); first at sample {i}, "
                f"joint {j + 1}"
            )
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise CommandError(f"command rate_hz must be > 0, got {self.rate_hz}")
        object.__setattr__(self, "q", readonly(q))

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.q.shape[0])

    @property
    def dt(self) -> float:
        """Sample period [s]."""
        return 1.0 / self.rate_hz

    @property
    def duration(self) -> float:
        """Time of the last sample [s]."""
        return (self.n - 1) * self.dt

    @property
    def times(self) -> np.ndarray:
        """Sample times, shape (n,) [s]."""
        return np.arange(self.n) * self.dt

    # --- files ---------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write the command as CSV (``t,q1..q7``, radians) or NPY ((n, 7) array)."""
        path = Path(path)
        if path.suffix == ".npy":
            np.save(path, np.asarray(self.q))
        else:
            header = "t," + ",".join(f"q{i}" for i in range(1, N_JOINTS + 1))
            data = np.column_stack([self.times, self.q])
            np.savetxt(path, data, delimiter=",", header=header, comments="", fmt="%.10g")

    @classmethod
    def load(cls, path: str | Path) -> JointCommand:
        """Read a command file.

        Formats (README, "Command files"):
          * ``.npy``: an (n, 7) float array [rad], played at 250 Hz.
          * ``.csv``: a header line ``t,q1,...,q7`` then one row per sample; ``t`` [s] must
            start at 0 and be uniformly spaced (its spacing sets the rate).
        """
        path = Path(path)
        if not path.is_file():
            raise CommandError(f"command file {str(path)!r} does not exist")
        if path.suffix == ".npy":
            try:
                q = np.load(path, allow_pickle=False)
            except Exception as e:
                raise CommandError(f"command file {str(path)!r} is not a valid .npy: {e}") from e
            return cls(q)
        if path.suffix != ".csv":
            raise CommandError(
                f"command file {str(path)!r}: unknown extension {path.suffix!r} "
                "(valid choices: .csv, .npy)"
            )
        try:
            text = path.read_text().strip().splitlines()
        except UnicodeDecodeError as e:
            raise CommandError(
                f"command file {str(path)!r} is not a text file (byte {e.start}: {e.reason})"
            ) from None
        if not text:
            raise CommandError(f"command file {str(path)!r} is empty")
        header = [h.strip() for h in text[0].split(",")]
        expected = ["t"] + [f"q{i}" for i in range(1, N_JOINTS + 1)]
        if header != expected:
            raise CommandError(
                f"command file {str(path)!r}: header must be {','.join(expected)!r}, "
                f"got {text[0]!r}"
            )
        rows = []
        for k, line in enumerate(text[1:], start=2):
            parts = line.split(",")
            if len(parts) != len(expected):
                raise CommandError(
                    f"command file {str(path)!r} line {k}: expected {len(expected)} values, "
                    f"got {len(parts)}"
                )
            try:
                rows.append([float(p) for p in parts])
            except ValueError as e:
                raise CommandError(f"command file {str(path)!r} line {k}: {e}") from e
        data = np.array(rows)
        if data.shape[0] < 2:
            raise CommandError(f"command file {str(path)!r} needs at least 2 samples")
        t = data[:, 0]
        dt = np.diff(t)
        if abs(t[0]) > 1e-9 or np.any(dt <= 0) or np.ptp(dt) > 1e-6 * max(1.0, dt.mean()):
            raise CommandError(
                f"command file {str(path)!r}: column t must start at 0 and be uniformly spaced"
            )
        return cls(data[:, 1:], rate_hz=float(1.0 / dt.mean()))


@dataclass(frozen=True)
class TrialRecord:
    """Everything one trial measured, as the real lab would measure it.

    Frames: markers, fingertip and base pose are in the motion-capture (world) frame.

    Attributes:
        t_joint: Joint sample times, shape (n,) [s], 0 at the first command sample.
        q_cmd: Commanded joints, shape (n, 7) [rad].
        q_meas: Measured joints, shape (n, 7) [rad].
        t_marker: Marker sample times, shape (m,) [s], same clock as ``t_joint``.
        markers: Rope markers, shape (m, 11, 3) [m]; marker 0 is 0.10 m from the fingertip,
            marker 10 at the free end; NaN where tracking is lost.
        fingertip_pos: Measured fingertip position, shape (n, 3) [m].
        fingertip_quat: Measured fingertip orientation (w, x, y, z), shape (n, 4).
        base_pose: Robot base in the mocap frame, (x, y, z, qw, qx, qy, qz), shape (7,).
        fault: None, or the controller's reason for aborting the trial.
        fault_time: Time of the fault [s] or None.
        first_contact_time: Time of the rope's first self-contact [s] or None (sim truth;
            the real lab leaves it None unless an operator annotates it).
        knot: "unknot", "trefoil", "other" or None if not judged (the verdict's knot type).
        verdict: The judged rope with its evidence (:class:`flyknot.verdict.Verdict`), or
            None if not judged; only its class ``knot`` is a success.
        metadata: Free-form plain data (cell, rope, seed, versions, ...).
        truth: Simulator-only ground truth (e.g. ``centreline`` (k, n_pts, 3) [m] and
            ``t_truth`` (k,) [s]); the learner must never read it.
    """

    t_joint: np.ndarray
    q_cmd: np.ndarray
    q_meas: np.ndarray
    t_marker: np.ndarray
    markers: np.ndarray
    fingertip_pos: np.ndarray
    fingertip_quat: np.ndarray
    base_pose: np.ndarray
    fault: str | None = None
    fault_time: float | None = None
    first_contact_time: float | None = None
    knot: str | None = None
    verdict: Verdict | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    truth: Mapping[str, np.ndarray] = field(default_factory=dict)

    _ARRAYS = (
        "t_joint",
        "q_cmd",
        "q_meas",
        "t_marker",
        "markers",
        "fingertip_pos",
        "fingertip_quat",
        "base_pose",
    )

    def __post_init__(self) -> None:
        for name in self._ARRAYS:
            object.__setattr__(self, name, readonly(getattr(self, name)))
        n = self.t_joint.shape[0]
        m = self.t_marker.shape[0]
        shapes = {
            "t_joint": (n,),
            "q_cmd": (n, N_JOINTS),
            "q_meas": (n, N_JOINTS),
            "t_marker": (m,),
            "markers": (m, N_MARKERS, 3),
            "fingertip_pos": (n, 3),
            "fingertip_quat": (n, 4),
            "base_pose": (7,),
        }
        for name, shape in shapes.items():
            got = getattr(self, name).shape
            if got != shape:
                raise RecordError(f"TrialRecord.{name} must have shape {shape}, got {got}")
        # Named knots beyond the trefoil are allowed (e.g. "4_1"), but not empty text.
        if self.knot is not None and (not isinstance(self.knot, str) or not self.knot):
            raise RecordError(f"TrialRecord.knot must be a knot name or None, got {self.knot!r}")
        if self.verdict is not None:
            if not isinstance(self.verdict, Verdict):
                raise RecordError(f"TrialRecord.verdict must be a Verdict, got {self.verdict!r}")
            if self.knot != self.verdict.knot:
                raise RecordError(
                    f"TrialRecord.knot {self.knot!r} differs from its verdict's "
                    f"{self.verdict.knot!r}"
                )
        truth = {k: readonly(v) for k, v in dict(self.truth).items()}
        object.__setattr__(self, "truth", truth)
        object.__setattr__(self, "metadata", json.loads(json.dumps(dict(self.metadata))))

    @property
    def succeeded(self) -> bool:
        """True when the trial ran without fault and its verdict is a knot in the hanging
        rope (class ``knot``); a record without a verdict never counts."""
        return self.fault is None and self.verdict is not None and self.verdict.success

    # --- files ---------------------------------------------------------------------
    def save(self, stem: str | Path) -> Path:
        """Write ``<stem>.npz``, ``<stem>.truth.npz`` (with truth) and, last, ``<stem>.json``.

        Every file is written to a temporary name and renamed into place, and the JSON comes
        last: a record whose ``.json`` exists is complete, whenever the writer was killed.

        Returns:
            The path of the JSON file.
        """
        stem = Path(stem)
        stem.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: getattr(self, k) for k in self._ARRAYS}
        atomic_save_npz(stem.with_name(stem.name + ".npz"), arrays)
        if self.truth:
            atomic_save_npz(stem.with_name(stem.name + ".truth.npz"), dict(self.truth))
        meta = {
            "format_version": RECORD_FORMAT_VERSION,
            "fault": self.fault,
            "fault_time": self.fault_time,
            "first_contact_time": self.first_contact_time,
            "knot": self.knot,
            "verdict": self.verdict.to_json() if self.verdict is not None else None,
            "metadata": self.metadata,
        }
        json_path = stem.with_name(stem.name + ".json")
        atomic_write_text(json_path, json.dumps(meta, indent=2, sort_keys=True))
        return json_path

    @classmethod
    def load(cls, stem: str | Path, *, with_truth: bool = False) -> TrialRecord:
        """Read a record written by :meth:`save` (``stem`` may end in .json or .npz)."""
        stem = _record_stem(stem)
        npz_path = stem.with_name(stem.name + ".npz")
        json_path = stem.with_name(stem.name + ".json")
        for p in (npz_path, json_path):
            if not p.is_file():
                raise RecordError(f"trial record file {str(p)!r} does not exist")
        meta = _read_meta(json_path)
        arrays = _read_npz(npz_path, cls._ARRAYS)
        truth: dict[str, np.ndarray] = {}
        truth_path = stem.with_name(stem.name + ".truth.npz")
        if with_truth and truth_path.is_file():
            truth = _read_npz(truth_path, ())
        return cls(
            **{k: arrays[k] for k in cls._ARRAYS},
            fault=meta["fault"],
            fault_time=meta["fault_time"],
            first_contact_time=meta["first_contact_time"],
            knot=meta["knot"],
            verdict=Verdict.from_json(meta["verdict"]) if meta.get("verdict") else None,
            metadata=meta["metadata"],
            truth=truth,
        )


class RecordOutcome(NamedTuple):
    """What a record's JSON says of its trial's end, read without its arrays
    (:func:`read_outcome`)."""

    fault: str | None
    knot: str
    verdict: Verdict | None


def read_outcome(stem: str | Path) -> RecordOutcome:
    """The fault, knot and stored verdict of the record at ``stem`` (.json, .npz or the stem)
    from its JSON alone, checked as :meth:`TrialRecord.load` checks it.

    Raises:
        RecordError: The JSON is missing, unreadable or not a record of this format.
    """
    stem = _record_stem(stem)
    json_path = stem.with_name(stem.name + ".json")
    if not json_path.is_file():
        raise RecordError(f"trial record file {str(json_path)!r} does not exist")
    meta = _read_meta(json_path)
    verdict = Verdict.from_json(meta["verdict"]) if meta.get("verdict") else None
    return RecordOutcome(meta["fault"], meta["knot"], verdict)


def _record_stem(stem: str | Path) -> Path:
    """A record's stem from its stem or one of its files."""
    stem = Path(stem)
    for suffix in (".truth.npz", ".json", ".npz"):
        if stem.name.endswith(suffix):
            return stem.with_name(stem.name[: -len(suffix)])
    return stem


def _read_meta(json_path: Path) -> dict:
    """A record's JSON, checked for its keys and format version."""
    try:
        meta = json.loads(json_path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise RecordError(f"{str(json_path)!r} is not a readable record ({e})") from e
    if not isinstance(meta, dict) or not set(meta) >= _RECORD_KEYS:
        raise RecordError(
            f"{str(json_path)!r} is not a trial record: it needs the keys "
            f"{', '.join(sorted(_RECORD_KEYS))}"
        )
    if meta.get("format_version") != RECORD_FORMAT_VERSION:
        raise RecordError(
            f"{str(json_path)!r}: format_version {meta.get('format_version')!r} is not "
            f"supported (valid choices: {RECORD_FORMAT_VERSION})"
        )
    return meta


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file renamed into place (flushed and
    synced first), so ``path`` is either absent, the previous file, or complete."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_save_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """``np.savez_compressed`` to ``path`` through a temporary file renamed into place."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_save_npy(path: Path, array: np.ndarray) -> None:
    """``np.save`` to ``path`` through a temporary file renamed into place."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        np.save(f, np.asarray(array))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


_RECORD_KEYS = frozenset(
    {"format_version", "fault", "fault_time", "first_contact_time", "knot", "metadata"}
)


def _read_npz(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file; a truncated or unreadable file or a missing array
    raises :class:`RecordError` naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in required if k not in z.files]
            if missing:
                raise RecordError(f"{str(path)!r} lacks arrays: {', '.join(missing)}")
            return {k: z[k] for k in z.files}
    except RecordError:
        raise
    except Exception as e:  # zipfile.BadZipFile, EOFError, OSError, ValueError, ...
        raise RecordError(f"{str(path)!r} is not a readable array file ({e})") from e


@runtime_checkable
class Cell(Protocol):
    """A place where a command can be tried: the simulated lab or the real lab.

    Attributes:
        base_pose: The lab's calibration: robot base in the mocap frame,
            (x, y, z, qw, qx, qy, qz); z is the base's height above the floor [m].
        trial_index: Index of the next trial (0 for a new cell); it seeds a simulated trial's
            variation, and a resumed run sets it so that its trials continue the sequence of
            the interrupted run.
    """

    base_pose: np.ndarray
    trial_index: int

    def run(self, command: JointCommand) -> TrialRecord:
        """Play ``command`` once from rest and return what was measured."""
        ...

"""A demonstration of the flying knot: the hand's pose and the rope markers over time.

On disk a demonstration is one ``.npz`` file (see :meth:`Demonstration.save`) with arrays
``t`` (k,) [s], ``hand_pos`` (k, 3) [m], ``hand_quat`` (k, 4) (w, x, y, z), ``markers``
(k, 11, 3) [m] (NaN where tracking is lost) and a JSON string ``meta`` holding ``t_c`` [s],
``rope`` (id) and free-form metadata. All positions are in the motion-capture frame, z up.
Recorded lab data in C3D or CSV is read by :mod:`flyknot.demo_formats`.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import N_MARKERS
from flyknot.errors import RecordError

DEMO_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Demonstration:
    """One demonstration, sampled uniformly (200 Hz for the mocap).

    Attributes:
        t: Sample times, shape (k,) [s].
        hand_pos: Hand (fingertip) position, shape (k, 3) [m].
        hand_quat: Hand orientation quaternion (w, x, y, z), shape (k, 4).
        markers: Rope markers, shape (k, 11, 3) [m], NaN where tracking is lost.
        t_c: Critical time, the rope's first self-contact [s] (same clock as ``t``).
        rope: Rope id the demonstration was given with.
        metadata: Plain data (variant, seed, generator, ...).
    """

    t: np.ndarray
    hand_pos: np.ndarray
    hand_quat: np.ndarray
    markers: np.ndarray
    t_c: float
    rope: int = 1
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        arrays = {}
        for name in ("t", "hand_pos", "hand_quat", "markers"):
            a = np.array(getattr(self, name), dtype=float, copy=True)
            a.setflags(write=False)
            arrays[name] = a
            object.__setattr__(self, name, a)
        k = arrays["t"].shape[0]
        want = {"t": (k,), "hand_pos": (k, 3), "hand_quat": (k, 4), "markers": (k, N_MARKERS, 3)}
        for name, shape in want.items():
            if arrays[name].shape != shape:
                raise RecordError(
                    f"Demonstration.{name} must have shape {shape}, got {arrays[name].shape}"
                )
        if k < 2 or np.any(np.diff(arrays["t"]) <= 0):
            raise RecordError("Demonstration.t must hold at least 2 increasing times")
        for name in ("t", "hand_pos", "hand_quat"):
            if not np.all(np.isfinite(arrays[name])):
                raise RecordError(f"Demonstration.{name} must be finite everywhere")
        if not (arrays["t"][0] <= self.t_c <= arrays["t"][-1]):
            raise RecordError(
                f"Demonstration.t_c = {self.t_c} lies outside the samples "
                f"[{arrays['t'][0]}, {arrays['t'][-1]}]"
            )
        object.__setattr__(self, "t_c", float(self.t_c))
        object.__setattr__(self, "rope", int(self.rope))
        object.__setattr__(self, "metadata", json.loads(json.dumps(dict(self.metadata))))

    @property
    def rate_hz(self) -> float:
        """Mean sample rate [Hz]."""
        return float((len(self.t) - 1) / (self.t[-1] - self.t[0]))

    def save(self, path: str | Path) -> None:
        """Write the demonstration to one ``.npz`` file."""
        meta = {
            "format_version": DEMO_FORMAT_VERSION,
            "t_c": self.t_c,
            "rope": self.rope,
            "metadata": self.metadata,
        }
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            t=self.t,
            hand_pos=self.hand_pos,
            hand_quat=self.hand_quat,
            markers=self.markers,
            meta=np.array(json.dumps(meta)),
        )

    @classmethod
    def load(cls, path: str | Path) -> Demonstration:
        """Read a file written by :meth:`save`.

        Raises:
            RecordError: The file is missing, is no demonstration or is damaged (the message
                names the file).
        """
        path = Path(path)
        if not path.is_file():
            raise RecordError(f"demonstration file {str(path)!r} does not exist")
        arrays, meta = _read_demo_npz(path)
        try:
            return cls(**arrays, t_c=meta["t_c"], rope=meta["rope"], metadata=meta["metadata"])
        except RecordError as e:
            raise RecordError(f"{str(path)!r}: {e}") from None


_ARRAYS = ("t", "hand_pos", "hand_quat", "markers")
_META_TYPES = {"t_c": (int, float), "rope": (int,), "metadata": (dict,)}
_READ_ERRORS = (ValueError, TypeError, OSError, EOFError, zipfile.BadZipFile, zlib.error)
"""What NumPy and zipfile raise for a damaged archive member or an array of Python objects."""


def _read_demo_npz(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The float arrays and the checked ``meta`` of a demonstration file."""
    try:
        z = np.load(path, allow_pickle=False)
    except _READ_ERRORS as e:
        raise RecordError(f"{str(path)!r} is not a demonstration file (.npz)") from e
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise RecordError(f"{str(path)!r} is not a demonstration file (.npz): a single array")
    with z:
        missing = [k for k in (*_ARRAYS, "meta") if k not in z.files]
        if missing:
            raise RecordError(f"{str(path)!r} lacks arrays: {', '.join(missing)}")
        try:
            arrays = {k: np.asarray(z[k], dtype=float) for k in _ARRAYS}
            meta = json.loads(str(z["meta"]))
        except _READ_ERRORS as e:
            raise RecordError(
                f"{str(path)!r} is not a readable demonstration file (.npz): {e}"
            ) from e
    return arrays, _check_meta(meta, path)


def _check_meta(meta: Any, path: Path) -> dict[str, Any]:
    """``meta`` of a demonstration file, its version and fields checked."""
    if not isinstance(meta, dict):
        raise RecordError(f"{str(path)!r}: meta must be a JSON object, got {meta!r}")
    if meta.get("format_version") != DEMO_FORMAT_VERSION:
        raise RecordError(
            f"{str(path)!r}: format_version {meta.get('format_version')!r} is not "
            f"supported (valid choices: {DEMO_FORMAT_VERSION})"
        )
    for key, types in _META_TYPES.items():
        value = meta.get(key)
        if isinstance(value, bool) or not isinstance(value, types):
            kind = " or ".join(t.__name__ for t in types)
            raise RecordError(f"{str(path)!r}: meta {key} must be {kind}, got {value!r}")
    return meta

"""What a motion-capture system hands over: a raw stream of unlabelled points and bodies.

A :class:`MocapSource` records one trial: :meth:`MocapSource.start` begins, :meth:`MocapSource.stop`
returns a :class:`RawStream`. Everything downstream (labelling, resampling, clock alignment)
works on that plain data, whatever the source (a live system through ``motioncapture``, or a
file written by the lab's own capture software).

Frames and units: positions in the mocap (world) frame [m]; times [s] on the mocap clock (its
origin is arbitrary; :mod:`flyknot_hw.mocap.clock` relates it to the robot's clock).

The rope geometry the labeller needs is here too: marker ``k`` (0..10) sits at arclength
``s_k = 0.10 (k + 1)`` m from the fingertip, the last one at the free end (``s_10`` = rope
length, 1.1 m for every rope of the paper), so a rope hanging at rest has marker ``k`` at
``fingertip + s_k g`` with ``g`` the unit vector of gravity.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from flyknot.constants import MARKER_SPACING, N_MARKERS, ROPE_LENGTH
from flyknot.errors import ConfigError, check_positive
from flyknot.geometry import readonly

__all__ = [
    "BodyTrack",
    "MocapSource",
    "RawStream",
    "hanging_markers",
    "marker_arclengths",
]


def marker_arclengths(length: float = ROPE_LENGTH) -> np.ndarray:
    """Arclengths of the 11 rope markers from the fingertip, shape (11,) [m].

    ``s_k = MARKER_SPACING (k + 1)`` for k < 10 and ``s_10 = length`` (the free end).

    Raises:
        ConfigError: ``length`` is not longer than marker 9's arclength.
    """
    check_positive("length", length)
    s = MARKER_SPACING * np.arange(1, N_MARKERS + 1, dtype=float)
    if length <= s[-2]:
        raise ConfigError("length", f"must exceed {s[-2]:g} m (marker 9), got {length!r}")
    s[-1] = length
    return s


def _unit(name: str, v: object) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
        raise ConfigError(name, f"must be a finite non-zero vector of shape (3,), got {v!r}")
    return a / np.linalg.norm(a)


def hanging_markers(
    fingertip: np.ndarray,
    gravity_dir: np.ndarray = (0.0, 0.0, -1.0),
    arclengths: np.ndarray | None = None,
) -> np.ndarray:
    """Marker positions of a rope hanging straight down from the fingertip, shape (11, 3) [m].

    Args:
        fingertip: Fingertip position in the mocap frame, shape (3,) [m].
        gravity_dir: Direction of gravity in the mocap frame, shape (3,) (normalised here).
        arclengths: Marker arclengths, shape (11,) [m]; None: :func:`marker_arclengths`.
    """
    tip = np.asarray(fingertip, dtype=float)
    if tip.shape != (3,) or not np.all(np.isfinite(tip)):
        raise ConfigError("fingertip", f"must be a finite position of shape (3,), got {tip!r}")
    g = _unit("gravity_dir", gravity_dir)
    s = marker_arclengths() if arclengths is None else np.asarray(arclengths, dtype=float)
    if s.shape != (N_MARKERS,):
        raise ConfigError("arclengths", f"must have shape ({N_MARKERS},), got {s.shape}")
    return tip[None, :] + s[:, None] * g[None, :]


@dataclass(frozen=True)
class BodyTrack:
    """A named rigid body (or labelled marker cluster) as the capture system reports it.

    Attributes:
        position: Body origin per frame, shape (m, 3) [m]; NaN where occluded.
        quat: Orientation per frame (w, x, y, z), shape (m, 4); NaN where occluded or where
            the source gives positions only.
    """

    position: np.ndarray
    quat: np.ndarray

    def __post_init__(self) -> None:
        p = readonly(self.position)
        q = readonly(self.quat)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ConfigError("BodyTrack.position", f"must have shape (m, 3), got {p.shape}")
        if q.shape != (p.shape[0], 4):
            raise ConfigError("BodyTrack.quat", f"must have shape ({p.shape[0]}, 4), got {q.shape}")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quat", q)

    @classmethod
    def positions_only(cls, position: np.ndarray) -> BodyTrack:
        """A track without orientation (quaternions NaN)."""
        p = np.asarray(position, dtype=float)
        return cls(p, np.full((p.shape[0] if p.ndim == 2 else 0, 4), np.nan))


@dataclass(frozen=True)
class RawStream:
    """One recording as the capture system delivered it, before labelling.

    Attributes:
        times: Frame times on the mocap clock, shape (m,) [s], strictly increasing.
        points: Unlabelled marker points, shape (m, P, 3) [m]; a frame with fewer than P
            points is padded with NaN rows (live systems report a varying number). The order
            of the points within a frame carries no meaning.
        bodies: Named rigid bodies, each a :class:`BodyTrack` with m rows.
        source: Where the data came from (file path, ``"vicon@host"``, ...), for messages.
    """

    times: np.ndarray
    points: np.ndarray
    bodies: Mapping[str, BodyTrack] = field(default_factory=dict)
    source: str = ""

    def __post_init__(self) -> None:
        t = readonly(self.times)
        if t.ndim != 1 or t.shape[0] < 1:
            raise ConfigError("RawStream.times", f"must have shape (m,) with m >= 1, got {t.shape}")
        if not np.all(np.isfinite(t)):
            raise ConfigError("RawStream.times", "must be finite everywhere")
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0))
            raise ConfigError(
                "RawStream.times", f"must increase strictly; frame {k + 1} is not after frame {k}"
            )
        p = readonly(self.points)
        if p.ndim != 3 or p.shape[0] != t.shape[0] or p.shape[2] != 3:
            raise ConfigError(
                "RawStream.points", f"must have shape ({t.shape[0]}, P, 3), got {p.shape}"
            )
        bodies = dict(self.bodies)
        for name, body in bodies.items():
            if not isinstance(name, str) or not name:
                raise ConfigError("RawStream.bodies", f"names must be non-empty text, got {name!r}")
            if not isinstance(body, BodyTrack):
                raise ConfigError(f"RawStream.bodies[{name!r}]", "must be a BodyTrack")
            if body.position.shape[0] != t.shape[0]:
                raise ConfigError(
                    f"RawStream.bodies[{name!r}]",
                    f"has {body.position.shape[0]} frames, the stream {t.shape[0]}",
                )
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "bodies", bodies)
        object.__setattr__(self, "source", str(self.source))

    @property
    def n_frames(self) -> int:
        """Number of frames m."""
        return int(self.times.shape[0])

    def body(self, name: str) -> BodyTrack:
        """The body ``name``; the error lists the bodies there are."""
        if name not in self.bodies:
            raise ConfigError(
                "body", f"no body {name!r} in {self.source or 'the stream'}", sorted(self.bodies)
            )
        return self.bodies[name]

    def frame_rate(self) -> float:
        """Median frame rate [Hz] (1 / median frame interval)."""
        if self.n_frames < 2:
            raise ConfigError("RawStream.times", "a rate needs at least 2 frames")
        return float(1.0 / np.median(np.diff(self.times)))


@runtime_checkable
class MocapSource(Protocol):
    """A motion-capture system, live or through the files its software writes.

    Usage per trial: ``start()`` just before the robot moves, ``stop()`` after the settle; the
    stream returned holds every frame in between (a file source may hold more: the file the
    operator recorded).
    """

    def start(self) -> None:
        """Begin recording (raises :class:`flyknot.errors.HardwareError` if it cannot)."""
        ...

    def stop(self) -> RawStream:
        """End recording and return what was captured."""
        ...

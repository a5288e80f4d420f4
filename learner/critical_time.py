"""The critical time t_c found from a demonstration's markers alone.

The paper annotates t_c (the rope's first self-contact) by hand. Here it is detected from
what the motion capture gives, with two cues:

1. **Self-approach**: the rope is the polyline fingertip -> marker 0 -> ... -> marker 10.
   Two of its segments that share no point come closer than ``threshold``: the rope's
   diameter plus 3 sigma of the markers' noise. (The polyline cuts corners between markers
   0.1 m apart, so a chord margin seems natural; over 86 simulated demonstrations and
   replays a 1 cm margin moves the median error from 4 to 3 ms, and 2-4 cm fire up to
   0.2-0.34 s early on near misses of the thrown end: ``docs/learning.md``, section 7.)
2. **Tracking loss**: the first sample at which any marker is missing (NaN). Markers are lost
   when the rope covers itself, i.e. at or after the first contact.

t_c = the earlier of the two (either may be absent). Frames with a missing marker are not used
for the self-approach (the polyline is incomplete).

Pure numpy: arrays in, times out; :func:`detect_critical_time` takes a
:class:`flyknot.demo.Demonstration`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import RecordError, check_nonnegative, check_positive

__all__ = [
    "CriticalTime",
    "detect_critical_time",
    "first_self_approach",
    "first_tracking_loss",
    "polyline_self_distance",
]

CHORD_MARGIN = 0.0
"""Added to the rope diameter in the self-approach threshold [m]; 0 measured best (module
docstring)."""


def _segment_pair_distances(p0, p1, q0, q1) -> np.ndarray:
    """Closest distances between segments [p0, p1] and [q0, q1], all (..., 3) -> (...)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    denom = a * e - b * b
    safe = np.where(denom > 1e-18, denom, 1.0)
    s = np.where(denom > 1e-18, np.clip((b * f - c * e) / safe, 0.0, 1.0), 0.0)
    t = np.where(e > 1e-18, (b * s + f) / np.where(e > 1e-18, e, 1.0), 0.0)
    # Clamp t to [0, 1] and recompute s for the clamped t.
    t_lo, t_hi = t < 0.0, t > 1.0
    t = np.clip(t, 0.0, 1.0)
    a_safe = np.where(a > 1e-18, a, 1.0)
    s = np.where(t_lo, np.clip(-c / a_safe, 0.0, 1.0), s)
    s = np.where(t_hi, np.clip((b - c) / a_safe, 0.0, 1.0), s)
    diff = (p0 + s[..., None] * d1) - (q0 + t[..., None] * d2)
    return np.sqrt(np.einsum("...i,...i->...", diff, diff))


def polyline_self_distance(points: np.ndarray, gap: int = 2) -> np.ndarray:
    """Smallest distance between two segments of a polyline at least ``gap`` segments apart.

    d = min over segment pairs (i, j), j >= i + gap, of the closest distance between segment
    [p_i, p_{i+1}] and segment [p_j, p_{j+1}] (gap 2: segments that share no point).

    Args:
        points: Polylines, shape (..., k, 3) [m], k >= gap + 2.
        gap: Smallest index difference of the segments compared, >= 2.

    Returns:
        Distances, shape (...) [m].
    """
    points = np.asarray(points, dtype=float)
    k = points.shape[-2]
    if isinstance(gap, bool) or not isinstance(gap, int) or gap < 2:
        raise RecordError(f"gap must be an integer >= 2, got {gap!r}")
    if points.ndim < 2 or points.shape[-1] != 3 or k < gap + 2:
        raise RecordError(
            f"points must have shape (..., k, 3) with k >= {gap + 2}, got {points.shape}"
        )
    i, j = np.triu_indices(k - 1, k=gap)
    d = _segment_pair_distances(
        points[..., i, :], points[..., i + 1, :], points[..., j, :], points[..., j + 1, :]
    )
    return d.min(axis=-1)


def first_self_approach(
    t: np.ndarray, hand_pos: np.ndarray, markers: np.ndarray, threshold: float, gap: int = 2
) -> float | None:
    """First time the rope polyline (fingertip then markers) comes within ``threshold`` of
    itself, using only frames where every marker is seen.

    Args:
        t: Sample times, shape (m,) [s].
        hand_pos: Fingertip positions, shape (m, 3) [m].
        markers: Markers, shape (m, 11, 3) [m], NaN where lost.
        threshold: Distance [m].
        gap: Smallest index difference of two polyline segments compared (2: segments
            sharing no vertex).

    Returns:
        The time [s], or None if never.
    """
    check_positive("threshold", threshold)
    poly = np.concatenate([np.asarray(hand_pos)[:, None, :], np.asarray(markers)], axis=1)
    seen = np.all(np.isfinite(poly), axis=(1, 2))
    if not np.any(seen):
        return None
    d = np.full(len(t), np.inf)
    d[seen] = polyline_self_distance(poly[seen], gap)
    hit = np.flatnonzero(d < threshold)
    return float(t[hit[0]]) if hit.size else None


def first_tracking_loss(t: np.ndarray, markers: np.ndarray) -> float | None:
    """First time any marker is missing (NaN), or None."""
    lost = np.flatnonzero(~np.all(np.isfinite(np.asarray(markers)), axis=(1, 2)))
    return float(t[lost[0]]) if lost.size else None


@dataclass(frozen=True)
class CriticalTime:
    """A detected critical time.

    Attributes:
        t_c: The detected time [s] (None if neither cue fired).
        cue: ``"approach"``, ``"tracking_loss"`` or ``"none"``.
        t_approach: Time of the self-approach cue [s] or None.
        t_loss: Time of the tracking-loss cue [s] or None.
    """

    t_c: float | None
    cue: str
    t_approach: float | None
    t_loss: float | None


def detect_critical_time(
    demo: Demonstration, diameter: float, *, margin: float = CHORD_MARGIN, noise: float = 0.001
) -> CriticalTime:
    """t_c from the demonstration's markers alone (module docstring).

    Args:
        demo: The demonstration (its own ``t_c`` is not read).
        diameter: Rope diameter [m].
        margin: Chord margin added to the diameter [m].
        noise: Marker noise std [m]; 3 sigma is added to the threshold.

    Returns:
        The detection with both cues.
    """
    check_positive("diameter", diameter)
    check_nonnegative("margin", margin)
    check_nonnegative("noise", noise)
    threshold = diameter + margin + 3.0 * noise
    ta = first_self_approach(demo.t, demo.hand_pos, demo.markers, threshold)
    tl = first_tracking_loss(demo.t, demo.markers)
    cands = [(x, name) for x, name in ((ta, "approach"), (tl, "tracking_loss")) if x is not None]
    if not cands:
        return CriticalTime(None, "none", ta, tl)
    tc, cue = min(cands)
    return CriticalTime(tc, cue, ta, tl)

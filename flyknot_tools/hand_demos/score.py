"""Score of one trial of a flying-knot motion, and the writhe it credits.

Score of one trial (:func:`score`; ``docs/demo-synthesis.md`` has the reasoning):

    S = 100 [knot at the end] + 30 f_settle + 10 [knot at any judged frame]
        + 5 [rope self-contact] + 5 min(|Wr|_max, 3) / 3
        - 20 max(0, v_peak - 8 m/s) - 100 max(0, e_max - 0.7 m) - 100 g_variant

with f_settle the knotted fraction of the judged settling frames, Wr the writhe of the
centreline (largest over judged frames), v_peak and e_max the target hand's peak speed and
largest distance from its start, and g_variant a variant's own constraint violation (e.g.
the Swipe's strike must travel as far horizontally as it drops). Motions that break the
speed, excursion or
variant limits are not simulated; they score -10 minus the penalty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError, RecordError, check_positive

SPEED_LIMIT = 8.0
"""Largest hand speed of a human demonstrator [m/s] (penalised above)."""
EXCURSION_LIMIT = 0.7
"""Largest distance of the hand from its start [m] (penalised above)."""


# ----------------------------------------------------------------------------------------
# writhe and score
# ----------------------------------------------------------------------------------------
def writhe(points: np.ndarray) -> float:
    """Writhe of an open polyline, the Gauss double integral summed over segment pairs.

    Wr = (1 / 2 pi) sum_{i < j} Omega_ij, with Omega_ij the signed solid angle of segment
    pair (i, j) (Klenin & Langowski, Biopolymers 54 (2000) 307-317, method 1a): for segment
    i from p1 to p2 and j from p3 to p4, r_kl = p_l - p_k,
    n1 = r13 x r14, n2 = r14 x r24, n3 = r24 x r23, n4 = r23 x r13 (normalised),
    Omega* = asin(n1.n2) + asin(n2.n3) + asin(n3.n4) + asin(n4.n1),
    Omega = Omega* sign((r34 x r12) . r13). Adjacent segments contribute 0.

    Args:
        points: Polyline, shape (n, 3) [m], n >= 2.

    Returns:
        Wr [-] (0 for planar curves; it changes sign under reflection).
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
        raise RecordError(f"points must have shape (n, 3) with n >= 2, got {p.shape}")
    m = p.shape[0] - 1
    i, j = np.triu_indices(m, k=2)
    if len(i) == 0:
        return 0.0
    p1, p2, p3, p4 = p[i], p[i + 1], p[j], p[j + 1]
    r13, r14, r23, r24 = p3 - p1, p4 - p1, p3 - p2, p4 - p2

    def unit(v: np.ndarray) -> np.ndarray:
        n = np.linalg.norm(v, axis=1, keepdims=True)
        return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-300)

    n1 = unit(np.cross(r13, r14))
    n2 = unit(np.cross(r14, r24))
    n3 = unit(np.cross(r24, r23))
    n4 = unit(np.cross(r23, r13))

    def asin_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.arcsin(np.clip(np.einsum("ki,ki->k", u, v), -1.0, 1.0))

    omega = asin_dot(n1, n2) + asin_dot(n2, n3) + asin_dot(n3, n4) + asin_dot(n4, n1)
    sign = np.sign(np.einsum("ki,ki->k", np.cross(p4 - p3, p2 - p1), r13))
    return float(np.sum(omega * sign) / (2.0 * math.pi))


@dataclass(frozen=True)
class TrialSummary:
    """What the score needs from one trial of a motion.

    Attributes:
        tied: A trefoil on the settled rope.
        settle_fraction: Knotted fraction of the judged settling frames, in [0, 1].
        knot_any: A trefoil in any judged frame from the motion's start on.
        contact: The rope touched itself.
        writhe: Largest |writhe| over the judged frames [-].
        peak_speed: Peak target hand speed [m/s].
        excursion: Largest target distance of the hand from its start [m].
        violation: The variant's own constraint violation (0 when met) [-].
        simulated: False for motions rejected before simulation (limits broken).
    """

    tied: bool = False
    settle_fraction: float = 0.0
    knot_any: bool = False
    contact: bool = False
    writhe: float = 0.0
    peak_speed: float = 0.0
    excursion: float = 0.0
    violation: float = 0.0
    simulated: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.settle_fraction <= 1.0:
            raise ConfigError(
                "TrialSummary.settle_fraction", f"must lie in [0, 1], got {self.settle_fraction!r}"
            )
        for f in ("writhe", "peak_speed", "excursion", "violation"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"TrialSummary.{f}", f"must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class ScoreWeights:
    """Weights of :func:`score` (see the module docstring).

    Attributes:
        tied: Knot on the settled rope.
        settle: Per unit knotted settling fraction.
        knot_any: Knot in any judged frame.
        contact: Rope self-contact.
        writhe: Per unit of min(|Wr|, writhe_cap) / writhe_cap.
        writhe_cap: Writhe beyond which there is no more credit [-].
        speed: Penalty per m/s above :data:`SPEED_LIMIT`.
        excursion: Penalty per m above :data:`EXCURSION_LIMIT`.
        violation: Penalty per unit of the variant's constraint violation.
        rejected: Extra penalty of a motion that is not simulated.
    """

    tied: float = 100.0
    settle: float = 30.0
    knot_any: float = 10.0
    contact: float = 5.0
    writhe: float = 5.0
    writhe_cap: float = 3.0
    speed: float = 20.0
    excursion: float = 100.0
    violation: float = 100.0
    rejected: float = 10.0

    def __post_init__(self) -> None:
        for f in ("tied", "settle", "knot_any", "contact", "writhe", "speed", "excursion"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"ScoreWeights.{f}", f"must be a finite number >= 0, got {v!r}")
        check_positive("ScoreWeights.writhe_cap", self.writhe_cap)


def limit_penalty(summary: TrialSummary, weights: ScoreWeights = ScoreWeights()) -> float:
    """P = w_v max(0, v_peak - 8) + w_e max(0, e_max - 0.7) + w_g g_variant (>= 0)."""
    return (
        weights.speed * max(0.0, summary.peak_speed - SPEED_LIMIT)
        + weights.excursion * max(0.0, summary.excursion - EXCURSION_LIMIT)
        + weights.violation * summary.violation
    )


def score(summary: TrialSummary, weights: ScoreWeights = ScoreWeights()) -> float:
    """Shaped score of one trial (module docstring); higher is better.

    S = w_k [tied] + w_s f_settle + w_a [knot_any] + w_c [contact]
        + w_w min(|Wr|, cap) / cap - P  (simulated), or -w_r - P (rejected),
    with P from :func:`limit_penalty`.
    """
    penalty = limit_penalty(summary, weights)
    if not summary.simulated:
        return -weights.rejected - penalty
    return (
        weights.tied * summary.tied
        + weights.settle * summary.settle_fraction
        + weights.knot_any * summary.knot_any
        + weights.contact * summary.contact
        + weights.writhe * min(summary.writhe, weights.writhe_cap) / weights.writhe_cap
        - penalty
    )

"""The kinds of flying-knot demonstration (Fast, Slow, Swipe, Inverse) and the search box.

A :class:`Variant` fixes the duration range, the seed motion, the variant's own constraint
(e.g. the Swipe's sideways strike) and pace limits; :func:`param_bounds` and
:data:`PARAM_SCALE` are the box and units the search works in. Angle control points are
bounded to +-300 degrees (without a bound a search drifts to multi-turn wrist spins).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from flyknot.errors import ConfigError, check_choice, check_positive
from flyknot_sim.hand_motion import (
    CURVES,
    N_HEAD,
    N_PARAMS,
    WINDUP_MAX,
    WINDUP_SPEED_MIN,
    KnotMotion,
)
from flyknot_tools.hand_demos.reference import load_reference_motion

ANGLE_BOUND = math.radians(300.0)
"""Bound of the wrist-angle control points [rad]."""
VIA_BOUND = 1.2
"""Bound of the position control points Y_3..Y_5 [m] (the path's excursion is limited
separately)."""
END_BOUND = 0.6
"""Bound of the end position [m]."""


# ----------------------------------------------------------------------------------------
# variants
# ----------------------------------------------------------------------------------------
SEEDS = ("reference", "reference-mirrored")
THROW_WINDOW = (0.66, 0.72)
"""Duration window of the throw (the first stage of every variant) [s]: the reference's
0.70 s; scaling a knotting motion in time keeps the knot only within about +-3 %."""
STAGE_KINDS = ("throw", "windup")
PACE_FIELDS = ("speed_limit", "axis_rate_limit", "accel_limit")
"""A variant's pace limits, in the order of :meth:`Variant.pace`'s peaks."""
PACE_WEIGHT = 0.1
"""Violation per unit of relative excess over a variant's pace limits (10 % over a limit
counts like a 1 cm swipe violation)."""


@dataclass(frozen=True)
class Variant:
    """A kind of flying-knot demonstration (the paper's Fast, Slow, Swipe, Inverse).

    Every variant is searched in stages (:meth:`stages`,
    :func:`~flyknot_tools.hand_demos.synthesis.synthesize_motion`): a throw in
    :data:`THROW_WINDOW` from the seed motion (with the variant's own constraint), then, for a
    longer ``duration``, a slow wind-up added before the throw
    (:meth:`KnotMotion.with_windup`).

    Attributes:
        name: Name (lower case).
        description: One line.
        duration: Range of the motion's duration T [s] (a hard bound of the search).
        seed: Start of the search: ``reference`` (the feasibility study's motion, refitted)
            or ``reference-mirrored`` (its mirror image, the opposite twist); its duration
            is clipped into ``duration``.
        swipe_ratio: If > 0, the strike (from the hand's highest point to its end) must
            travel at least this many times farther horizontally than it drops:
            violation g = max(0, dz - dh / swipe_ratio) [m].
        throw_sigma: CMA-ES initial step of the throw stage [normalised units]; a
            constrained throw needs a broader search (measured, see the docs).
        speed_limit: Peak hand speed allowed by the variant [m/s] (inf: only the global
            :data:`~flyknot_tools.hand_demos.score.SPEED_LIMIT`); the excess counts in the
            violation (:meth:`violation`).
        axis_rate_limit: Peak angular rate of the rope's exit axis allowed [rad/s] (inf: no
            limit). A robot follows a hand only as fast as its wrist turns: a demonstration
            for a robot is made with a limit near the robot's own (see :meth:`pace`).
        accel_limit: Peak hand acceleration allowed [m/s^2] (inf: no limit). The three pace
            limits of a demonstration within the arm's reach come from
            :func:`flyknot_tools.hand_demos.envelope.shared_envelope`.
    """

    name: str
    description: str
    duration: tuple[float, float]
    seed: str = "reference"
    swipe_ratio: float = 0.0
    throw_sigma: float = 0.3
    speed_limit: float = math.inf
    axis_rate_limit: float = math.inf
    accel_limit: float = math.inf

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.duration)
        if not 0.1 <= lo <= hi <= 5.0:
            raise ConfigError(
                "Variant.duration", f"need 0.1 <= lo <= hi <= 5 s, got {self.duration}"
            )
        object.__setattr__(self, "duration", (lo, hi))
        check_choice("Variant.seed", self.seed, SEEDS)
        if not (math.isfinite(self.swipe_ratio) and self.swipe_ratio >= 0):
            raise ConfigError("Variant.swipe_ratio", f"must be >= 0, got {self.swipe_ratio!r}")
        check_positive("Variant.throw_sigma", self.throw_sigma)
        for f in PACE_FIELDS:
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"Variant.{f}", f"must be a number > 0 (inf: none), got {v!r}")

    def pace(self, motion: KnotMotion, dt: float = 0.001) -> tuple[float, float, float]:
        """Peak hand speed max |p'| [m/s], peak exit-axis rate max |d'| [rad/s] and peak hand
        acceleration max |p''| [m/s^2].

        The rope leaves the hand along d = Ry(b) Rx(a) (0, 0, -1), so
        |d'| = sqrt(a'^2 + cos(a)^2 b'^2); sampled every ``dt`` over [0, T].
        """
        t = np.linspace(0.0, motion.duration, max(3, math.ceil(motion.duration / dt) + 1))
        y, yd, ydd = motion.curves(t), motion.curves(t, 1), motion.curves(t, 2)
        speed = np.linalg.norm(yd[:, :3], axis=1)
        rate = np.sqrt(yd[:, 3] ** 2 + (np.cos(y[:, 3]) * yd[:, 4]) ** 2)
        accel = np.linalg.norm(ydd[:, :3], axis=1)
        return float(speed.max()), float(rate.max()), float(accel.max())

    def strike(self, motion: KnotMotion) -> tuple[float, float]:
        """The strike's drop dz and horizontal travel dh [m], from the hand's highest point
        (sampled at 201 times) to its end."""
        t = np.linspace(0.0, motion.duration, 201)
        p = motion.curves(t)[:, :3]
        k = int(np.argmax(p[:, 2]))
        return float(p[k, 2] - p[-1, 2]), float(np.linalg.norm(p[-1, :2] - p[k, :2]))

    def violation(self, motion: KnotMotion) -> float:
        """The variant's constraint violation g(motion) >= 0 (0 when met).

        g = max(0, dz - dh / swipe_ratio) [m] (swipe)
            + PACE_WEIGHT (max(0, v_peak / speed_limit - 1) + max(0, w_peak / axis_rate_limit - 1)
                           + max(0, a_peak / accel_limit - 1))
        """
        g = 0.0
        if self.swipe_ratio > 0:
            dz, dh = self.strike(motion)
            g += max(0.0, dz - dh / self.swipe_ratio)
        limits = tuple(getattr(self, f) for f in PACE_FIELDS)
        if any(math.isfinite(v) for v in limits):
            peaks = self.pace(motion)
            g += PACE_WEIGHT * sum(
                max(0.0, p / v - 1.0) for p, v in zip(peaks, limits, strict=True)
            )
        return g

    def seed_motion(self) -> KnotMotion:
        """The search's start: the seed motion with T clipped into ``duration``."""
        m = load_reference_motion()
        if self.seed == "reference-mirrored":
            m = m.mirrored()
        x = m.x.copy()
        x[0] = float(np.clip(x[0], *self.duration))
        return KnotMotion(x)

    def stages(self) -> list[tuple[str, Variant]]:
        """The search stages: (kind, stage variant) with kind in :data:`STAGE_KINDS`.

        ``throw`` in :data:`THROW_WINDOW` (with ``swipe_ratio``); a ``windup`` stage moves to
        ``duration`` if that differs from the throw window. The last stage is the variant
        itself.
        """
        if self.duration == THROW_WINDOW:
            return [("throw", self)]
        throw = replace(self, name=f"{self.name}/throw", duration=THROW_WINDOW)
        return [("throw", throw), ("windup", self)]


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("fast", "a quick throw and strike from rest", THROW_WINDOW),
        Variant("slow", "the same kind of throw after a long slow wind-up", (1.00, 1.08)),
        Variant(
            "swipe",
            "the strike sweeps sideways: it travels as far horizontally as it drops",
            (0.80, 0.86),
            swipe_ratio=1.0,
            throw_sigma=0.6,
        ),
        Variant(
            "inverse",
            "the opposite twist (mirror-image seed: a knot of the other handedness)",
            (0.90, 0.96),
            seed="reference-mirrored",
        ),
    )
}
"""The four demonstration kinds, by name."""


def get_variant(name: str) -> Variant:
    """The variant called ``name``.

    Raises:
        ConfigError: Unknown name, listing the valid ones.
    """
    if name not in VARIANTS:
        raise ConfigError("variant", f"unknown value {name!r}", list(VARIANTS))
    return VARIANTS[name]


def param_bounds(variant: Variant) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds of the 21 numbers for ``variant``: lo, hi, shape (21,) [s, m, rad]."""
    lo = np.empty(N_PARAMS)
    hi = np.empty(N_PARAMS)
    lo[0], hi[0] = variant.duration
    lo[1], hi[1] = 0.0, WINDUP_MAX
    lo[2], hi[2] = WINDUP_SPEED_MIN, 1.0
    for c, name in enumerate(CURVES):
        sl = slice(N_HEAD + 4 * c, N_HEAD + 4 + 4 * c)
        bound = ANGLE_BOUND if name in ("a", "b") else VIA_BOUND
        lo[sl], hi[sl] = -bound, bound
        if name not in ("a", "b"):
            lo[N_HEAD + 3 + 4 * c], hi[N_HEAD + 3 + 4 * c] = -END_BOUND, END_BOUND
    return lo, hi


PARAM_SCALE = np.array([0.05, 0.05, 0.05] + [0.1] * 12 + [0.5] * 8)
"""Unit of the search's normalised coordinates per number: 50 ms, 0.05 of p and r, 10 cm,
0.5 rad."""

"""The hand lab's parameters and conventions: settings, trial variation, motions, orientation.

What defines a hand lab (:class:`HandParams`) and its seeded trial-to-trial variation
(:class:`HandVariation`), the protocol of a hand motion (:class:`JointTrajectory`: targets of
the six hand joints) and the hinge chain's orientation R = Ry(b) Rx(a) Rz(c)
(:func:`hand_rotation`). The lab itself (scene, trial) is :mod:`flyknot_sim.hand`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from flyknot.errors import ConfigError, check_nonnegative, check_positive
from flyknot.judge import with_rope_diameter
from flyknot.rest import SettleParams
from flyknot.verdict import JudgeParams
from flyknot_sim.aero import AeroParams
from flyknot_sim.bend_friction import BendFrictionParams
from flyknot_sim.lab_params import VariationParams
from flyknot_sim.rope_custom import resolve_rope
from flyknot_sim.rope_table import RopeParams, SimSettings

__all__ = ["HandParams", "HandVariation", "JointTrajectory", "hand_rotation"]


# ----------------------------------------------------------------------------------------
# parameters
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HandVariation(VariationParams):
    """Seeded trial-to-trial variation of a hand trial: the robot lab's
    (:class:`flyknot_sim.lab_params.VariationParams`: each field's source and bracket; the
    command's start delay is the motion's here) plus the person's tempo.

    Attributes:
        tempo_rel: Relative std of the motion's duration (a person never repeats a tempo
            exactly) [-]. 0.005 is 4 ms on a 0.8 s throw; bracket 0.0025-0.0125 (2-10 ms):
            recreational ball players time a throw's release to about 10 ms (Hore et al.,
            J. Neurophysiol. 75 (1996) 1013, as New Scientist, 6 April 1996, reports it).
    """

    tempo_rel: float = 0.005

    def __post_init__(self) -> None:
        super().__post_init__()
        check_nonnegative("tempo_rel", self.tempo_rel)
        if self.tempo_rel >= 0.2:
            raise ConfigError("tempo_rel", f"must be < 0.2, got {self.tempo_rel!r}")

    @classmethod
    def none(cls) -> HandVariation:
        """No variation: every trial of a motion is the same."""
        return cls(0.0, 0.0, 0.0, False, tempo_rel=0.0)


@dataclass(frozen=True)
class HandParams:
    """Everything that defines the hand lab.

    Attributes:
        rope: Rope id (1..7, see ``assets/ropes.toml``), a rope's name (the paper's, or one of
            ``ropes``), or a :class:`flyknot_sim.rope_table.RopeParams`
            (:func:`flyknot_sim.rope_custom.resolve_rope`); a paper rope's name becomes its id.
        home: Hand position at zero joints [m]; the rope hangs from it.
        hand_mass: Mass of the hand [kg] (gravity-compensated).
        hand_inertia: Rotational inertia of the hand about each axis [kg m^2].
        hinge_armature: Armature of each hinge [kg m^2]; keeps the mass matrix regular where
            the y and z hinges align (a = +-90 degrees).
        slide_bandwidth: Natural frequency w of the slide servos [rad/s].
        hinge_bandwidth: Natural frequency w of the hinge servos [rad/s].
        hang_s: Time the hand holds still before the motion [s].
        settle: When the knot is judged after the motion (:class:`flyknot.rest.SettleParams`):
            at rest, capped, as in the robot lab.
        settle_s: A fixed wait instead [s]; None: ``settle``.
        aero: Air drag on the rope.
        bend_friction: Hysteretic bending friction of the rope (by default the rope's own), as
            in the robot lab.
        twist: Build the rope with a twist hinge per edge, as in the robot lab.
        judge_rate_hz: Rate of the frames judged for ``knot_any`` and the settling
            fraction [Hz].
        variation: Trial-to-trial variation.
        settings: Rope simulation settings (default: the ``[simulation]`` table of
            ``assets/ropes.toml``).
        ropes: A user's ropes file whose ropes ``rope`` may name, or None (an absolute path).
    """

    rope: int | str | RopeParams = 1
    home: tuple[float, float, float] = (0.0, 0.0, 1.5)
    hand_mass: float = 0.5
    hand_inertia: float = 1e-3
    hinge_armature: float = 2e-4
    slide_bandwidth: float = 200.0
    hinge_bandwidth: float = 200.0
    hang_s: float = 0.05
    settle: SettleParams = field(default_factory=SettleParams)
    settle_s: float | None = None
    aero: AeroParams = field(default_factory=AeroParams)
    bend_friction: BendFrictionParams = field(default_factory=BendFrictionParams)
    twist: bool = False
    judge_rate_hz: float = 10.0
    variation: HandVariation = field(default_factory=HandVariation)
    settings: SimSettings | None = None
    ropes: str | None = None

    def __post_init__(self) -> None:
        if self.ropes is not None:
            object.__setattr__(self, "ropes", str(Path(self.ropes).expanduser().resolve()))
        rope = resolve_rope(self.rope, self.ropes)  # validates, listing the valid choices
        if not rope.custom and not isinstance(self.rope, RopeParams):
            object.__setattr__(self, "rope", rope.id)
        home = tuple(float(v) for v in np.asarray(self.home, dtype=float).ravel())
        if len(home) != 3 or not all(math.isfinite(v) for v in home):
            raise ConfigError("HandParams.home", f"must be 3 finite numbers, got {self.home!r}")
        object.__setattr__(self, "home", home)
        for f in (
            "hand_mass",
            "hand_inertia",
            "hinge_armature",
            "slide_bandwidth",
            "hinge_bandwidth",
            "judge_rate_hz",
        ):
            check_positive(f"HandParams.{f}", getattr(self, f))
        check_nonnegative("HandParams.hang_s", self.hang_s)
        if self.settle_s is not None:
            check_nonnegative("HandParams.settle_s", self.settle_s)
        if not isinstance(self.variation, HandVariation):
            raise ConfigError(
                "HandParams.variation",
                f"must be a HandVariation, got {type(self.variation).__name__}",
            )

    @property
    def settle_rule(self) -> SettleParams:
        """The settle in force: ``settle``, or a fixed wait of ``settle_s``."""
        return self.settle if self.settle_s is None else SettleParams.fixed(self.settle_s)

    @property
    def rope_params(self) -> RopeParams:
        """The rope."""
        return resolve_rope(self.rope, self.ropes)

    @property
    def judge_params(self) -> JudgeParams:
        """The judge of this rope: a knot on the floor told by the rope's own radius."""
        return with_rope_diameter(self.rope_params.diameter)

    def joint_inertia(self) -> np.ndarray:
        """Inertia seen by each joint, (m, m, m, I + I_a, I + I_a, I + I_a), shape (6,)
        [kg, kg m^2] (the hinges' coupling through the chain is neglected)."""
        return np.array([self.hand_mass] * 3 + [self.hand_inertia + self.hinge_armature] * 3)

    def servo_gains(self) -> tuple[np.ndarray, np.ndarray]:
        """Nominal servo gains: kp = I w^2 [N/m, N m/rad], kv = 2 I w [N s/m, N m s/rad].

        Returns:
            kp, kv, shape (6,) each.
        """
        inertia = self.joint_inertia()
        w = np.array([self.slide_bandwidth] * 3 + [self.hinge_bandwidth] * 3)
        return inertia * w**2, 2.0 * inertia * w


# ----------------------------------------------------------------------------------------
# motions
# ----------------------------------------------------------------------------------------
class JointTrajectory(Protocol):
    """A hand motion as targets of the six hand joints (see :data:`HAND_JOINTS`)."""

    @property
    def duration(self) -> float:
        """Length of the motion [s]; it is at rest at 0 and from ``duration`` on."""
        ...

    def joint_targets(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint targets at times ``t`` (T,) [s] from the motion's start (held outside
        [0, duration]): q (T, 6) [m, rad] relative to ``home``, qd (T, 6), qdd (T, 6)."""
        ...


def hand_rotation(b: np.ndarray, a: np.ndarray, c: np.ndarray | None = None) -> np.ndarray:
    """Hand orientation R = Ry(b) Rx(a) Rz(c) of the hinge chain.

    Args:
        b: Angles about world y, shape (T,) [rad].
        a: Angles about x (after the y turn), shape (T,) [rad].
        c: Angles about z (last), shape (T,) [rad]; None means 0.

    Returns:
        Rotation matrices, shape (T, 3, 3).
    """
    b = np.atleast_1d(np.asarray(b, dtype=float))
    a = np.atleast_1d(np.asarray(a, dtype=float))
    c = np.zeros_like(a) if c is None else np.atleast_1d(np.asarray(c, dtype=float))
    cb, sb, ca, sa, cc, sc = np.cos(b), np.sin(b), np.cos(a), np.sin(a), np.cos(c), np.sin(c)
    one, zero = np.ones_like(a), np.zeros_like(a)
    ry = np.stack([cb, zero, sb, zero, one, zero, -sb, zero, cb], -1).reshape(-1, 3, 3)
    rx = np.stack([one, zero, zero, zero, ca, -sa, zero, sa, ca], -1).reshape(-1, 3, 3)
    rz = np.stack([cc, -sc, zero, sc, cc, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return ry @ rx @ rz

"""What defines the simulated lab (:class:`LabParams`) and its trial-to-trial variation
(:class:`VariationParams`): parameters only, read by :class:`flyknot_sim.lab.SimLab` and the
trial it plays (:mod:`flyknot_sim.session`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from flyknot.errors import ConfigError, check_nonnegative, check_positive, check_share
from flyknot.rest import SettleParams
from flyknot_sim import mocap
from flyknot_sim.aero import AeroParams
from flyknot_sim.bend_friction import BendFrictionParams
from flyknot_sim.rope_custom import resolve_rope
from flyknot_sim.rope_table import RopeParams, SimSettings
from flyknot_sim.scene import SceneParams


@dataclass(frozen=True)
class VariationParams:
    """Seeded trial-to-trial variation, as in a real lab.

    Where each number comes from (``docs/rope-model.md``, "The lab's trial-to-trial
    variation", with what each does to the repeats across its bracket):

    * ``servo_gain_rel`` 0.03: not measured on an xArm; it stands in for everything that moves
      the arm's path from one play of a command to the next. Bracket 0.003-0.03: at 0.003 a
      learned rope-1 command's fingertip path lies within 0.15 mm of its play without
      variation (the median over 200 plays of the largest distance), the size of the xArm's
      published position repeatability, +-0.1 mm (UFACTORY xArm user manual, section 8.1,
      "Technical specifications"); at 0.03 within 0.97 mm, four times an industrial arm's
      dynamic path error at 0.7 m/s (+-0.25 mm, ABB IRB 1600: Slamani, Nubiola & Bonev,
      Industrial Robot 39 (2012) 57) at this throw's 4 m/s.
    * ``start_delay_max_s`` 0.004: one tick of the controller's 250 Hz joint stream; the lab's
      clock and the command's are not synchronised (a derivation, not a bracket).
    * ``rest_start`` and ``rest_scale`` 1: the rope's start anywhere a lab would call it
      static (:func:`flyknot.rest.settled_start`, the rest criterion's 8.4 mm and 3 cm/s,
      ``docs/rope-model.md``). Bracket 0.1-1: a person who waits longer starts the rope
      stiller; 0.1 (0.8 mm) is the motion capture's 1 mm noise, below which a lab cannot tell.

    Attributes:
        sway_deg: Std of an extra initial tilt of the rope from vertical [deg], |N(0, s^2)|
            toward a uniform azimuth, for robustness studies (0: the settled start alone).
        servo_gain_rel: Relative std of each servo's stiffness and damping gains [-].
        start_delay_max_s: The command starts after a uniform delay in [0, this) [s].
        rest_start: Draw the rope's start state uniformly within the lab's rest criterion
            (a rope that a lab would call static; :func:`flyknot.rest.settled_start`); False
            starts it hanging straight and still.
        rest_scale: The settled start's disc as a share of the rest criterion's, in [0, 1]
            (the same draws scaled: 1 any static start, 0 hanging still).
    """

    sway_deg: float = 0.0
    servo_gain_rel: float = 0.03
    start_delay_max_s: float = 0.004
    rest_start: bool = True
    rest_scale: float = 1.0

    def __post_init__(self) -> None:
        check_nonnegative("sway_deg", self.sway_deg)
        check_nonnegative("servo_gain_rel", self.servo_gain_rel)
        check_nonnegative("start_delay_max_s", self.start_delay_max_s)
        if not isinstance(self.rest_start, bool):
            raise ConfigError("rest_start", f"must be true or false, got {self.rest_start!r}")
        check_share("rest_scale", self.rest_scale)

    @classmethod
    def none(cls) -> VariationParams:
        """No variation: every trial of a command is the same."""
        return cls(0.0, 0.0, 0.0, False)


@dataclass(frozen=True)
class LabParams:
    """Everything that defines the simulated lab.

    Attributes:
        rope: Rope id (1..7, see ``assets/ropes.toml``), a rope's name (the paper's, or one of
            ``ropes``), or a :class:`flyknot_sim.rope_table.RopeParams`
            (:func:`flyknot_sim.rope_custom.resolve_rope`); a paper rope's name becomes its id.
        seed: Seed of the trial-to-trial variation and the mocap noise; trial ``i`` of a
            lab uses ``(seed, i)``.
        settle: When the knot is judged after the command: until the rope is at rest, capped
            (:class:`flyknot.rest.SettleParams`).
        settle_s: A fixed wait instead [s] (judged then, at rest or not); None: ``settle``.
        aero: Air drag on the rope.
        bend_friction: Hysteretic bending friction of the rope (Grosberg's frictional couple);
            by default the rope's own (``assets/ropes.toml``, ``docs/rope-model.md``).
        twist: Build the rope with a twist hinge per edge (rod torsion; ``add_rope(twist=)``).
        brake_s: After a fault, how long the arm is simulated braking [s].
        truth_rate_hz: Rate of the ground-truth centreline stored in ``truth`` [Hz].
        variation: Trial-to-trial variation.
        mocap: Motion-capture emulation.
        scene: Geometry of the lab.
        ropes: A user's ropes file (``assets/ropes_example.toml``) whose ropes ``rope`` may
            name, or None; kept as an absolute path.
        settings: Rope simulation settings (default: the ``[simulation]`` table of
            ``assets/ropes.toml``), as in the hand lab.
    """

    rope: int | str | RopeParams = 1
    seed: int = 0
    settle: SettleParams = field(default_factory=SettleParams)
    settle_s: float | None = None
    aero: AeroParams = field(default_factory=AeroParams)
    bend_friction: BendFrictionParams = field(default_factory=BendFrictionParams)
    twist: bool = False
    brake_s: float = 0.3
    truth_rate_hz: float = 100.0
    variation: VariationParams = field(default_factory=VariationParams)
    mocap: mocap.MocapParams = field(default_factory=mocap.MocapParams)
    scene: SceneParams = field(default_factory=SceneParams)
    ropes: str | None = None
    settings: SimSettings | None = None

    def __post_init__(self) -> None:
        if self.ropes is not None:
            object.__setattr__(self, "ropes", str(Path(self.ropes).expanduser().resolve()))
        rope = resolve_rope(self.rope, self.ropes)  # validates, listing valid choices
        if not rope.custom and not isinstance(self.rope, RopeParams):
            object.__setattr__(self, "rope", rope.id)
        if self.settle_s is not None:
            check_nonnegative("settle_s", self.settle_s)
        if not isinstance(self.settle, SettleParams):
            raise ConfigError("settle", f"must be SettleParams, got {type(self.settle).__name__}")
        if not isinstance(self.twist, bool):
            raise ConfigError("twist", f"must be true or false, got {self.twist!r}")
        if not isinstance(self.bend_friction, BendFrictionParams):
            raise ConfigError(
                "bend_friction",
                f"must be BendFrictionParams, got {type(self.bend_friction).__name__}",
            )
        if not isinstance(self.aero, AeroParams):
            raise ConfigError("aero", f"must be AeroParams, got {type(self.aero).__name__}")
        check_nonnegative("brake_s", self.brake_s)
        check_positive("truth_rate_hz", self.truth_rate_hz)

    @property
    def rope_params(self) -> RopeParams:
        """The rope."""
        return resolve_rope(self.rope, self.ropes)

    @property
    def settle_rule(self) -> SettleParams:
        """The settle in force: ``settle``, or a fixed wait of ``settle_s``."""
        return self.settle if self.settle_s is None else SettleParams.fixed(self.settle_s)


__all__ = ["LabParams", "VariationParams"]

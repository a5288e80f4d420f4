"""Record a demonstration's stored motion again in today's lab, without searching again.

A demonstration stores the motion that made it: a hand demonstration its 23 motion numbers
(``motion``), a robot demonstration its command (``command_knots``, ``command_T``). When the
lab changes in a way that should not change what that motion does (a faster solve of the same
equations, say), its recording no longer replays bit for bit; this plays the stored motion
once more, nominally, records it exactly as the search's recorder did (same capture noise
seeds), keeps every other field of the metadata (the search's record among them), and runs
the varied check again:

* hand: ``check_repeats`` varied replays of seed ``metadata.seed``
  (:func:`flyknot_sim.hand_replay.replay`), stored as ``check``;
* robot: the command's lab trials at lab seeds ``confirm .. confirm + check_repeats - 1``
  (the robot search's fresh check, :class:`flyknot_tools.robot_demo.CommandSearchConfig`),
  stored as ``check``.

A motion that no longer ties a knot in its nominal trial is refused (it must be searched
again): :class:`flyknot.errors.FlyknotError`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, FlyknotError, check_int

RECORDER_KEYS = (
    "generator",
    "generator_version",
    "variant",
    "seed",
    "motion",
    "motion_start",
    "motion_duration",
    "hand",
    "hand_frame",
    "mocap",
    "settle_outcome",
    "knot_any",
    "settle_fraction",
    "mujoco",
    "rope",
    "simulation",
)
"""Metadata a hand demonstration's recorder writes itself (:func:`make_demonstration`)."""


@dataclass(frozen=True)
class Rerecorded:
    """A demonstration recorded again.

    Attributes:
        demo: The new demonstration.
        kind: ``hand`` or ``robot``.
        t_c_before: The stored recording's t_c [s].
        knots: Knots in the varied check.
        repeats: Trials of the varied check.
    """

    demo: Demonstration
    kind: str
    t_c_before: float
    knots: int
    repeats: int

    def summary(self) -> dict[str, Any]:
        """Plain numbers for the CLI."""
        return {
            "kind": self.kind,
            "t_c_before": round(self.t_c_before, 4),
            "t_c": round(self.demo.t_c, 4),
            "check": f"{self.knots}/{self.repeats}",
        }


def _hand(demo: Demonstration, check_repeats: int) -> tuple[Demonstration, int]:
    from flyknot_sim.hand_motion import KnotMotion
    from flyknot_sim.hand_replay import hand_from_demo, replay
    from flyknot_sim.mocap import MocapParams
    from flyknot_tools.hand_demos.synthesis import make_demonstration

    meta = demo.metadata
    extra = {k: v for k, v in meta.items() if k not in RECORDER_KEYS}
    new, trial = make_demonstration(
        KnotMotion.from_dict(meta["motion"]),
        variant=meta["variant"],
        seed=int(meta["seed"]),
        hand=hand_from_demo(demo, demo.rope, vary=False),
        mocap_params=MocapParams(**meta["mocap"]),
        extra=extra,
    )
    if trial.knot != "trefoil":
        raise FlyknotError(
            f"the stored motion ends {trial.knot} in today's lab: search it again "
            "(flyknot-tools demo synthesize)"
        )
    knots = 0
    if check_repeats:
        knots = replay(new, repeats=check_repeats, seed=int(meta["seed"])).knots
        m = dict(new.metadata)
        m["check"] = {"repeats": check_repeats, "seed": int(meta["seed"]), "knots": knots}
        new = replace(new, metadata=m)
    return new, knots


def _robot(demo: Demonstration, check_repeats: int) -> tuple[Demonstration, int]:
    from flyknot_sim.lab import LabParams, SimLab
    from flyknot_tools.robot_demo import CommandSearchConfig, record_demonstration
    from learner.bezier import BezierCommand

    meta = demo.metadata
    knots_, T = np.asarray(meta["command_knots"], dtype=float), float(meta["command_T"])
    keep = {"generator", "source", "command_T", "command_knots", "knot"}
    extra = {k: v for k, v in meta.items() if k not in keep}
    new = record_demonstration(knots_, T, rope=demo.rope, metadata=extra)
    if new.metadata["knot"] != "trefoil":
        raise FlyknotError(
            f"the stored command ends {new.metadata['knot']} in today's lab: search it again "
            "(flyknot-tools demo robot)"
        )
    first = CommandSearchConfig().confirm
    seeds = range(first, first + check_repeats)
    command = BezierCommand(knots_, T).joint_command()
    knots = sum(SimLab(LabParams(rope=demo.rope, seed=s)).run(command).succeeded for s in seeds)
    if check_repeats:
        m = dict(new.metadata)
        m["check"] = {"repeats": check_repeats, "lab_seeds": [seeds.start, seeds.stop - 1],
                      "knots": int(knots)}  # fmt: skip
        new = replace(new, metadata=m)
    return new, int(knots)


def rerecord(demo: Demonstration, check_repeats: int = 20) -> Rerecorded:
    """Record ``demo``'s stored motion again in today's lab (module docstring).

    Raises:
        ConfigError: The demonstration stores no motion.
        FlyknotError: The motion no longer ties a knot in its nominal trial.
    """
    check_int("check_repeats", check_repeats, 0)
    meta = demo.metadata
    if isinstance(meta.get("motion"), dict):
        new, knots = _hand(demo, check_repeats)
        kind = "hand"
    elif "command_knots" in meta and "command_T" in meta:
        new, knots = _robot(demo, check_repeats)
        kind = "robot"
    else:
        raise ConfigError(
            "demo", "stores no motion to record again (valid: a hand motion or a robot command)"
        )
    return Rerecorded(new, kind, float(demo.t_c), knots, check_repeats)

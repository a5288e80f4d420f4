"""Lock-up: a link chain thrown as in a flying knot never bends past the angle at which its
links jam.

Real links turn about each other as hinges on their end wires and jam only when the
next-but-one links meet (``assets/ropes.toml``, rope 6: 140.7 deg between two of the lab's
segments). The lab holds that angle with a limit on the chord of every two segments
(:func:`flyknot_sim.rope.lock_chord`); the case throws the chain with the flying-knot hand
motion of :mod:`~flyknot_tools.rope_validate.rest_after_motion`, holds still, and takes the
largest turning angle between segments at every step.
"""

from __future__ import annotations

import numpy as np

from flyknot.geometry import turning_angles
from flyknot_tools.rope_validate.common import CaseResult, RopeModel, hung, result
from flyknot_tools.rope_validate.rest_after_motion import Throw, hanging_at_home

LOCK_TOL_DEG = 1.0
"""How far past its lock-up angle a chain's joint may turn [deg]: the constraint is soft
(MuJoCo's solref), as a real link's wire gives a little."""


def lock_up(rope: RopeModel, throw: Throw | None = None, wait_s: float = 2.0) -> CaseResult:
    """The throw (default :class:`Throw`'s flying-knot motion) and ``wait_s`` of holding still;
    expected: no turn between two segments past the rope's ``lock_angle`` +
    :data:`LOCK_TOL_DEG` (the joint at the held end left out: its first segment lies between
    the two held vertices). A rope without links (``lock_angle`` 0) is reported, not judged."""
    p = rope.params
    throw = Throw() if throw is None else throw
    b = hung(rope, hanging_at_home(p))
    path = throw.path(b.dt)
    largest = [0.0, 0.0]  # [deg]: during the throw, during the wait

    def probe(phase: int):
        def take(bench) -> None:
            turn = float(np.degrees(turning_angles(bench.vertices())[1:].max()))
            largest[phase] = max(largest[phase], turn)

        return take

    b.run(throw.duration, path, b.dt, probe(0))
    b.run(wait_s, path, b.dt, probe(1))
    worst = max(largest)
    measured = {
        "throw": throw.label(),
        "lock_angle_deg": p.lock_angle,
        "max_turn_throw_deg": largest[0],
        "max_turn_wait_deg": largest[1],
    }
    lock = p.lock_angle
    detail = (
        f"largest turn between segments {largest[0]:.1f} deg in the throw, {largest[1]:.1f} "
        f"deg in the {wait_s:g} s after"
        + (f" (lock-up {lock:g} deg)" if lock > 0 else " (no links: not judged)")
    )
    return result(
        "lock_up",
        rope,
        lock > 0 and worst <= lock + LOCK_TOL_DEG,
        f"no turn past the links' lock-up angle + {LOCK_TOL_DEG:g} deg",
        "links jam when the next-but-one links meet (their geometry, assets/ropes.toml)",
        measured,
        detail,
        applies=lock > 0,
    )


__all__ = ["LOCK_TOL_DEG", "lock_up"]

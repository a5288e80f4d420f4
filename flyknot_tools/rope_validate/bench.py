"""The validation bench: the rope-study harness with the lab's passive forces on the rope.

A case builds a :class:`Bench` (holder on slides and hinges, the rope as the lab builds it,
optionally a fixed rod, a pinned free end or no gravity) and steps it the way the lab's trial
does: air drag recomputed every :data:`flyknot_sim.aero.DRAG_HOLD_S`, the frictional bending
couple solved at every step, then ``mj_step``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from flyknot_sim.aero import DRAG_HOLD_S, AeroParams, RopeDrag
from flyknot_sim.bend_friction import RopeBendFriction
from flyknot_sim.rope_table import RopeParams, SimSettings
from flyknot_tools.rope_study.harness import HOLDER_JOINTS, Harness, build_harness, place_vertices

__all__ = ["Bench", "HolderPath", "RopeModel"]

HolderPath = Callable[[float], tuple[np.ndarray, np.ndarray]]
"""t [s] -> (holder slide offsets (3,) [m], their rates (3,) [m/s]), the hinges staying at
zero; or the slides then the hinges b, a, c (6,) [m, rad] and their rates (6,) [m/s, rad/s]
(:data:`~flyknot_tools.rope_study.harness.HOLDER_JOINTS`)."""


@dataclass(frozen=True)
class RopeModel:
    """What the suite validates: a rope's parameters and the lab's air drag.

    Attributes:
        params: The rope (its ``bend_hysteresis`` sets the frictional couple).
        aero: Air drag as the lab applies it (the rope's own ``cd`` when it has one).
        settings: The simulation settings (None: ``[simulation]`` of the rope file).
        label: Name of this variant in tables.
    """

    params: RopeParams
    aero: AeroParams = field(default_factory=AeroParams)
    settings: SimSettings | None = None
    label: str = "default"

    @property
    def drag(self) -> AeroParams:
        """The drag settings with the rope's own cross-flow coefficient, as the labs use."""
        if self.params.cd is None:
            return self.aero
        from dataclasses import replace

        return replace(self.aero, cd=self.params.cd)


class Bench:
    """A harness stepped with the lab's rope forces.

    Attributes:
        harness: The compiled scene (``model``, ``data``, ``rope``).
        t: Simulated time since the bench was built [s].
    """

    def __init__(self, rope: RopeModel, *, home: Sequence[float], axis: Sequence[float], **kw):
        """Build the scene (``kw``: :func:`flyknot_tools.rope_study.harness.build_harness`'s
        ``rod``, ``gravity``, ``free_end_at``, ``timestep``)."""
        p = rope.params
        self.harness: Harness = build_harness(p, home=home, axis=axis, settings=rope.settings, **kw)
        bound = self.harness.rope
        self._drag = RopeDrag(bound, rope.drag)
        self._bend = RopeBendFriction(bound, p.frictional_couple)
        self._drag_every = max(1, round(DRAG_HOLD_S / self.harness.model.opt.timestep))
        self._j = 0

    @property
    def model(self) -> mujoco.MjModel:
        """The compiled model."""
        return self.harness.model

    @property
    def data(self) -> mujoco.MjData:
        """The simulation state."""
        return self.harness.data

    @property
    def dt(self) -> float:
        """The step [s]."""
        return float(self.model.opt.timestep)

    @property
    def t(self) -> float:
        """Simulated time since the bench was built [s]."""
        return self._j * self.dt

    def place(self, x: np.ndarray) -> None:
        """Put the rope's vertices at ``x`` (n + 1, 3) [m], at rest."""
        place_vertices(self.harness, x)

    def vertices(self) -> np.ndarray:
        """The centreline now, (n + 1, 3) [m]."""
        return self.harness.vertices()

    def step(self, path: HolderPath | None = None) -> None:
        """One step: the holder's targets at the step's start, the rope forces, ``mj_step``."""
        d = self.data
        if path is not None:
            q, qd = path(self.t)
            d.ctrl[0 : 2 * len(q) : 2] = q
            d.ctrl[1 : 2 * len(q) : 2] = qd
        if self._j % self._drag_every == 0:
            self._drag.apply(d)
        self._bend.apply(d)
        mujoco.mj_step(self.model, d)
        self._j += 1

    def run(
        self,
        seconds: float,
        path: HolderPath | None = None,
        every: float | None = None,
        probe: Callable[[Bench], None] | None = None,
    ) -> None:
        """Step for ``seconds``; call ``probe(self)`` every ``every`` seconds (and at the end)."""
        n = round(seconds / self.dt)
        k = max(1, round(every / self.dt)) if every else 0
        for i in range(1, n + 1):
            self.step(path)
            if probe is not None and k and i % k == 0:
                probe(self)
        if probe is not None and (not k or n % k):
            probe(self)

    def holder_force(self) -> np.ndarray:
        """The force the holder exerts on the rope (3,) [N]: minus the constraint force the
        rope's hold puts on the holder's slides.

        Not the servos' force: while the holder moves, the position servo's reported force
        carries kp v dt more (the holder is one step behind the moving target: 0.4 N at
        2 cm/s and 1 ms) than the hold passes to the rope; over a frictionless rod it read
        4.6x the load at 2 cm/s, this reads 0.99-1.00x at any speed."""
        m, d = self.model, self.data
        dofs = [int(m.jnt_dofadr[m.joint(name).id]) for name in HOLDER_JOINTS[:3]]
        return -np.asarray(d.qfrc_constraint[dofs], dtype=float)

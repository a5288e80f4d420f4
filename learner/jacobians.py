"""Where an update's Jacobian M(t_c) = dx(t_c)/dkappa comes from: a registry.

The inverse-model QP (:mod:`learner.inverse_qp`) needs M(t_c) (66, 80): how the rope state
at the critical point moves with the knots. Each entry of :data:`JACOBIANS` says where it
comes from; a run names one with the update option ``jacobian``:

* ``"model"`` (the paper's): the learner's rope model linearised about the measured joints
  (:func:`learner.system_model.linearise`), computed inside :func:`learner.update.ilc_update`.
* ``"oracle"``: the cell's own Jacobian, measured by finite differences of the rope state at
  t_c over the knots, played without trial-to-trial variation. It bounds what any
  model-based ILC can do with this objective and QP. Only a simulated lab can replay a
  command without variation, so the cell's side supplies it (the application layer's
  ``flyknot_app.oracle``); the learner sees an opaque :data:`JacobianProvider` and nothing
  of the simulator.

Adding a source is one :class:`JacobianKind` and one line in :data:`JACOBIANS`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError

JacobianProvider = Callable[[np.ndarray, float], np.ndarray]
"""``provider(knots (10, 8), T [s]) -> M(t_c) (66, 80)``: a Jacobian measured elsewhere."""


@dataclass(frozen=True)
class JacobianKind:
    """One source of M(t_c).

    Attributes:
        name: The option's value.
        description: One line for ``--help`` and reports.
        needs_provider: The run must hand :func:`learner.ilc.learn` a
            :data:`JacobianProvider` (a measurement outside the learner).
    """

    name: str
    description: str
    needs_provider: bool


JACOBIANS: dict[str, JacobianKind] = {
    k.name: k
    for k in (
        JacobianKind("model", "the learner's rope model, linearised (the paper's)", False),
        JacobianKind(
            "oracle",
            "the simulated lab's own, by finite differences without variation (a measuring "
            "stick, simulated lab only)",
            True,
        ),
    )
}
"""Every source of the update's Jacobian, by the name the ``jacobian`` option gives."""


def jacobian_kind(name: object) -> JacobianKind:
    """The registered source ``name``; the error lists the valid ones."""
    if not isinstance(name, str) or name not in JACOBIANS:
        raise ConfigError("jacobian", f"unknown Jacobian source {name!r}", sorted(JACOBIANS))
    return JACOBIANS[name]


def provided_jacobian(
    name: str, provider: JacobianProvider | None, knots: np.ndarray, T: float
) -> np.ndarray | None:
    """M(t_c) for ``knots`` from the source ``name``: None for the model (the update
    linearises it), else the provider's measurement.

    Raises:
        ConfigError: The source needs a provider and the run has none.
    """
    kind = jacobian_kind(name)
    if not kind.needs_provider:
        return None
    if provider is None:
        raise ConfigError(
            "jacobian", f"{name!r} needs a cell that can measure it ({kind.description})"
        )
    return np.asarray(provider(np.asarray(knots, dtype=float), float(T)), dtype=float)


__all__ = ["JACOBIANS", "JacobianKind", "JacobianProvider", "jacobian_kind", "provided_jacobian"]

"""Where an update's Jacobian M(t) = dx(t)/dkappa comes from: a registry.

The inverse-model QP (:mod:`learner.inverse_qp`) needs M(t) (66, 80) at each time t its
objective fits (t_c, and the launch t_l for ``objective = "launch"``): how the rope state
there moves with the knots. Each entry of :data:`JACOBIANS` says where it comes from; a run
names one with the update option ``jacobian``:

* ``"model"`` (the paper's): the learner's rope model linearised about the measured joints
  (:func:`learner.system_model.linearise`), computed inside :func:`learner.update.ilc_update`.
* ``"secant"``: the model's, corrected from the measured trials by Broyden's rank-one update
  (:class:`SecantCorrection`): M_k = M_model(kappa_k) + C_k, with C learned from how the
  measured critical state moved between consecutive trials.
* ``"oracle"``: the cell's own Jacobian, measured by finite differences of the rope state at
  t_c over the knots, played without trial-to-trial variation. It bounds what any
  model-based ILC can do with this objective and QP. Only a simulated lab can replay a
  command without variation, so the cell's side supplies it (the application layer's
  ``flyknot_app.diagnose.oracle``); the learner sees an opaque :data:`JacobianProvider` and nothing
  of the simulator.

Adding a source is one :class:`JacobianKind` and one line in :data:`JACOBIANS`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError

JacobianProvider = Callable[[np.ndarray, float, tuple[float, ...]], dict[float, np.ndarray]]
"""``provider(knots (10, 8), T [s], times (P,) [s]) -> {t: M(t) (66, 80)}``: Jacobians
measured elsewhere, one per time."""


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
    learns: bool = False
    """The source corrects the model from the measured trials (it has a memory)."""


JACOBIANS: dict[str, JacobianKind] = {
    k.name: k
    for k in (
        JacobianKind("model", "the learner's rope model, linearised (the paper's)", False),
        JacobianKind(
            "secant",
            "the rope model's, corrected by Broyden updates from the measured trials",
            False,
            learns=True,
        ),
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
    name: str,
    provider: JacobianProvider | None,
    knots: np.ndarray,
    T: float,
    times: tuple[float, ...],
) -> dict[float, np.ndarray] | None:
    """{t: M(t)} for ``knots`` at the objective's fitted ``times`` [s] from the source
    ``name``: None for the model's sources (the update linearises it), else the provider's
    measurement.

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
    measured = provider(np.asarray(knots, dtype=float), float(T), tuple(times))
    return {float(t): np.asarray(M, dtype=float) for t, M in measured.items()}


class SecantCorrection:
    """The secant source's memory: C of M_k = M_model(kappa_k) + C_k (Broyden, 1965).

    After trial k+1 is measured, with dkappa = kappa_{k+1} - kappa_k (80,) and
    de = e_{k+1} - e_k (66,) the change of the measured critical error:

        C_{k+1} = C_k + (de - M_k dkappa) dkappa^T / (dkappa^T dkappa)          (66, 80)

    so that the corrected M_{k+1} maps the last measured step exactly onto the measured
    change (the secant condition), changing nothing along directions orthogonal to it. The
    update (:func:`learner.update.ilc_update`) hands it only errors measured at t_c.
    """

    def __init__(self) -> None:
        self.C = np.zeros((66, 80))
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        """(kappa_k (80,), e_k (66,), M_k (66, 80)) of the last trial it learned from."""

    def corrected(
        self, knots: np.ndarray, M_model: np.ndarray, err: np.ndarray, *, learn: bool = True
    ) -> np.ndarray:
        """M_model + C for the trial of ``knots`` (10, 8) whose measured error is ``err``;
        with ``learn``, C first takes the secant step from the last trial to this one."""
        kappa, err = np.asarray(knots, dtype=float).ravel(), np.asarray(err, dtype=float)
        if learn and self.last is not None:
            k0, e0, M0 = self.last
            dk = kappa - k0
            norm2 = float(dk @ dk)
            if norm2 > 0.0:
                self.C = self.C + np.outer((err - e0) - M0 @ dk, dk) / norm2
        M = np.asarray(M_model, dtype=float) + self.C
        if learn:
            self.last = (kappa, err.copy(), M)
        return M


__all__ = [
    "JACOBIANS",
    "JacobianKind",
    "JacobianProvider",
    "SecantCorrection",
    "jacobian_kind",
    "provided_jacobian",
]

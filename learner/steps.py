"""How far an update moves the command: the step rules, a registry.

The paper moves the command by the whole update, kappa_{k+1} = kappa_k - alpha dkappa_k with a
fixed gain alpha (``step = "gain"``). ``step = "damped"`` is Levenberg-Marquardt on the
measured critical cost c_k = ||x_k(t_c) - x_demo(t_c)||_Q^2, with the QP's control weight as
the damping lambda (:class:`learner.inverse_qp.InverseModelWeights` ``w_control``):

    if c_k < c_best:                 best <- k,  lambda <- max(lambda / shrink, smallest)
                                     kappa_{k+1} = kappa_k - dkappa(kappa_k; lambda_k)
    elif c_k <= (1 + nu) c_best:     lambda unchanged (a rise within the noise)
                                     kappa_{k+1} = kappa_k - dkappa(kappa_k; lambda_k)
    else:                            lambda <- lambda * grow
                                     kappa_{k+1} = kappa_best - dkappa(kappa_best; lambda)

with nu the trial-to-trial noise of the critical cost (``damping.noise``, relative; 0: every
rise is a failed step). One command's cost varies from play to play with the lab's variation,
so the lowest cost measured is partly luck: without the band, every later trial near the noise
floor reads as a rise, and lambda grows until the steps vanish.

A trial that measured nothing after a best exists (the cell refused or faulted on its
command, or the markers were lost before t_c) is a step that failed as a raised cost is:
c_k = inf, the second line. (Before any best, the gain rule's halfway back or stop rules.)

where dkappa(kappa; lambda) is the inverse-model QP's solution about trial kappa's record with
w_control = lambda. A step that raised the measured cost is thus taken back, and the next one
from the best command is shorter; steps that lower it grow. The rule sees only the measured
costs (as a real lab's would), never the simulator.

:class:`Damping` is the rule's memory; the loop and a resumed run feed it the same ledger
lines, so both reach the same state.

Adding a rule is one :class:`StepKind` and one line in :data:`STEPS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError, check_nonnegative, check_positive


@dataclass(frozen=True)
class StepKind:
    """One step rule: its option value and a line for reports."""

    name: str
    description: str


STEPS: dict[str, StepKind] = {
    k.name: k
    for k in (
        StepKind("gain", "kappa - gain dkappa, a fixed gain (the paper's)"),
        StepKind(
            "damped", "Levenberg-Marquardt on the measured cost: back to the best when it rose"
        ),
    )
}
"""Every step rule, by the name the ``step`` option gives."""


def step_kind(name: object) -> StepKind:
    """The registered rule ``name``; the error lists the valid ones."""
    if not isinstance(name, str) or name not in STEPS:
        raise ConfigError("step", f"unknown step rule {name!r}", sorted(STEPS))
    return STEPS[name]


@dataclass(frozen=True)
class DampingParams:
    """The damped step's settings (``step = "damped"``).

    Attributes:
        start: lambda of the first update (the QP's w_control) [1/rad^2]. 0.25: rope 1 from
            ``fast-paced`` with the scenarios' learner ties at trial 2 in 9 of 10 lab seeds
            (0-4 chose it, 5-9 checked it); 0.1, 0.5 and 1 give medians of 5, 6 and 8 trials
            over seeds 0-4 (docs/measuring-sticks.md).
        shrink: lambda's divisor after a trial that lowered the best cost (> 1).
        grow: lambda's factor after one that did not (> 1).
        smallest: lambda's lower bound [1/rad^2].
        noise: nu, the relative rise of the measured cost that still counts as the same cost
            (the trial-to-trial noise floor, >= 0; 0: every rise is a failed step). One
            command's critical cost over the lab's variation: 0.104 +- 0.016, a relative
            standard deviation of 0.15 (the reachable floor's command on ``fast-paced``, 12
            plays; docs/measuring-sticks.md), so 0.3 is two of them.
        common_time: Weigh two trials whose markers were lost before t_c at one time, the
            earlier of their critical points t_eff (each cost refitted there from its
            record), not each at its own.
    """

    start: float = 0.25
    shrink: float = 2.0
    grow: float = 4.0
    smallest: float = 1e-3
    noise: float = 0.0
    common_time: bool = False

    def __post_init__(self) -> None:
        for name in ("start", "smallest"):
            check_positive(f"damping.{name}", getattr(self, name))
        check_nonnegative("damping.noise", self.noise)
        if not isinstance(self.common_time, (bool, np.bool_)):
            raise ConfigError("damping.common_time", f"must be a bool, got {self.common_time!r}")
        object.__setattr__(self, "common_time", bool(self.common_time))
        for name in ("shrink", "grow"):
            value = getattr(self, name)
            check_positive(f"damping.{name}", value)
            if value <= 1:
                raise ConfigError(f"damping.{name}", f"must be > 1, got {value!r}")


class Damping:
    """The damped step's memory: lambda and the best measured trial (module docstring)."""

    def __init__(self, params: DampingParams):
        self.params = params
        self.lam = params.start
        self.best: tuple[float, int] | None = None
        """(cost, trial) of the lowest measured cost so far."""

    def observe(
        self,
        cost: float | None,
        trial: int,
        against: float | None = None,
        own: float | None = None,
    ) -> bool | None:
        """Take trial ``trial``'s measured cost; return True when the full step is taken from
        it (a new best, lambda shrunk, or a rise within the noise band, lambda unchanged),
        False when it is not (step again from the best, more damped; a cost of +inf: a step
        that measured nothing), None when there is no cost to weigh (lambda unchanged).
        ``against``: the best trial's cost at the time ``cost`` was taken (the common time;
        default its own); ``own``: the trial's cost at its own time, kept as the best's
        (default ``cost``)."""
        if cost is None:
            return None
        p = self.params
        if cost == math.inf:  # a step that measured nothing: never the best
            self.lam *= p.grow
            return False
        best = None if self.best is None else (self.best[0] if against is None else against)
        if best is None or cost < best:
            self.best = (float(cost if own is None else own), int(trial))
            self.lam = max(self.lam / p.shrink, p.smallest)
            return True
        if p.noise > 0 and cost <= (1.0 + p.noise) * best:
            return True
        self.lam *= p.grow
        return False

    def is_best(self, trial: int) -> bool:
        """Whether trial ``trial`` holds the lowest measured cost."""
        return self.best is not None and self.best[1] == int(trial)


__all__ = ["STEPS", "Damping", "DampingParams", "StepKind", "step_kind"]

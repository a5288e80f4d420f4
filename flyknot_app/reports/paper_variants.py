"""The variants of ``flyknot paper``: the paper's experiments run again with a few options
changed (``flyknot paper --variant NAME``), each a column beside the scenarios' own in the
results table; :data:`VARIANTS` by name."""

from __future__ import annotations

from dataclasses import dataclass

from flyknot.errors import ConfigError
from flyknot_app.learner_settings import FOLLOW_WEIGHTS, PAPER_SETTINGS
from learner.inverse_qp import InverseModelWeights

NO_FOLLOW_THROUGH = (
    "follow_through=false",
    "damping.noise=0",
    "damping.common_time=false",
    "converged_knot=false",
    *(f"weights.{w}={getattr(InverseModelWeights(), w):g}" for w in FOLLOW_WEIGHTS),
)
"""The learner options of the ``no-follow-through`` variant: the scenarios' learner without
the follow-through term, the damped step's noise band and its common time, stopping at the
first knot (the follow-through weights back at the paper's, which the term's absence leaves
unused)."""


PAPER_VELOCITY_WEIGHT = 0.00375
"""The ``paper-velocity`` variant's w_crit_vel [s^2/m^2], the paper's: the critical cost's marker
velocities weighted as the position error they make in dt = sqrt(0.00375 / w_crit_pos) = 12 ms.
The scenarios' own is 0.1, dt = 63 ms: this lab's knot is decided 65-106 ms after the first
contact (``flyknot diagnose decided``, ``docs/measuring-sticks.md``)."""


@dataclass(frozen=True)
class Part:
    """Scenarios a variant runs for the results document, with ``--set`` pairs of their own
    (e.g. fewer repeats)."""

    scenarios: tuple[str, ...]
    sets: tuple[str, ...] = ()


@dataclass(frozen=True)
class Variant:
    """The paper's experiments run again with a few options changed, into ``OUT/<name>``; the
    table puts each run's results beside the scenarios' own, under ``label``.

    Attributes:
        name: ``flyknot paper --variant NAME`` and the directory under ``OUT``.
        overrides: ``--set`` pairs laid over the scenarios' defaults, under each run's own
            fields and the user's ``--set``.
        label: The column heads' prefix in the table.
        skips: Scenarios the variant does not apply to (run without it or not at all).
        results: What ``flyknot paper --all`` runs of it for ``docs/results.md`` (none: the
            variant is run by hand only).
    """

    name: str
    overrides: tuple[str, ...]
    label: str
    skips: tuple[str, ...] = ()
    results: tuple[Part, ...] = ()


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("paper-settings", PAPER_SETTINGS, "with the paper's learner settings"),
        Variant(
            "robot-demo",
            ("demo=robot",),
            "from the robot demonstration (a command searched in this lab, not the paper's "
            "protocol)",
            skips=("05-demos",),  # its runs name their demonstrations
            results=(
                Part(("02-objectives", "03-ropes", "07-sensitivity")),
                Part(("01-tracking", "04-success-rate"), ("repeats=8",)),
            ),
        ),
        Variant(
            "oracle",
            ("jacobian=oracle",),
            "the oracle learner (the same objective with the lab's own Jacobian, a measuring "
            "stick)",
            skips=("01-tracking", "02-objectives", "07-sensitivity"),  # no update / no model
            results=(Part(("03-ropes", "05-demos")),),
        ),
        Variant(
            "paper-velocity",
            (f"weights.w_crit_vel={PAPER_VELOCITY_WEIGHT:g}",),
            "with the paper's velocity weight (the critical point's marker velocities weighted "
            "as 12 ms of their position, w_crit_vel 0.00375)",
            skips=("01-tracking",),  # no update; run by hand (docs/measuring-sticks.md)
        ),
        Variant(
            "no-follow-through",
            NO_FOLLOW_THROUGH,
            "without the follow-through term, the noise band, the common time and the converged "
            "knot (learner options)",
            skips=("01-tracking",),  # no update
            results=(
                Part(("02-objectives", "03-ropes", "04-success-rate", "05-demos", "08-certainty")),
            ),
        ),
    )
}
"""The variants ``flyknot paper --variant`` runs, by name."""


def variant_kind(name: object) -> Variant:
    """The registered variant ``name``; the error lists the valid ones."""
    if not isinstance(name, str) or name not in VARIANTS:
        raise ConfigError("--variant", f"unknown variant {name!r}", list(VARIANTS))
    return VARIANTS[name]

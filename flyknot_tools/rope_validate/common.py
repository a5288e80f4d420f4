"""What the validation cases share: their result, the lab's frame, a hung rope."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flyknot_tools.rope_validate.bench import Bench, RopeModel

__all__ = ["DOWN", "HOME", "KNOT_MATERIALS", "UP", "CaseResult", "G", "hung", "result"]

G = 9.81
UP = np.array([0.0, 0.0, 1.0])
DOWN = -UP
HOME = np.array([0.0, 0.0, 1.5])


@dataclass(frozen=True)
class CaseResult:
    """One case on one rope.

    Attributes:
        case: Case name.
        rope: Rope id.
        variant: The rope model's label.
        passed: Whether the measured behaviour is the expected one.
        expected: The expectation for this material, in words.
        source: Why a real rope of this kind behaves so (publication or physical reason).
        measured: The numbers measured (name -> value).
        detail: One line with the numbers that decided.
        applies: False when no expectation holds for this material (then ``passed`` only
            says whether the generic expectation was met; the result is reported, not judged).
    """

    case: str
    rope: int | str
    variant: str
    passed: bool
    expected: str
    source: str
    measured: dict = field(default_factory=dict)
    detail: str = ""
    applies: bool = True

    def to_json(self) -> dict:
        """The result as plain data."""
        return {
            "case": self.case,
            "rope": self.rope,
            "variant": self.variant,
            "passed": self.passed,
            "expected": self.expected,
            "source": self.source,
            "measured": self.measured,
            "detail": self.detail,
            "applies": self.applies,
        }


KNOT_MATERIALS = ("cotton", "steel")
"""Materials whose knots are expected to hold: cords (friction between fibres) and chains
(links jam). For latex tubing no behaviour of a knot under a small load was found: its knot
cases are reported, not judged."""


def result(
    case, rope: RopeModel, passed, expected, source, measured, detail, applies=True
) -> CaseResult:
    """A :class:`CaseResult` of ``rope`` (its id and label filled in)."""
    return CaseResult(
        case,
        rope.params.id,
        rope.label,
        bool(passed),
        expected,
        source,
        measured,
        detail,
        bool(applies),
    )


def hung(rope: RopeModel, x: np.ndarray, **kw) -> Bench:
    """A bench whose holder sits where ``x[0]`` is held from above (tube pointing down)."""
    home = x[0] + UP * rope.params.clearance
    b = Bench(rope, home=home, axis=DOWN, **kw)
    b.place(x)
    return b

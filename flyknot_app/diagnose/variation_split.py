"""Which part of the lab's trial-to-trial variation decides a command's knot.

A command that ties in some varied plays and not in others sits where the lab's variation
decides. This plays it ``plays`` times with each component of
:class:`flyknot_sim.lab_params.VariationParams` alone (the others off), once with none (a
play without variation is the same every time) and ``plays`` times with all of them, each
play on its own lab seed, and counts the knots. A component that alone takes the knot away
as often as all of them together is where the knot is decided; when the smallest one (a
start delay of a few milliseconds) does, the command is on a knife edge that no learner
reading the rope state at t_c can move it off by a step it can measure.

Only a simulated lab can switch its variation off, so a run on a real cell is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace

import numpy as np

from flyknot.errors import ConfigError

COMPONENTS = ("rest_start", "servo_gain_rel", "start_delay_max_s", "sway_deg")
"""The variation's components, as :class:`VariationParams` fields."""


@dataclass(frozen=True)
class VariationSplit:
    """A command's verdict classes per variation setting.

    Attributes:
        classes: ``{setting: (class, ...)}``: ``"none"``, each component that the lab
            varies (its field name) and ``"all"``.
        seeds: The lab seeds of the varied plays, in play order.
    """

    classes: dict[str, tuple[str, ...]]
    seeds: tuple[int, ...]

    def knots(self, setting: str) -> int:
        """How many plays of ``setting`` tied."""
        return sum(c == "knot" for c in self.classes[setting])

    def to_json(self) -> dict:
        """The split as JSON values."""
        return {
            "classes": {k: list(v) for k, v in self.classes.items()},
            "knots": {k: self.knots(k) for k in self.classes},
            "seeds": list(self.seeds),
        }


def alone(variation, component: str):
    """``variation`` with only ``component`` left on (the others off: 0 or False).

    Raises:
        ConfigError: ``component`` is not a variation field (the valid ones listed).
    """
    off = _all_off(variation)
    if component not in off:
        raise ConfigError("component", f"unknown variation component {component!r}", list(off))
    off[component] = getattr(variation, component)
    return replace(variation, **off)


def _is_on(variation, component: str) -> bool:
    value = getattr(variation, component)
    return bool(value) if isinstance(value, bool) else value > 0.0


def split_variation(
    lab_params,
    play: Callable[[object], str],
    plays: int,
    seeds: Sequence[int] | None = None,
) -> VariationSplit:
    """The knots of one command per variation setting (module docstring).

    Args:
        lab_params: The lab (:class:`flyknot_sim.lab_params.LabParams`); its ``variation``
            says which components are on.
        play: ``play(lab_params) -> verdict class`` of one play of the command in that lab.
        plays: Varied plays per setting (>= 1).
        seeds: Lab seeds of the varied plays (default 1000 .. 1000 + plays - 1, seeds no
            learning run uses).

    Raises:
        ConfigError: ``plays`` < 1 or a wrong number of seeds.
    """
    if isinstance(plays, bool) or not isinstance(plays, int) or plays < 1:
        raise ConfigError("--plays", f"must be an integer >= 1, got {plays!r}")
    seeds = tuple(range(1000, 1000 + plays)) if seeds is None else tuple(seeds)
    if len(seeds) != plays:
        raise ConfigError("seeds", f"must be {plays} seeds, got {len(seeds)}")
    full = lab_params.variation
    settings = {"none": (replace(full, **_all_off(full)), seeds[:1])}
    for c in COMPONENTS:
        if _is_on(full, c):
            settings[c] = (alone(full, c), seeds)
    settings["all"] = (full, seeds)
    classes = {
        name: tuple(play(replace(lab_params, variation=v, seed=s)) for s in ss)
        for name, (v, ss) in settings.items()
    }
    return VariationSplit(classes, seeds)


def _all_off(variation) -> dict:
    return {
        f.name: (False if isinstance(getattr(variation, f.name), bool) else 0.0)
        for f in fields(variation)
    }


def lab_play(knots: np.ndarray, T: float) -> Callable[[object], str]:
    """``play(lab_params)``: the verdict class of one play of ``knots`` in a fresh lab
    (``"fault"`` when the play faulted)."""
    from flyknot_sim.lab import SimLab
    from learner.bezier import BezierCommand

    command = BezierCommand(np.asarray(knots, dtype=float), float(T)).joint_command()

    def play(lab_params) -> str:
        record = SimLab(lab_params).run(command)
        return "fault" if record.fault else record.verdict.klass

    return play


def format_split(split: VariationSplit) -> str:
    """One line per setting: its knots out of its plays and the classes of its misses."""
    lines = []
    for name, classes in split.classes.items():
        misses = sorted({c for c in classes if c != "knot"})
        tail = f" (misses: {', '.join(misses)})" if misses else ""
        label = "no variation" if name == "none" else f"{name} alone" if name != "all" else "all"
        lines.append(f"{label}: {split.knots(name)} of {len(classes)} tied{tail}")
    return "\n".join(lines)


__all__ = ["COMPONENTS", "VariationSplit", "alone", "format_split", "lab_play", "split_variation"]

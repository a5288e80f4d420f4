"""Which part of the lab's trial-to-trial variation decides a command's knot.

A command that ties in some varied plays and not in others sits where the lab's variation
decides. This plays it ``plays`` times with each component of
:class:`flyknot_sim.lab_params.VariationParams` alone (the others off), once with none (a
play without variation is the same every time) and ``plays`` times with all of them, each
play on its own lab seed, and counts the knots. A component that alone takes the knot away
as often as all of them together is where the knot is decided; when the smallest one (a
start delay of a few milliseconds) does, the command is on a knife edge that no learner
reading the rope state at t_c can move it off by a step it can measure.

Each setting also reports how far the variation moves the arm: a play's fingertip path spread
is the largest distance of its fingertip from the play without variation at the same tick,

    s = max_i ||p_i - p0_i||   [m],   p, p0: (n, 3) fingertip positions at the command's ticks,

whose median over the plays is what a lab compares with its own arm's repeatability.

Only a simulated lab can switch its variation off, so a run on a real cell is refused.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from flyknot.errors import ConfigError

COMPONENTS = ("rest_start", "servo_gain_rel", "start_delay_max_s", "sway_deg")
"""The variation's components, as :class:`VariationParams` fields."""


@dataclass(frozen=True)
class Play:
    """One play of the command: its verdict class (``"fault"`` when it faulted) and its
    fingertip positions at the command's ticks, (n, 3) [m]."""

    klass: str
    tip: np.ndarray


def path_spread(tip: np.ndarray, nominal: np.ndarray) -> float:
    """s = max_i ||p_i - p0_i|| [m] over the ticks both plays have; ``tip``, ``nominal``
    (n, 3) and (m, 3) [m]."""
    n = min(len(tip), len(nominal))
    return float(np.linalg.norm(np.asarray(tip)[:n] - np.asarray(nominal)[:n], axis=1).max())


@dataclass(frozen=True)
class VariationSplit:
    """A command's verdict classes and fingertip path spreads per variation setting.

    Attributes:
        classes: ``{setting: (class, ...)}``: ``"none"``, each component that the lab
            varies (its field name) and ``"all"``.
        seeds: The lab seeds of the varied plays, in play order.
        spread: ``{setting: (s, ...)}`` [m], each play's fingertip path spread
            (:func:`path_spread`) from the play without variation.
    """

    classes: dict[str, tuple[str, ...]]
    seeds: tuple[int, ...]
    spread: dict[str, tuple[float, ...]]

    def knots(self, setting: str) -> int:
        """How many plays of ``setting`` tied."""
        return sum(c == "knot" for c in self.classes[setting])

    def median_spread(self, setting: str) -> float:
        """The median fingertip path spread of ``setting``'s plays [m]."""
        return float(np.median(self.spread[setting]))

    def to_json(self) -> dict:
        """The split as JSON values (spreads in mm)."""
        return {
            "classes": {k: list(v) for k, v in self.classes.items()},
            "knots": {k: self.knots(k) for k in self.classes},
            "spread_mm": {k: [1e3 * x for x in v] for k, v in self.spread.items()},
            "median_spread_mm": {k: 1e3 * self.median_spread(k) for k in self.spread},
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
    play: Callable[[object], Play],
    plays: int,
    seeds: Sequence[int] | None = None,
) -> VariationSplit:
    """The knots and path spreads of one command per variation setting (module docstring).

    Args:
        lab_params: The lab (:class:`flyknot_sim.lab_params.LabParams`); its ``variation``
            says which components are on, and how much.
        play: ``play(lab_params) -> Play`` of one play of the command in that lab.
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
    played = {
        name: [play(replace(lab_params, variation=v, seed=s)) for s in ss]
        for name, (v, ss) in settings.items()
    }
    nominal = played["none"][0].tip
    return VariationSplit(
        {name: tuple(p.klass for p in ps) for name, ps in played.items()},
        seeds,
        {name: tuple(path_spread(p.tip, nominal) for p in ps) for name, ps in played.items()},
    )


def _all_off(variation) -> dict:
    """Every component off (a magnitude that is not a component, ``rest_scale``, kept)."""
    return {
        c: (False if isinstance(getattr(variation, c), bool) else 0.0)
        for c in COMPONENTS
        if hasattr(variation, c)
    }


def lab_play(knots: np.ndarray, T: float) -> Callable[[object], Play]:
    """``play(lab_params)``: one play of ``knots`` in a fresh lab (:class:`Play`)."""
    from flyknot_sim.lab import SimLab
    from learner.bezier import BezierCommand

    command = BezierCommand(np.asarray(knots, dtype=float), float(T)).joint_command()

    def play(lab_params) -> Play:
        record = SimLab(lab_params).run(command)
        klass = "fault" if record.fault else record.verdict.klass
        return Play(klass, record.fingertip_pos[: command.n])

    return play


def format_split(split: VariationSplit) -> str:
    """One line per setting: its knots out of its plays, the classes of its misses and the
    median fingertip path spread."""
    lines = []
    for name, classes in split.classes.items():
        misses = sorted({c for c in classes if c != "knot"})
        tail = f" (misses: {', '.join(misses)})" if misses else ""
        label = "no variation" if name == "none" else f"{name} alone" if name != "all" else "all"
        line = f"{label}: {split.knots(name)} of {len(classes)} tied{tail}"
        if name != "none":
            line += f"; fingertip path spread {1e3 * split.median_spread(name):.3g} mm (median)"
        lines.append(line)
    return "\n".join(lines)


__all__ = [
    "COMPONENTS",
    "Play",
    "VariationSplit",
    "alone",
    "format_split",
    "lab_play",
    "path_spread",
    "split_variation",
]

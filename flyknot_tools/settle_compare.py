"""An early end of the settle against the settle without it, trial by trial.

A demonstration's motion is played in its lab twice per trial, with the same variation: once
in the lab as it is and once with one early end of the settle off
(:data:`flyknot.rest.EARLY_ENDS`: the knot-set end, after which a knotted rope waits for rest
or the cap; or the held-unknot end, after which an unknotted rope that touches itself does).
The robot demonstration's command plays in :class:`flyknot_sim.lab.SimLab` (lab seeds
``seeds``), a hand demonstration's motion in the hand lab (replays ``seeds`` of variation
seed 0). Per trial: the verdict class both
ways, whether the rule ended the lab's settle, the settle [s] both ways, and the wall time
both ways. ``docs/performance.md`` has the measured tables.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError
from flyknot.rest import EARLY_ENDS, SettleParams

SETTLES = ("lab", "without")
"""The two settles compared: the lab's, and the same without the rule."""


def settles(rule: str) -> dict[str, SettleParams]:
    """The lab's settle and the same without ``rule`` (a key of
    :data:`flyknot.rest.EARLY_ENDS`)."""
    if rule not in EARLY_ENDS:
        raise ConfigError("rule", f"unknown rule {rule!r}", sorted(EARLY_ENDS))
    return {"lab": SettleParams(), "without": SettleParams().without(rule)}


@dataclass(frozen=True)
class Compared:
    """One trial played with both settles.

    Attributes:
        trial: Lab seed (robot command) or replay index (hand demonstration).
        klass: Verdict class per settle (None when the trial faulted or diverged).
        settle_s: Time from the end of the motion to the verdict per settle [s].
        wall_s: Wall time per settle [s].
        ended_early: The rule ended the lab's settle.
    """

    trial: int
    klass: dict[str, str | None]
    settle_s: dict[str, float | None]
    wall_s: dict[str, float]
    ended_early: bool

    @property
    def agree(self) -> bool:
        """Both settles gave the same verdict class."""
        return self.klass["lab"] == self.klass["without"]


def _robot(demo: Demonstration, rope: int, seed: int, rule: str) -> dict[str, Any]:
    from flyknot_sim.lab import LabParams, SimLab
    from learner.bezier import BezierCommand

    meta = demo.metadata
    command = BezierCommand(
        np.asarray(meta["command_knots"], dtype=float), float(meta["command_T"])
    ).joint_command()
    out = {}
    for name, settle in settles(rule).items():
        t0 = time.perf_counter()
        rec = SimLab(LabParams(rope=rope, seed=seed, settle=settle)).run(command)
        st = rec.metadata.get("settle") or {}
        klass = None if rec.verdict is None else rec.verdict.klass
        out[name] = (klass, st.get("settle_s"), time.perf_counter() - t0, bool(st.get(rule)))
    return out


def _hand(labs: dict[str, Any], motion, index: int, rule: str) -> dict[str, Any]:
    out = {}
    for name, lab in labs.items():
        t0 = time.perf_counter()
        trial = lab.run(motion, np.random.default_rng([0, index]))
        st = trial.settle or {}
        klass = None if trial.verdict is None else trial.verdict.klass
        out[name] = (klass, st.get("settle_s"), time.perf_counter() - t0, bool(st.get(rule)))
    return out


def compare_settles(
    demo: str = "robot", trials: range = range(10, 30), rope: int = 1, rule: str = "knot_set"
) -> list:
    """Play ``demo``'s motion with both settles (module docstring); one
    :class:`Compared` per trial, in order.

    Args:
        demo: A shipped demonstration's name (``robot`` or a hand demonstration).
        trials: Lab seeds (robot) or replay indices (hand).
        rope: The rope (robot command only; a hand demonstration replays on its own rope).
        rule: The early end compared (a key of :data:`flyknot.rest.EARLY_ENDS`).
    """
    settles(rule)  # the rule's name checked before anything is played
    path = DEMOS_DIR / f"{demo}.npz"
    if not path.is_file():
        names = sorted(p.stem for p in DEMOS_DIR.glob("*.npz"))
        raise ConfigError("demo", f"unknown demonstration {demo!r}", names)
    d = Demonstration.load(path)
    robot = "command_knots" in d.metadata
    labs, motion = None, None
    if not robot:
        from flyknot_sim.hand import HandLab
        from flyknot_sim.hand_replay import hand_from_demo, motion_from_demo

        motion = motion_from_demo(d)
        hand = hand_from_demo(d, d.rope)
        labs = {name: HandLab(replace(hand, settle=s)) for name, s in settles(rule).items()}
    out = []
    for i in trials:
        played = _robot(d, rope, i, rule) if robot else _hand(labs, motion, i, rule)
        out.append(
            Compared(
                trial=i,
                klass={k: v[0] for k, v in played.items()},
                settle_s={k: v[1] for k, v in played.items()},
                wall_s={k: v[2] for k, v in played.items()},
                ended_early=played["lab"][3],
            )
        )
    return out


def format_compared(rows: list[Compared], rule: str = "knot_set") -> str:
    """One line per trial and the totals (``rule``: the early end compared)."""
    head = f"{'trial':>5} {'verdict':>16} {'same':>5} {'early':>5} {'settle s':>14} {'wall s':>12}"
    lines = [head]
    for r in rows:
        s = r.settle_s
        settle = "/".join("-" if s[k] is None else f"{s[k]:.1f}" for k in SETTLES)
        wall = "/".join(f"{r.wall_s[k]:.1f}" for k in SETTLES)
        lines.append(
            f"{r.trial:>5} {r.klass['lab']!s:>16} {'yes' if r.agree else 'NO':>5} "
            f"{'yes' if r.ended_early else '-':>5} {settle:>14} {wall:>12}"
        )
    walls = {k: sum(r.wall_s[k] for r in rows) for k in SETTLES}
    lines.append(
        f"same verdict class in {sum(r.agree for r in rows)} of {len(rows)}; ended by {rule} "
        f"in {sum(r.ended_early for r in rows)}; wall time without / with it: "
        f"{walls['without'] / walls['lab']:.2f}x (settle s and wall s: with/without)"
    )
    return "\n".join(lines)

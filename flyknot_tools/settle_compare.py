"""The knot-set end of the settle against the settle without it, trial by trial.

A demonstration's motion is played in its lab twice per trial, with the same variation: once
in the lab as it is (:attr:`flyknot.rest.SettleParams.knot_set_s` on) and once with the
knot-set end off (a knotted rope then waits for rest or the cap). The robot demonstration's
command plays in :class:`flyknot_sim.lab.SimLab` (lab seeds ``seeds``), a hand
demonstration's motion in the hand lab (replays ``seeds`` of variation seed 0). Per trial:
the verdict class both ways, whether the knot set, the settle [s] both ways, and the wall
time both ways. ``docs/performance.md`` has the measured table.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError
from flyknot.rest import SettleParams

SETTLES = {"knot_set": SettleParams(), "no_knot_set": SettleParams(knot_set_s=None)}
"""The two settles compared: the lab's, and the same without the knot-set end."""


@dataclass(frozen=True)
class Compared:
    """One trial played with both settles.

    Attributes:
        trial: Lab seed (robot command) or replay index (hand demonstration).
        klass: Verdict class per settle (None when the trial faulted or diverged).
        settle_s: Time from the end of the motion to the verdict per settle [s].
        wall_s: Wall time per settle [s].
        knot_set: The lab's settle ended because the knot had set.
    """

    trial: int
    klass: dict[str, str | None]
    settle_s: dict[str, float | None]
    wall_s: dict[str, float]
    knot_set: bool

    @property
    def agree(self) -> bool:
        """Both settles gave the same verdict class."""
        return self.klass["knot_set"] == self.klass["no_knot_set"]


def _robot(demo: Demonstration, rope: int, seed: int) -> dict[str, Any]:
    from flyknot_sim.lab import LabParams, SimLab
    from learner.bezier import BezierCommand

    meta = demo.metadata
    command = BezierCommand(
        np.asarray(meta["command_knots"], dtype=float), float(meta["command_T"])
    ).joint_command()
    out = {}
    for name, settle in SETTLES.items():
        t0 = time.perf_counter()
        rec = SimLab(LabParams(rope=rope, seed=seed, settle=settle)).run(command)
        st = rec.metadata.get("settle") or {}
        klass = None if rec.verdict is None else rec.verdict.klass
        out[name] = (klass, st.get("settle_s"), time.perf_counter() - t0, bool(st.get("knot_set")))
    return out


def _hand(labs: dict[str, Any], motion, index: int) -> dict[str, Any]:
    out = {}
    for name, lab in labs.items():
        t0 = time.perf_counter()
        trial = lab.run(motion, np.random.default_rng([0, index]))
        st = trial.settle or {}
        klass = None if trial.verdict is None else trial.verdict.klass
        out[name] = (klass, st.get("settle_s"), time.perf_counter() - t0, bool(st.get("knot_set")))
    return out


def compare_settles(demo: str = "robot", trials: range = range(10, 30), rope: int = 1) -> list:
    """Play ``demo``'s motion with both settles (module docstring); one
    :class:`Compared` per trial, in order.

    Args:
        demo: A shipped demonstration's name (``robot`` or a hand demonstration).
        trials: Lab seeds (robot) or replay indices (hand).
        rope: The rope (robot command only; a hand demonstration replays on its own rope).
    """
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
        labs = {name: HandLab(replace(hand, settle=s)) for name, s in SETTLES.items()}
    out = []
    for i in trials:
        played = _robot(d, rope, i) if robot else _hand(labs, motion, i)
        out.append(
            Compared(
                trial=i,
                klass={k: v[0] for k, v in played.items()},
                settle_s={k: v[1] for k, v in played.items()},
                wall_s={k: v[2] for k, v in played.items()},
                knot_set=played["knot_set"][3],
            )
        )
    return out


def format_compared(rows: list[Compared]) -> str:
    """One line per trial and the totals."""
    lines = [f"{'trial':>5} {'verdict':>16} {'same':>5} {'set':>4} {'settle s':>14} {'wall s':>12}"]
    for r in rows:
        s = r.settle_s
        settle = "/".join("-" if s[k] is None else f"{s[k]:.1f}" for k in SETTLES)
        wall = "/".join(f"{r.wall_s[k]:.1f}" for k in SETTLES)
        lines.append(
            f"{r.trial:>5} {r.klass['knot_set']!s:>16} {'yes' if r.agree else 'NO':>5} "
            f"{'yes' if r.knot_set else '-':>4} {settle:>14} {wall:>12}"
        )
    walls = {k: sum(r.wall_s[k] for r in rows) for k in SETTLES}
    lines.append(
        f"same verdict class in {sum(r.agree for r in rows)} of {len(rows)}; knot set early in "
        f"{sum(r.knot_set for r in rows)}; wall time without / with the knot-set end: "
        f"{walls['no_knot_set'] / walls['knot_set']:.2f}x (settle s and wall s: with/without)"
    )
    return "\n".join(lines)

"""The knot cases: a loose overhand knot hung and swung, and a tightened one left hanging."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from flyknot.errors import check_nonnegative, check_positive
from flyknot.verdict import KNOT, TREFOIL, judge_centreline, tube_knot
from flyknot_sim.rope_table import RopeParams
from flyknot_tools.rope_study.crossings import count_crossings, overhand_knot_vertices
from flyknot_tools.rope_validate.bench import Bench, RopeModel
from flyknot_tools.rope_validate.common import DOWN, HOME, KNOT_MATERIALS, CaseResult, hung, result

__all__ = ["Swing", "knot_hold", "knot_hold_grid", "static_hold"]


# ----------------------------------------------------------------------------------------
# knot hold in a hung and swung rope
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Swing:
    """A sideways swing of the holder: x(t) = amplitude sin(2 pi f t) for whole cycles.

    Attributes:
        amplitude: [m] (0: the holder stays still).
        frequency: [Hz].
        seconds: Longest swing [s]; the swing runs floor(seconds f) whole cycles.
    """

    amplitude: float = 0.3
    frequency: float = 0.5
    seconds: float = 8.0

    def __post_init__(self) -> None:
        check_nonnegative("amplitude", self.amplitude)
        check_positive("frequency", self.frequency)
        check_positive("seconds", self.seconds)

    @property
    def duration(self) -> float:
        """The swing's length: whole cycles within ``seconds`` [s]."""
        if self.amplitude == 0:
            return self.seconds
        return math.floor(self.seconds * self.frequency + 1e-9) / self.frequency

    def path(self, start: float):
        """The holder path of this swing starting at time ``start`` [s]."""
        w = 2 * math.pi * self.frequency
        end = start + self.duration

        def at(t: float) -> tuple[np.ndarray, np.ndarray]:
            if self.amplitude == 0 or t < start or t >= end:
                return np.zeros(3), np.zeros(3)
            s = t - start
            return (
                np.array([self.amplitude * math.sin(w * s), 0.0, 0.0]),
                np.array([self.amplitude * w * math.cos(w * s), 0.0, 0.0]),
            )

        return at

    def label(self) -> str:
        """The swing in words."""
        if self.amplitude == 0:
            return "no swing"
        return f"+-{self.amplitude:g} m at {self.frequency:g} Hz"


def _loose_knot(p: RopeParams, tail: float, knot_length: float = 0.7) -> np.ndarray:
    return overhand_knot_vertices(p, knot_length, centre=(0.0, 0.0, 0.0), tail_below=tail) + HOME


def knot_hold(
    rope: RopeModel,
    tail: float = 0.1,
    swing: Swing = Swing(),
    hold_s: float = 2.0,
    check_every: float = 0.05,
) -> CaseResult:
    """A loose overhand knot (0.7 m of rope in the knot, ``tail`` below it) hangs ``hold_s``,
    the holder swings, then holds ``hold_s``; the knot is checked every ``check_every``.

    Passes when the knot is there at every check after the first hold (the end weight has
    pulled it in by then) and the rope never passed through itself (crossings between
    consecutive steps)."""
    p = rope.params
    b = hung(rope, _loose_knot(p, tail))
    path = swing.path(hold_s)
    types: list[str] = []
    crossings = [0]
    prev = [b.vertices()]
    every = max(1, round(check_every / b.dt))
    steps = [0]

    def probe(bench: Bench) -> None:  # every step: crossings need straight-line motion
        x = bench.vertices()
        crossings[0] += count_crossings(prev[0], x)
        prev[0] = x
        steps[0] += 1
        if steps[0] % every == 0:
            types.append(tube_knot(x, DOWN))

    b.run(hold_s, path, b.dt, probe)
    settled = types[-1]
    n_first = len(types)
    b.run(swing.duration + hold_s, path, b.dt, probe)
    after = types[n_first:]
    kept = sum(t == TREFOIL for t in after)
    final = judge_centreline(b.vertices(), DOWN)
    held = settled == TREFOIL and kept == len(after) and final.klass == KNOT
    return result(
        "knot_hold",
        rope,
        held and crossings[0] == 0,
        "an overhand knot with the end weight below it holds when the rope is swung",
        "the end weight pulls the knot in and friction between the strands holds it "
        "(Bayman, Am. J. Phys. 45 (1977) 185: a knot whose friction inequality holds stays "
        "tied; everyday experience of cords)",
        {
            "tail_m": tail,
            "swing": swing.label(),
            "after_hold": settled,
            "checks_with_knot": kept,
            "checks": len(after),
            "final": final.klass,
            "crossings": crossings[0],
        },
        f"tail {tail:g} m, {swing.label()}: knot at {kept}/{len(after)} checks, final "
        f"{final.klass}, crossings {crossings[0]}",
        applies=p.material in KNOT_MATERIALS,
    )


# ----------------------------------------------------------------------------------------
# static hold: a tightened knot under the end weight
# ----------------------------------------------------------------------------------------
def static_hold(
    rope: RopeModel, seconds: float = 60.0, tail: float = 0.2, tighten_s: float = 20.0
) -> CaseResult:
    """A loose knot hangs ``tighten_s`` (the end weight pulls it in: the heavier ends take
    ~20 s to tighten it), then ``seconds`` more. Rope slipping through the knot lowers the
    free end, so the slip is the change of the free end's height (averaged over 2 s, about a
    swing period, at both ends of the interval: a chain keeps swinging); it must stay within
    one rope diameter and the knot must stay."""
    p = rope.params
    b = hung(rope, _loose_knot(p, tail))

    window = 2.0

    def end_height(bench: Bench) -> float:
        zs: list[float] = []
        bench.run(window, every=0.01, probe=lambda bb: zs.append(float(bb.vertices()[-1, 2])))
        return float(np.mean(zs))

    b.run(max(tighten_s - window, 0.0))
    z0 = end_height(b)
    v0 = judge_centreline(b.vertices(), DOWN)
    b.run(max(seconds - window, 0.0))
    z1 = end_height(b)
    v1 = judge_centreline(b.vertices(), DOWN)
    both = v0.klass == KNOT and v1.klass == KNOT
    slip = z0 - z1
    held = both and abs(slip) <= p.diameter
    return result(
        "static_hold",
        rope,
        held,
        f"a knot pulled in by the end weight does not slip over {seconds:g} s",
        "static friction between the strands exceeds the end weight's pull on the knot "
        "(capstan friction of the wraps; Maddocks & Keller, SIAM J. Appl. Math. 47 (1987))",
        {"seconds": seconds, "start": v0.klass, "end": v1.klass, "slip_m": slip},
        f"knot {v0.klass} -> {v1.klass}, free end lowered {slip * 1e3:.1f} mm in {seconds:g} s "
        f"(limit one diameter, {p.diameter * 1e3:g} mm)",
        applies=p.material in KNOT_MATERIALS,
    )


def knot_hold_grid(
    rope: RopeModel,
    tails: Sequence[float] = (0.1, 0.2, 0.3),
    swings: Sequence[Swing] = (Swing(0.0), Swing(0.15, 0.7), Swing(0.3, 0.5)),
) -> list[CaseResult]:
    """:func:`knot_hold` over tails x swings."""
    return [knot_hold(rope, t, s) for t in tails for s in swings]

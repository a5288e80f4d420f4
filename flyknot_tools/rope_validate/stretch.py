"""Stretch: a rope hung from one end stretches under its weight and bounces as a spring does.

A rope of axial stiffness EA (``stretch_modulus``, :attr:`flyknot_sim.rope_table.RopeParams.
axial_stiffness`) hung straight down carries the tension T(s) = g (m_end + rho (L - s)) at
arc length s, so it lengthens by the integral of T / EA, and let go at its rest length it
bounces about that length as a spring with an end mass does. The case hangs the rope straight
at its rest length, lets it fall into its stretch and takes its length (the sum of its edges)
every 2 ms. An inextensible rope (``stretch_modulus`` 0) is reported, not judged.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from flyknot_sim.rope_table import RopeParams
from flyknot_tools.rope_validate.common import CaseResult, G, RopeModel, hung, result
from flyknot_tools.rope_validate.rest_after_motion import hanging_at_home

__all__ = ["STRETCH_TOL", "hung_stretch", "stretch"]

STRETCH_TOL = 0.10
"""Relative tolerance on the elongation and the period: the law takes the whole length as
stretching, where the model's first edge lies in the holder (1 of 30: -3 %) and its last, to
the end weight, is stiffer (``flyknot_sim.rope.stretch_solref``: -2 % on the tube)."""


def hung_stretch(p: RopeParams) -> tuple[float, float]:
    """The elongation and the period of the first stretch mode of a rope hung from one end.

        delta = g L (m_end + rho L / 2) / EA  [m]
        T = 2 pi L / (beta c),  c = sqrt(EA / rho),  beta tan(beta) = rho L / m_end  [s]

    delta integrates the tension g (m_end + rho (L - s)) over EA along the length; T is the
    first mode of a bar fixed at one end with a mass at the other (longitudinal waves, e.g.
    Timoshenko, "Vibration Problems in Engineering"; beta = pi / 2 without an end mass, and
    T -> 2 pi sqrt(L (m_end + rho L / 3) / EA), a spring with a third of its own mass, for a
    heavy end). Undefined (ZeroDivisionError) for an inextensible rope.
    """
    ea, L = p.axial_stiffness, p.length
    delta = G * L * (p.end_mass + p.density * L / 2) / ea
    ratio = p.mass / p.end_mass if p.end_mass > 0 else math.inf
    top = math.pi / 2 * (1 - 1e-12)
    beta = math.pi / 2 if math.isinf(ratio) else brentq(_mode, 0.0, top, args=(ratio,))
    return delta, 2 * math.pi * L / (beta * math.sqrt(ea / p.density))


def _mode(beta: float, ratio: float) -> float:
    """beta tan(beta) - ratio, the end-mass bar's first-mode equation (a root in (0, pi/2))."""
    return beta * math.tan(beta) - ratio


def _period(t: np.ndarray, x: np.ndarray) -> float:
    """Twice the mean time between the sign changes of ``x`` about zero [s] (NaN: too few)."""
    s = np.sign(x)
    crossings = t[1:][s[1:] != s[:-1]]
    return float(2 * np.diff(crossings).mean()) if len(crossings) >= 3 else math.nan


def stretch(rope: RopeModel, seconds: float = 3.0) -> CaseResult:
    """The rope hung straight at its rest length and let go for ``seconds``: its elongation
    (the last second's mean) and the period of its bounce (sign changes about that mean)
    within :data:`STRETCH_TOL` of :func:`hung_stretch`'s."""
    p = rope.params
    b = hung(rope, hanging_at_home(p))
    t, length = [], []

    def take(bench) -> None:
        t.append(bench.t)
        length.append(float(np.linalg.norm(np.diff(bench.vertices(), axis=0), axis=1).sum()))

    b.run(seconds, every=0.002, probe=take)
    t_s, x = np.array(t), np.array(length) - p.length
    rest = x[t_s > seconds - 1.0].mean()
    period = _period(t_s, x - rest)
    measured = {"elongation_m": float(rest), "period_s": period}
    if p.stretch_modulus <= 0:
        return result(
            "stretch", rope, True, "no stretch (an inextensible model)", "", measured,
            f"elongation {rest * 1e3:.2f} mm (inextensible: reported, not judged)", applies=False,
        )  # fmt: skip
    delta, period_law = hung_stretch(p)
    measured |= {"law_elongation_m": delta, "law_period_s": period_law}
    err_d, err_t = rest / delta - 1, period / period_law - 1
    ok = abs(err_d) <= STRETCH_TOL and abs(err_t) <= STRETCH_TOL
    return result(
        "stretch",
        rope,
        ok,
        f"stretches and bounces as a spring of EA {p.axial_stiffness:.1f} N "
        f"(within {STRETCH_TOL:.0%})",
        "Hooke's law on the hanging tension; the first longitudinal mode of a bar with an end mass",
        measured,
        f"elongation {rest * 1e3:.2f} mm vs {delta * 1e3:.2f} ({err_d:+.1%}), period "
        f"{period * 1e3:.1f} ms vs {period_law * 1e3:.1f} ({err_t:+.1%})",
    )

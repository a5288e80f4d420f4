"""The validation cases: behaviours every real rope of its kind shows, measured on the lab's rope.

Each case returns a :class:`CaseResult`: the measured numbers, the expectation for the rope's
material, and the source or physical reason of that expectation. Expectations per material:
``cotton`` (a textile cord: fibres that stick and slip), ``latex`` (an elastic tube), ``steel``
(a link chain). Where a behaviour does not apply to a material, the case says so (e.g. a chain
has no bending stiffness to measure; a latex tube's knots are reported, not judged). The knot
cases are in :mod:`flyknot_tools.rope_validate.knots`; this module has the others and the
table of all of them, :data:`CASES`; the rest after a throw is in
:mod:`flyknot_tools.rope_validate.rest_after_motion`, the stretch in
:mod:`flyknot_tools.rope_validate.stretch`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.optimize import brentq

from flyknot_sim.aero import cylinder_cd, sphere_cd
from flyknot_sim.rope_table import RopeParams
from flyknot_tools.rope_study.crossings import resample_equal_chords
from flyknot_tools.rope_validate.bench import Bench, RopeModel
from flyknot_tools.rope_validate.common import DOWN, HOME, UP, CaseResult, G, hung, result
from flyknot_tools.rope_validate.knots import Swing, knot_hold, static_hold
from flyknot_tools.rope_validate.lock_up import lock_up
from flyknot_tools.rope_validate.rest_after_motion import Throw, rest_after_motion
from flyknot_tools.rope_validate.stretch import stretch

__all__ = [
    "CASES",
    "CaseResult",
    "Swing",
    "Throw",
    "cantilever",
    "capstan",
    "catenary_sag",
    "drag_decay_theory",
    "knot_hold",
    "lock_up",
    "loop_spring_back",
    "peirce_bending_length",
    "rest_after_motion",
    "rest_shape",
    "static_hold",
    "stretch",
    "swing_decay",
]


# ----------------------------------------------------------------------------------------
# capstan
# ----------------------------------------------------------------------------------------
def capstan(
    rope: RopeModel,
    rod_radius: float = 0.05,
    speed: float = 0.02,
    seconds: float = 3.0,
    load: float | None = None,
) -> CaseResult:
    """The rope over a fixed horizontal rod (wrap angle pi, the rod's friction = the rope's):
    the holder pulls the rope down on one side at ``speed``, lifting the other side's hanging
    length and end weight. At steady sliding the tensions where the rope leaves the rod obey
    the capstan law T_pull / T_load = exp(mu theta) (Euler-Eytelwein), with the frictional
    couple's resistance to being bent on and off the rod (a rope over a sheave: each change of
    curvature 1/R costs a pull M_0 / R, R the radius of the centreline):
    T_pull = (T_load + M_0 / R) exp(mu theta) + M_0 / R; with the links' friction of a chain
    (``link_friction_radius`` r, flyknot_sim.bend_friction) each bend costs mu r T / R more,
    T_pull = ((T_load k + M_0 / R) exp(mu theta)) k + M_0 / R, k = 1 + mu r / R.
    ``load`` [kg]: the end's mass
    (None: the rope's end weight, the tension of the lab's knots). Passes within 25 %
    (a polygon of 36.7 mm elements touches a 5 cm rod at a few points: MuJoCo issue #454
    reports capsule ropes under-delivering the capstan effect)."""
    p = rope.params if load is None else replace(rope.params, end_mass=load)
    mu, theta = p.friction, math.pi
    bend = p.frictional_couple / (rod_radius + p.radius)  # [N]
    link = 1.0 + p.link_friction_arm / (rod_radius + p.radius)  # [-], 1 without
    centre = np.array([0.0, 0.0, 1.2])
    x = _draped(p, centre, rod_radius)
    home = x[0] - DOWN * p.clearance
    b = Bench(replace(rope, params=p), home=home, axis=UP, rod=(centre, rod_radius, mu))
    b.place(x)

    def pull(t: float) -> tuple[np.ndarray, np.ndarray]:
        s = max(0.0, t - 0.5)
        return np.array([0.0, 0.0, -speed * s]), np.array([0.0, 0.0, -speed if t > 0.5 else 0.0])

    ratios = []

    def probe(bench: Bench) -> None:
        if bench.t < 1.0:
            return
        xs = bench.vertices()
        f_hold = -bench.holder_force()[2]  # the holder pulls the rope down
        left = centre[2] - xs[0, 2]  # length below the rod on the holder's side
        load_side = xs[:, 0] > centre[0] + 0.5 * rod_radius
        right = max(0.0, centre[2] - float(xs[load_side, 2].min()))
        t_pull = f_hold + p.density * G * left
        t_load = p.end_mass * G + p.density * G * right
        ratios.append(t_pull / ((t_load * link + bend) * math.exp(mu * theta) * link + bend))

    b.run(seconds, pull, 0.01, probe)
    measured = float(np.median(ratios)) if ratios else float("nan")
    ok = abs(measured - 1) <= 0.25
    return result(
        "capstan",
        rope,
        ok,
        f"pull = capstan law with exp(mu pi) = {math.exp(mu * theta):.2f} (mu = {mu:g}) within "
        "25 %",
        "the capstan equation T2 / T1 = exp(mu theta) (Euler 1762; every rope on a round "
        "post) plus the bending resistance of a rope over a sheave; 25 %: the polygonal wrap",
        {
            "pull_over_capstan_law": measured,
            "exp_mu_theta": math.exp(mu * theta),
            "bend_pull_n": bend,
            "mu": mu,
            "load_kg": p.end_mass,
            "rod_radius_m": rod_radius,
            **({"link_bend_factor": link} if link != 1.0 else {}),
        },
        f"pull {measured:.2f} x the capstan law (exp(mu pi) = {math.exp(mu * theta):.2f}, "
        f"load {p.end_mass * 1e3:g} g, bending {bend:.3f} N)",
    )


def _draped(p: RopeParams, centre: np.ndarray, radius: float) -> np.ndarray:
    """Vertices up the left side of a rod, over it, and down the right side, equal chords."""
    r = radius + p.radius
    half = (p.length - math.pi * r) / 2
    s = np.linspace(0.0, p.length + 0.02, 4001)  # a little extra: resampling stops at n
    pts = np.empty((len(s), 3))
    for i, si in enumerate(s):
        if si < half:  # straight up on the left
            pts[i] = centre + np.array([-r, 0.0, -(half - si)])
        elif si < half + math.pi * r:  # over the top
            a = math.pi - (si - half) / r
            pts[i] = centre + np.array([r * math.cos(a), 0.0, r * math.sin(a)])
        else:  # down on the right
            pts[i] = centre + np.array([r, 0.0, -(si - half - math.pi * r)])
    return resample_equal_chords(pts, p.segment_length, p.segments)


# ----------------------------------------------------------------------------------------
# cantilever: bending length from above and from below (hysteresis)
# ----------------------------------------------------------------------------------------
HYSTERESIS_SEEN = 0.05
"""Smallest relative difference of two cantilever bending lengths the test tells apart."""


def peirce_bending_length(overhang: float, angle: float) -> float:
    """Peirce's cantilever: c = l (cos(theta / 2) / (8 tan theta))^(1/3) [m] for an overhang
    ``overhang`` [m] whose chord to the tip makes ``angle`` [rad] with the horizontal
    (F. T. Peirce, J. Textile Inst. 21 (1930) T377); NaN outside the formula's range
    0 < angle < pi / 2 (a tip hanging straight down or curling back up)."""
    if not 0.0 < angle < math.pi / 2:
        return math.nan
    return overhang * (math.cos(angle / 2) / (8 * math.tan(angle))) ** (1 / 3)


def _arc(p: RopeParams, n: int, turn: float, start: np.ndarray) -> np.ndarray:
    """n + 1 vertices of equal chords from ``start`` along +x, the first chord straight and
    the others turning by ``turn`` [rad] each (positive: upward)."""
    x = [start, start + np.array([p.segment_length, 0.0, 0.0])]
    a = 0.0
    for _ in range(n - 1):
        a += turn
        x.append(x[-1] + p.segment_length * np.array([math.cos(a), 0.0, math.sin(a)]))
    return np.array(x)


def cantilever(rope: RopeModel, seconds: float = 8.0) -> CaseResult:
    """A short piece of the rope held horizontally (no end weight), released once bent up
    (curling 60 degrees above the horizontal) and once bent down (60 degrees below the
    droop it settles to from above); after ``seconds`` the tip's chord angle gives Peirce's
    bending length c for each. The overhang is the smallest whole number of elements
    >= 2.5 c_elastic (c_elastic = (EI / w)^(1/3)), so the chord angle is 30-60 degrees.

    Expected: cotton c_up > c_down by >= 5 % (fibres stick: a textile keeps part of
    whichever bend it is given: Grosberg, Text. Res. J. 36 (1966) 205; Kawabata's
    hysteresis 2HB); latex within 5 % (rubber is nearly elastic: tan delta ~ 0.1,
    Ferry 1980); a chain has no bending stiffness (it hangs down from the clamp). 5 %: what
    the cantilever test can tell apart (its readings repeat to a few per cent)."""
    p = rope.params
    if p.material == "steel":
        return _chain_cantilever(rope, seconds)
    w = p.density * G
    c_el = (p.bending_stiffness / w) ** (1 / 3)
    n = max(3, math.ceil(2.5 * c_el / p.segment_length))
    short = replace(p, length=n * p.segment_length, segments=n, end_mass=0.0)
    model = replace(rope, params=short)
    start = HOME
    results = {}
    for name, turn in (("up", math.radians(60) / (n - 1)), ("down", None)):
        if turn is None:
            drop = results["up"][1]
            turn = -(drop + math.radians(60)) / (n - 1)
        b = Bench(model, home=start - [short.clearance, 0, 0], axis=[1.0, 0.0, 0.0])
        b.place(_arc(short, n, turn, start))
        b.run(seconds - 1.0)
        tips: list[np.ndarray] = []
        b.run(1.0, every=0.02, probe=lambda bench, tips=tips: tips.append(bench.vertices()[-1]))
        chord = np.mean(tips, axis=0) - b.vertices()[0]  # averaged over the last second
        angle = math.atan2(-chord[2], chord[0])
        results[name] = (peirce_bending_length(n * p.segment_length, angle), angle * 2)
    c_up, c_down = results["up"][0], results["down"][0]
    spread = (c_up - c_down) / (0.5 * (c_up + c_down))
    up_deg, down_deg = (math.degrees(results[k][1] / 2) for k in ("up", "down"))
    if p.material == "cotton":
        ok = spread >= HYSTERESIS_SEEN
        expected = "bending length from above exceeds that from below by >= 5 %"
    else:
        ok = abs(spread) <= HYSTERESIS_SEEN
        expected = "bending lengths from above and below agree within 5 %"
    return result(
        "cantilever",
        rope,
        ok,
        expected,
        "Grosberg's frictional couple of textiles (Text. Res. J. 36 (1966) 205; Kawabata "
        "KES-FB2 2HB); rubber nearly elastic (Ferry, Viscoelastic Properties of Polymers)",
        {
            "overhang_m": n * p.segment_length,
            "c_up_m": c_up,
            "c_down_m": c_down,
            "spread": spread,
            "c_elastic_m": c_el,
        },
        f"c from above {c_up * 100:.1f} cm, from below {c_down * 100:.1f} cm "
        f"({spread:+.0%}); elastic c {c_el * 100:.1f} cm"
        if math.isfinite(spread)
        else f"a tip chord outside Peirce's range (from above {up_deg:.0f} deg, from below "
        f"{down_deg:.0f} deg below the horizontal)",
    )


def _chain_cantilever(rope: RopeModel, seconds: float) -> CaseResult:
    p = rope.params
    n = 4
    short = replace(p, length=n * p.segment_length, segments=n, end_mass=0.0)
    b = Bench(replace(rope, params=short), home=HOME - [short.clearance, 0, 0], axis=[1, 0, 0])
    b.place(_arc(short, n, 0.0, HOME))
    b.run(max(seconds - 1.0, 0.0))
    tips = []
    b.run(1.0, every=0.01, probe=lambda bench: tips.append(bench.vertices()[-1]))
    # it swings as a pendulum below the clamped first link: its mean tip lies below that link
    reach = float(np.mean(tips, axis=0)[0] - b.vertices()[1, 0])
    hang = (n - 1) * p.segment_length
    ok = abs(reach) <= 0.2 * hang  # a swinging pendulum averaged over ~1.5 periods
    return result(
        "cantilever",
        rope,
        ok,
        "a chain held horizontally hangs down beyond the clamp (no bending stiffness)",
        "links turn freely on each other until they lock",
        {"reach_m": reach, "free_length_m": hang},
        f"tip on average {reach * 100:.1f} cm out from the clamp ({hang * 100:.1f} cm free length)",
    )


# ----------------------------------------------------------------------------------------
# spring-back of a loop
# ----------------------------------------------------------------------------------------
def loop_spring_back(rope: RopeModel, radius: float = 0.05, seconds: float = 2.0) -> CaseResult:
    """A piece of rope bent into a 5 cm radius arc (about the loop of a flying knot), held at
    one end, released with gravity off: the fraction of its turning angle left after
    ``seconds``. Expected: cotton keeps >= 50 % (a released bend springs back only until its
    elastic moment falls to the frictional couple: residual curvature HB / B, 23-54 1/m from
    Kawabata data, above this loop's 20 1/m: Grosberg 1966); latex keeps <= 20 % (elastic);
    a chain keeps its shape (no stiffness: >= 90 %)."""
    p = rope.params
    n = max(4, round(0.75 * 2 * math.pi * radius / p.segment_length))
    short = replace(p, length=n * p.segment_length, segments=n, end_mass=0.0)
    turn = 2 * math.asin(min(1.0, p.segment_length / (2 * radius)))
    b = Bench(
        replace(rope, params=short),
        home=HOME - [short.clearance, 0, 0],
        axis=[1, 0, 0],
        gravity=False,
    )
    x0 = _arc(short, n, turn, HOME)
    b.place(x0)
    total0 = _turning(x0)
    kept = []
    b.run(seconds, every=0.05, probe=lambda bench: kept.append(_turning(bench.vertices())))
    tail = float(np.mean(kept[-10:])) / total0
    lo, hi = {"cotton": (0.5, 10.0), "latex": (-10.0, 0.2), "steel": (0.9, 10.0)}[p.material]
    ok = lo <= tail <= hi
    expected = {
        "cotton": "keeps >= 50 % of its bend",
        "latex": "springs back: keeps <= 20 %",
        "steel": "keeps >= 90 % (no stiffness)",
    }[p.material]
    return result(
        "spring_back",
        rope,
        ok,
        expected,
        "Grosberg's frictional couple (Text. Res. J. 36 (1966) 205) with HB / B of cotton "
        "fabrics 0.23-0.54 1/cm (Kawabata KES-FB2 data, J. Textiles 2016, 4614168); rubber "
        "elastic; chain links free",
        {"radius_m": radius, "turning_deg": math.degrees(total0), "kept": tail},
        f"{math.degrees(total0):.0f} deg bend keeps {tail:.0%} after {seconds:g} s",
    )


def _turning(x: np.ndarray) -> float:
    """Signed total turning angle [rad] of a polyline in the x-z plane (positive: turning
    from +x towards +z), the sum of the signed angles between consecutive chords."""
    e = np.diff(x, axis=0)
    cross_y = e[:-1, 0] * e[1:, 2] - e[:-1, 2] * e[1:, 0]  # -(e_k x e_k+1) . y
    dot = np.einsum("ij,ij->i", e[:-1], e[1:])
    return float(np.arctan2(cross_y, dot).sum())


# ----------------------------------------------------------------------------------------
# swing decay against air-drag theory
# ----------------------------------------------------------------------------------------
def drag_decay_theory(p: RopeParams, amplitude: float, cycles: float) -> float:
    """Tip amplitude [m] after ``cycles`` of a hanging rope swinging rigidly about its hold
    with quadratic air drag: theta'' + w^2 theta + kappa theta'|theta'| = 0 loses
    dA = (8 / 3) kappa A^2 of angular amplitude per cycle, so 1 / A_N = 1 / A_0 + (8 / 3)
    kappa N. kappa = sum(1/2 rho C_D D l s^3 + sphere) / I, the drag coefficients of
    :mod:`flyknot_sim.aero` at the speed of the swing's mid-point (a rigid pendulum is the
    first mode to ~2 % in frequency: a chain's is 1.2024 sqrt(g/L) vs 1.2247 sqrt(g/L)).
    Air: rho 1.204 kg/m^3, nu 1.516e-5 m^2/s."""
    rho, nu = 1.204, 1.516e-5
    L = p.length
    s = (np.arange(p.segments) + 0.5) * p.segment_length
    inertia = p.density * L**3 / 3 + p.end_mass * L**2
    stiffness = G * (p.density * L**2 / 2 + p.end_mass * L)
    w = math.sqrt(stiffness / inertia)
    a0 = amplitude / L
    v_mid = (2 / math.pi) * w * a0 * s  # a mean speed of each element over the swing
    cd = cylinder_cd(np.maximum(v_mid * p.diameter / nu, 1.0))
    k_rope = float(np.sum(0.5 * rho * cd * p.diameter * p.segment_length * s**3))
    re_end = max((2 / math.pi) * w * a0 * L * 2 * p.end_radius / nu, 1.0)
    k_end = 0.5 * rho * float(sphere_cd(np.array([re_end]))[0]) * math.pi * p.end_radius**2 * L**3
    kappa = (k_rope + k_end) / inertia
    return L / (1 / a0 + (8 / 3) * kappa * cycles)


def swing_decay(rope: RopeModel, angle_deg: float = 15.0, seconds: float = 10.0) -> CaseResult:
    """The rope hangs straight at ``angle_deg`` from the vertical (the held segment
    vertical), released at rest; the free end's horizontal amplitude is taken from its
    peaks. Compared with air drag alone (:func:`drag_decay_theory`) over the same number
    of cycles: every real rope decays at least as fast as air drag makes it (internal
    friction only adds); the model passes when its decay (amplitude lost) is >= 70 % of the
    drag-alone decay (30 %: the rigid-pendulum approximation of the theory)."""
    p = rope.params
    a = math.radians(angle_deg)
    direction = np.array([math.sin(a), 0.0, -math.cos(a)])
    x0 = HOME + DOWN * p.clearance
    kink = x0 + DOWN * p.segment_length  # the held segment stays vertical
    x = np.array([x0] + [kink + direction * p.segment_length * k for k in range(p.segments)])
    b = hung(rope, x)
    tip = []
    b.run(seconds, every=0.01, probe=lambda bench: tip.append(bench.vertices()[-1, 0]))
    xs = np.array(tip)
    mag = np.abs(xs)
    peaks = [i for i in range(1, len(xs) - 1) if mag[i] >= mag[i - 1] and mag[i] > mag[i + 1]]
    amps = np.abs(xs[peaks])
    if len(amps) < 3:
        return result("swing_decay", rope, False, "a swing", "", {}, "no swing measured")
    cycles = (len(amps) - 1) / 2
    a_start, a_end = float(amps[0]), float(amps[-1])
    theory_end = drag_decay_theory(p, a_start, cycles)
    lost, lost_theory = a_start - a_end, a_start - theory_end
    ratio = lost / lost_theory
    ok = ratio >= 0.7
    return result(
        "swing_decay",
        rope,
        ok,
        "decays at least as fast as air drag alone",
        "quadratic drag on a pendulum: dA = (8/3) kappa A^2 per cycle; internal friction "
        "of cords adds to it",
        {
            "cycles": cycles,
            "tip_amplitude_start_m": a_start,
            "tip_amplitude_end_m": a_end,
            "drag_theory_end_m": theory_end,
            "decay_ratio": ratio,
        },
        f"tip amplitude {a_start * 100:.1f} -> {a_end * 100:.1f} cm in {cycles:g} cycles; "
        f"air drag alone -> {theory_end * 100:.1f} cm (decay x{ratio:.2f})",
    )


# ----------------------------------------------------------------------------------------
# rest shape: a catenary
# ----------------------------------------------------------------------------------------
def catenary_sag(length: float, span: float) -> tuple[float, float]:
    """(sag [m], end slope angle below horizontal [rad]) of a uniform catenary of
    ``length`` between two points ``span`` apart at one height: L = 2 a sinh(S / 2a),
    sag = a (cosh(S / 2a) - 1), slope sinh(S / 2a)."""
    a = brentq(lambda a: 2 * a * math.sinh(span / (2 * a)) - length, span / 50, 1e3 * span)
    u = span / (2 * a)
    return a * (math.cosh(u) - 1), math.atan(math.sinh(u))


def rest_shape(rope: RopeModel, span_fraction: float = 0.7, seconds: float = 6.0) -> CaseResult:
    """The rope hung between two points at one height ``span_fraction`` of its length apart
    (the end weight is held too), started as a V and settled for ``seconds``: its sag (the
    lowest point, averaged over the last second) must be within 5 % of the catenary's (every
    rope much longer than its bending length hangs as a catenary: Irvine, "Cable Structures",
    1981)."""
    p = rope.params
    span = span_fraction * p.length
    sag, slope = catenary_sag(p.length - p.clearance, span)
    axis = np.array([math.cos(slope), 0.0, -math.sin(slope)])
    start = HOME + axis * p.clearance
    end = start + np.array([span, 0.0, 0.0])
    half = p.length / 2 + 0.01  # the V is a little longer than the rope: it ends at ``end``
    depth = math.sqrt(max(half**2 - (span / 2) ** 2, 0.0))
    bottom = start + np.array([span / 2, 0.0, -depth])
    pts = np.vstack([np.linspace(start, bottom, 500), np.linspace(bottom, end, 500)[1:]])
    x = resample_equal_chords(pts, p.segment_length, p.segments)
    b = Bench(rope, home=HOME, axis=axis, free_end_at=end)
    b.place(x)
    b.run(max(seconds - 1.0, 0.0))
    lows = []  # the lowest point averaged over the last second (a chain still sways)
    b.run(1.0, every=0.01, probe=lambda bench: lows.append(bench.vertices()[:, 2].min()))
    measured = float(start[2] - np.mean(lows))
    err = measured / sag - 1
    return result(
        "rest_shape",
        rope,
        abs(err) <= 0.05,
        "hangs as a catenary between two holds (sag within 5 %)",
        "a uniform cable much longer than its bending length (Irvine, Cable Structures, 1981)",
        {"span_m": span, "sag_m": measured, "catenary_sag_m": sag, "error": err},
        f"sag {measured * 100:.1f} cm vs catenary {sag * 100:.1f} cm ({err:+.1%})",
    )


CASES = {
    "knot_hold": knot_hold,
    "static_hold": static_hold,
    "capstan": capstan,
    "cantilever": cantilever,
    "spring_back": loop_spring_back,
    "swing_decay": swing_decay,
    "rest_shape": rest_shape,
    "rest_after_motion": rest_after_motion,
    "lock_up": lock_up,
    "stretch": stretch,
}
"""The cases by name (each ``f(rope: RopeModel, ...) -> CaseResult``)."""

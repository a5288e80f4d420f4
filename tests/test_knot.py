"""Knot classification of open rope centrelines (flyknot.knot, flyknot.knot_diagram).

Curves are built here from explicit geometry: analytic knots (trefoil, figure-eight, torus
knots), hanging ropes made of waypoints whose crossings are placed by hand, and ropes lying on
a table. Each knotted or unknotted fixture whose free end hangs below and beside the rest is
first checked with an independent closure (held end straight up, free end straight down,
joined far away), so a test cannot pass on a fixture that is not what its name says.

Run ``python tests/test_knot.py`` to rewrite the small fixture files in tests/data/knots/.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import flyknot.knot as kn
import flyknot.knot_diagram as kd
from flyknot.errors import ConfigError, RecordError

DATA = Path(__file__).parent / "data" / "knots"
ROPE = 1.1  # [m]
HAND = np.array([0.0, 0.0, 1.5])  # [m]

# ------------------------------------------------------------------------------------------
# Curve builders


def resample(poly: np.ndarray, n: int) -> np.ndarray:
    """n points equally spaced in arc length along the polyline (n, 3)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, k]) for k in range(3)], axis=1)


def length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def trefoil(n: int, mirror: bool = False) -> np.ndarray:
    """Closed trefoil (n, 3), radius <= 3, starting at the outer tip of a lobe (s = pi / 3)."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False) + np.pi / 3
    z = -np.sin(3 * s)
    return np.stack(
        [np.sin(s) + 2 * np.sin(2 * s), np.cos(s) - 2 * np.cos(2 * s), -z if mirror else z], 1
    )


def figure_eight(n: int) -> np.ndarray:
    """Closed figure-eight knot (n, 3), radius <= 3, starting at an outer point."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = 2 + np.cos(2 * s)
    return np.stack([r * np.cos(3 * s), r * np.sin(3 * s), np.sin(4 * s)], 1)


def torus_knot(p: int, q: int, n: int) -> np.ndarray:
    """Closed (p, q) torus knot (n, 3): q turns about the z axis, p about the tube."""
    s = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = 2 + np.cos(p * s)
    return np.stack([r * np.cos(q * s), r * np.sin(q * s), np.sin(p * s)], 1)


def open_pulled(closed: np.ndarray, gap: int, pull: float) -> np.ndarray:
    """Cut a closed curve at vertex 0, drop `gap` vertices each side, push the ends outward."""
    p = closed[gap : len(closed) - gap + 1].copy()
    centre = closed.mean(axis=0)
    for end in (0, -1):
        out = p[end] - centre
        p[end] += pull * out / np.linalg.norm(out)
    return p


def hang_closed_knot(closed: np.ndarray, size: float, n: int) -> np.ndarray:
    """A closed knot opened at its top and hung like a rope (about 1.1 m), resampled to n.

    The held tail goes straight up from one cut end to the hand; the other cut end rises
    above the knot, goes out sideways beyond it and hangs down beside it. Both tails run
    outside the knot's convex hull, so the knot type is that of the closed curve.
    """
    k = closed * (size / np.ptp(closed[:, 0]))
    top = int(np.argmax(k[:, 2]))
    k = np.roll(k, -top, axis=0)[1:]
    zmax, zmin, xmax = k[:, 2].max(), k[:, 2].min(), k[:, 0].max()
    m = 0.02
    first, last = k[0], k[-1]
    held = first + np.array([0.0, 0.0, zmax - first[2] + 0.25])
    free = [
        [last[0], last[1], zmax + m],
        [xmax + m, last[1], zmax + m],
        [xmax + m, last[1], zmin - 0.1],
    ]
    pts = np.vstack([held, k, free])
    return resample(pts - pts[0] + HAND, n)


# An overhand knot tied the way a person ties one: the rope comes down, makes an "alpha" loop
# in the x-z plane (the first strand passes in front, +y, at the loop's crossing), and the end
# then goes through the loop. Units of U = 15 mm; the rope is 9 mm thick.
U = 0.015
ALPHA = [(-2, 0, 3), (0, 0.4, 0), (2, 0, -2), (0, 0, -4), (-2, 0, -2), (0, -0.4, 0), (2, 0, 3)]
ENDS = {
    # In front across the loop's right edge, through the loop to the back, behind across the
    # left edge: crossings alternate over/under -> trefoil.
    "overhand": [
        (3.5, 0, 0), (3.5, 1, -2.5), (0.5, 1, -2.5), (-0.5, -1, -2.5), (-3.5, -1, -2.5),
        (-3.5, -1, -5),
    ],
    # Through the loop the other way: over, over, under, under, under, over -> unknot.
    "false_overhand": [
        (3.5, 0, 0), (3.5, -1, -2.5), (0.5, -1, -2.5), (-0.5, 1, -2.5), (-3.5, 1, -2.5),
        (-3.5, 1, -5),
    ],
    # A bight of the end goes into the loop from the front and back out to the front (a
    # "slip"): pulling the end would draw it out -> unknot.
    "slip": [
        (3.5, 0, 0), (3.5, 1, -2.2), (0.8, 1, -2.2), (0.3, -1, -2.2), (0.3, -1, -3.0),
        (0.8, 1, -3.0), (3.5, 1, -3.0), (3.5, 1, -6),
    ],
}  # fmt: skip


def knot_core(kind: str, unit: float = U) -> np.ndarray:
    return np.array(ALPHA + ENDS[kind], dtype=float) * unit


def rope(cores: list[np.ndarray], n: int, sway: float = 0.05) -> np.ndarray:
    """A 1.1 m rope from the hand: a swaying hanging part, then the knot cores, one below the
    other, each joined to the next by 10 cm of rope; resampled to n points."""
    parts, bottom = [], None
    for core in cores:
        core = core - core[0]
        if bottom is not None:
            core = core + bottom + [0.0, 0.0, -0.1]
        parts.append(core)
        bottom = core[-1]
    tail = np.vstack(parts)
    held_len = ROPE - length(tail)
    assert held_len > 0.2
    s = np.linspace(0, 1, 60)
    held = np.stack(
        [sway * np.sin(np.pi * s), 0.6 * sway * np.sin(2 * np.pi * s), held_len * (1 - s)], 1
    )
    pts = np.vstack([held, tail[1:] + held[-1]])
    return resample(pts - pts[0] + HAND, n)


def wandering_tail(n: int, turns: float) -> np.ndarray:
    """Unknotted: the rope hangs 0.4 m, its tail coils `turns` times around the hanging part
    (radius 4 cm) and ends 0.1 m above the hand, 2 cm from the hanging part."""
    s = np.linspace(0, 1, 30)
    down = np.stack([0.01 * np.sin(np.pi * s), 0 * s, 1.5 - 0.4 * s], 1)
    th = np.linspace(0, 2 * np.pi * turns, 80)
    coil = np.stack([0.04 * np.cos(th), 0.04 * np.sin(th), 1.08 + 0.35 * th / th[-1]], 1)
    a = th[-1]
    end = [[0.02 * np.cos(a), 0.02 * np.sin(a), 1.48], [0.02 * np.cos(a), 0.02 * np.sin(a), 1.6]]
    return resample(np.vstack([down, [[0.02, 0, 1.07]], coil, end]), n)


def cycloid_on_table(n: int) -> np.ndarray:
    """A rope lying on a table in three curls (a prolate cycloid), each curl's crossing lifted
    by the rope diameter on alternate strands: every crossing is a kink -> unknot."""
    r, b = 0.02, 0.05
    s = np.linspace(-np.pi, 5 * np.pi, 3000)
    delta = 2.1333  # sin(delta) / delta = r / b: the curl crosses itself at 2 pi k +- delta
    z = np.zeros_like(s)
    for k in range(3):
        over = 2 * np.pi * k + (delta if k % 2 == 0 else -delta)
        z += 0.009 * np.exp(-(((s - over) / 0.25) ** 2))
    return resample(np.stack([r * s - b * np.sin(s), b * np.cos(s), z], 1), n)


def spirograph_on_table(n: int) -> np.ndarray:
    """A rope on a table along a hypotrochoid with many self-crossings, rising 9 mm from one
    end to the other so that the later strand is always on top (descending) -> unknot."""
    t = np.linspace(0, 2 * np.pi * 2.6, 4000)
    R, r, d = 0.15, 0.06, 0.08
    x = (R - r) * np.cos(t) + d * np.cos((R - r) / r * t)
    y = (R - r) * np.sin(t) - d * np.sin((R - r) / r * t)
    return resample(np.stack([x, y, 0.009 * t / t[-1]], 1), n)


def updown_closure(p: np.ndarray, reach: float = 10.0) -> np.ndarray:
    """The closure the feasibility notes warn about: held end straight up, free end straight
    down, joined far to the side. Right when the free end hangs below and beside the rope."""
    up, down = p[0] + [0, 0, reach], p[-1] - [0, 0, reach]
    side = [10 * reach, 0, 0]
    return np.vstack([up, p, down, down + side, up + side])


# ------------------------------------------------------------------------------------------
# The kernel: diagrams and Alexander polynomials


@pytest.mark.parametrize(
    ("curve", "poly", "name"),
    [
        (trefoil(60), (1, -1, 1), "trefoil"),
        (trefoil(60, mirror=True), (1, -1, 1), "trefoil"),
        (figure_eight(60), (-1, 3, -1), "4_1"),
        (torus_knot(2, 5, 100), (1, -1, 1, -1, 1), "5_1"),
        (torus_knot(2, 7, 140), (1, -1, 1, -1, 1, -1, 1), "7_1"),
        (torus_knot(3, 4, 160), (1, -1, 0, 1, 0, -1, 1), "8_19"),
        (torus_knot(3, 5, 200), None, "10_124"),
    ],
)
def test_closed_analytic_knots(curve, poly, name):
    assert kn.classify_polygon(curve) == name
    if poly is not None:
        diagram = kd.project_diagram(kd.normalise(curve), np.array([0.3, 0.5, 0.8]), closure="edge")
        assert kd.alexander_polynomial(diagram) == poly


def test_alexander_rows_sum_to_zero_and_minor_choice_does_not_matter():
    p = kd.normalise(torus_knot(2, 5, 100))
    diagram = kd.project_diagram(p, np.array([0.2, -0.4, 0.9]), closure="edge")
    m0, m1 = kd.alexander_matrix(diagram)
    c = diagram.n_crossings
    assert c >= 5 and m0.shape == (c, c)
    np.testing.assert_array_equal((m0 + m1).sum(axis=1), 0)  # row sums at t = 1
    np.testing.assert_array_equal(m0.sum(axis=1) + 2 * m1.sum(axis=1), 0)  # and at t = 2
    # |det| of two different minors agrees at a point of the unit circle (same Delta up to
    # a unit +-t^k, whose modulus there is 1).
    t = np.exp(0.7j)
    m = m0 + t * m1
    d1 = np.linalg.det(m[1:, 1:])
    d2 = np.linalg.det(np.delete(np.delete(m, 2, 0), c - 1, 1))
    assert abs(abs(d1) - abs(d2)) < 1e-9
    delta = np.polyval([1, -1, 1, -1, 1][::-1], t)
    assert abs(abs(d1) - abs(delta)) < 1e-9


def test_merging_kinks_keeps_the_polynomial():
    """Kink elimination is exact: same polynomial as the full matrix, on noisy ropes (many
    small loops) and random blobs, and it shrinks the matrix."""
    rng = np.random.default_rng(2)
    p = rope([knot_core("overhand")], 200)
    curves = [p + rng.normal(0.0, 0.003, p.shape) for _ in range(3)]
    curves += [rng.normal(size=(20, 3)) for _ in range(6)]
    shrunk = 0
    for curve in curves:
        q = kd.normalise(curve)
        for d in kn.closure_directions(5):
            diagram = kd.project_diagram(q, d)
            if diagram is None or not 3 <= diagram.n_crossings <= 60:
                continue
            full = kd.alexander_polynomial(diagram, merge_kinks=False)
            assert kd.alexander_polynomial(diagram) == full
            m0, m1 = kd.alexander_matrix(diagram, merge_kinks=True)
            np.testing.assert_array_equal((m0 + m1).sum(axis=1), 0)
            shrunk += len(m0) < diagram.n_crossings
    assert shrunk >= 5


def test_alexander_polynomial_with_aliasing_above_32_crossings():
    # A trefoil drawn with a long wiggly tail that crosses it many times: more than 32
    # crossings forces the cyclic (aliased) evaluation path.
    rng = np.random.default_rng(3)
    tre = trefoil(80)
    x = np.linspace(3.5, -3.5, 120)
    wiggle = np.stack([x, 0.3 * rng.standard_normal(120), np.linspace(1.7, 2.2, 120)], 1)
    wiggle[:, 1] += 2.5 * np.sin(np.linspace(0, 12 * np.pi, 120))
    p = kd.normalise(np.vstack([tre, tre[:1] + np.array([0.4, 0.2, 1.6]), wiggle]))
    diagram = kd.project_diagram(p, np.array([0.0, 0.0, 1.0]))
    assert diagram.n_crossings > 32
    assert kd.alexander_polynomial(diagram) == (1, -1, 1)


@pytest.mark.slow
def test_matches_topoly_on_random_closed_polygons():
    """Random closed polygons in a blob (often knotted) against topoly's own Alexander
    polynomial; seeds chosen where topoly gives the same answer for rotated copies."""
    topoly = pytest.importorskip("topoly")
    rng = np.random.default_rng(5)
    names = {"0_1": "unknot", "3_1": "trefoil"}
    seen = set()
    for _ in range(30):
        poly = rng.normal(size=(int(rng.integers(12, 22)), 3))
        with contextlib.redirect_stdout(io.StringIO()):
            ref = topoly.alexander(poly.tolist(), closure=topoly.Closure.CLOSED, run_parallel=False)
        if "|" in ref or "TMC" in ref:
            continue
        assert kn.classify_polygon(poly) == names.get(ref, ref)
        seen.add(names.get(ref, ref))
    assert {"unknot", "trefoil"} <= seen and len(seen) >= 3


def test_over_chord_equals_explicit_ray_closure():
    """The chord-over diagram (and its rerouted path) is the closure by two parallel rays:
    build the rays in 3-D and identify the closed polygon with an ordinary projection."""
    rng = np.random.default_rng(11)
    checked = {}
    for trial in range(12):
        walk = np.cumsum(rng.normal(size=(int(rng.integers(15, 40)), 3)), axis=0)
        p = kd.normalise(walk)
        for d in kn.closure_directions(7):
            explicit = np.vstack([p[0] + 5 * d, p, p[-1] + 5 * d])
            name = kn.classify_closure(p, d)
            assert name == kn.classify_polygon(explicit), (trial, d)
            checked[name] = checked.get(name, 0) + 1
    assert len(checked) >= 2  # not only unknots


def test_projection_frame_is_right_handed():
    for d in kn.closure_directions(17):
        f = kd.projection_frame(3 * d)
        np.testing.assert_allclose(f @ f.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.cross(f[0], f[1]), d, atol=1e-12)


def test_closure_directions_cover_the_sphere():
    d = kn.closure_directions(31)
    assert d.shape == (31, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # Equal-area lattice: the mean is near 0, and the first 8 are spread over the sphere.
    assert np.linalg.norm(d.mean(axis=0)) < 0.05
    assert len({tuple(np.sign(x)) for x in d[:8]}) >= 5
    assert abs(np.sign(d[:8, 2]).sum()) <= 2  # the raw lattice would start with 8 upper ones
    assert len({tuple(np.round(x, 9)) for x in d}) == 31


def test_degenerate_projections_fall_back():
    # A straight vertical rope: every projection is a line with the chord along it.
    line = np.stack([0 * np.arange(20), 0 * np.arange(20), 1.5 - 0.05 * np.arange(20)], 1)
    assert kd.project_diagram(kd.normalise(line), np.array([1.0, 0, 0])) is None
    assert kn.classify_centreline(line) == "unknot"
    # An exactly planar spiral seen edge-on (one lattice direction is horizontal).
    th = np.linspace(0, 6 * np.pi, 200)
    spiral = np.stack([0.02 * th * np.cos(th), 0.02 * th * np.sin(th), 0 * th], 1)
    assert kd.project_diagram(kd.normalise(spiral), np.array([1.0, 0.3, 0])) is None
    assert kn.classify_centreline(spiral) == "unknot"


# ------------------------------------------------------------------------------------------
# Naming and voting


@pytest.mark.parametrize(
    ("poly", "name"),
    [
        ((1,), "unknot"),
        ((1, -1, 1), "trefoil"),
        ((-1, 3, -1), "4_1"),
        ((2, -3, 2), "5_2"),
        ((1, -2, 3, -2, 1), "3_1#3_1"),
        ((-2, 9, -13, 9, -2), "other"),  # 5_2#4_1 and 9_12: same polynomial, 9 crossings
        ((1000, -1999, 1000), "other"),  # no knot in the table
        (None, "other"),
    ],
)
def test_knot_name(poly, name):
    assert kd.knot_name(poly) == name


def test_plurality_and_ties():
    assert kn.plurality({"trefoil": 3, "unknot": 2}) == "trefoil"
    assert kn.plurality({"trefoil": 2, "unknot": 2}) == "unknot"
    assert kn.plurality({"other": 2, "5_1": 2, "4_1": 2}) == "4_1"
    assert kn.plurality({"other": 2, "trefoil": 2}) == "trefoil"
    assert kn.plurality({"11n34": 1, "10_124": 1, "3_1#3_1": 1}) == "3_1#3_1"
    with pytest.raises(ConfigError) as err:
        kn.plurality({})
    assert str(err.value) == "votes: no votes to count"
    with pytest.raises(ConfigError) as err:
        kd.Diagram(n_edges=4, over=np.zeros(2), under=np.zeros(3), sign=np.ones(2, int))
    assert str(err.value) == "Diagram: over, under and sign need the same shape (c,)"


# ------------------------------------------------------------------------------------------
# Open curves and hanging ropes


@pytest.mark.parametrize("n", [25, 60])
def test_open_analytic_knots_with_ends_pulled_apart(n):
    for closed, name in [
        (trefoil(n), "trefoil"),
        (trefoil(n, mirror=True), "trefoil"),
        (figure_eight(n), "4_1"),
    ]:
        p = open_pulled(closed, gap=1, pull=0.4)
        assert np.linalg.norm(p[0] - p[-1]) > 0.8
        assert kn.classify_centreline(p) == name


@pytest.mark.parametrize(
    ("closed", "name"), [(trefoil(400), "trefoil"), (figure_eight(400), "4_1")], ids=["3_1", "4_1"]
)
@pytest.mark.parametrize(("n", "noise"), [(200, 0.0), (41, 0.003), (25, 0.003), (25, 0.0)])
def test_hanging_analytic_knots(closed, name, n, noise):
    rng = np.random.default_rng(n)
    p = hang_closed_knot(closed, size=0.15, n=n)
    assert 0.9 < length(p) < 1.6 and p[0, 2] == pytest.approx(1.5)
    p = p + rng.normal(0.0, noise, p.shape)
    assert kn.classify_polygon(updown_closure(p)) == name  # the fixture is what it says
    votes = kn.closure_votes(p)
    assert max(votes, key=votes.get) == name and votes[name] >= 25
    assert kn.classify_centreline(p) == name


@pytest.mark.parametrize("n", [41, 100])
@pytest.mark.parametrize(
    ("kind", "name"), [("overhand", "trefoil"), ("false_overhand", "unknot"), ("slip", "unknot")]
)
def test_rope_with_knot_near_free_end(kind, name, n):
    p = rope([knot_core(kind)], n)
    assert length(p) == pytest.approx(ROPE, rel=0.03)
    assert p[-1, 2] < p[0, 2] - 0.6  # the knot hangs near the free end
    assert kn.classify_polygon(updown_closure(p)) == name
    assert kn.classify_centreline(p) == name


def test_loose_overhand_with_noise_in_a_41_point_rope():
    rng = np.random.default_rng(0)
    p = rope([knot_core("overhand")], 41)
    for _ in range(5):
        assert kn.classify_centreline(p + rng.normal(0.0, 0.002, p.shape)) == "trefoil"


def test_two_overhand_knots_are_a_granny_or_reef():
    p = rope([knot_core("overhand", 0.01), knot_core("overhand", 0.01)], 120, sway=0.03)
    assert kn.classify_polygon(updown_closure(p)) == "3_1#3_1"
    assert kn.classify_centreline(p) == "3_1#3_1"


@pytest.mark.parametrize("turns", [1.0, 1.5, 2.0])
def test_free_end_above_the_hand_is_not_a_false_knot(turns):
    p = wandering_tail(100, turns)
    assert p[-1, 2] > p[0, 2] + 0.05  # free end above the held end
    # The pitfall: extending the held end up and the free end down threads the coil.
    assert kn.classify_polygon(updown_closure(p)) != "unknot"
    votes = kn.closure_votes(p)
    assert votes.get("unknot", 0) >= 28
    assert kn.classify_centreline(p) == "unknot"


@pytest.mark.parametrize("builder", [cycloid_on_table, spirograph_on_table])
def test_rope_lying_on_a_table_with_crossings_is_unknotted(builder):
    p = builder(150)
    assert np.ptp(p[:, 2]) <= 0.0091
    seen_from_above = kd.project_diagram(kd.normalise(p), np.array([0.0, 0.0, 1.0]))
    assert seen_from_above.n_crossings >= 3
    assert kn.classify_centreline(p) == "unknot"


def test_reversed_curve_gives_identical_votes():
    for p in (
        rope([knot_core("overhand")], 41),
        wandering_tail(60, 1.5),
        hang_closed_knot(figure_eight(300), 0.15, 41),
    ):
        assert kn.closure_votes(p) == kn.closure_votes(p[::-1])


def test_early_stop_gives_the_full_vote_winner():
    for p in (
        rope([knot_core("overhand")], 41),
        rope([knot_core("slip")], 41),
        wandering_tail(60, 1.0),
    ):
        full = kn.closure_votes(p)
        part = kn.closure_votes(p, stop_early=True)
        assert sum(part.values()) < sum(full.values()) == kn.DEFAULT_DIRECTIONS
        assert kn.plurality(part) == kn.plurality(full)


def test_knot_fraction():
    frames = np.stack(
        [rope([knot_core(k)], 41) for k in ("overhand", "slip", "overhand", "false_overhand")]
    )
    assert kn.knot_fraction(frames) == 0.5
    assert kn.knot_fraction(frames, knot="unknot", n_directions=9) == 0.5


_ROT = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: float(np.linalg.norm(q)) > 0.1
)


def _rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


_FIXTURES = {
    "overhand": (rope([knot_core("overhand")], 41), "trefoil"),
    "slip": (rope([knot_core("slip")], 41), "unknot"),
    "figure_eight": (hang_closed_knot(figure_eight(300), 0.15, 41), "4_1"),
    "wandering": (wandering_tail(60, 1.5), "unknot"),
}


@settings(max_examples=25, deadline=None)
@given(
    which=st.sampled_from(sorted(_FIXTURES)),
    q=_ROT,
    shift=st.lists(st.floats(-100.0, 100.0), min_size=3, max_size=3),
    scale=st.floats(1e-3, 1e3),
)
def test_rigid_motion_and_scale_do_not_change_the_answer(which, q, shift, scale):
    p, name = _FIXTURES[which]
    moved = scale * (p @ _rotation(q).T) + np.asarray(shift)
    assert kn.classify_centreline(moved) == name


# ------------------------------------------------------------------------------------------
# Input errors and files


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((5, 2)), "points: expected an array of shape (n, 3), got shape (5, 2)"),
        (np.zeros((2, 5, 3)), "points: expected an array of shape (n, 3), got shape (2, 5, 3)"),
        (np.zeros((3, 3)), "points: need at least 4 points, got 3"),
        (
            np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0], [0, np.inf, 1], [0, 0, 1.0]]),
            "points: 2 point(s) with NaN or inf, first at row 2",
        ),
        (np.ones((6, 3)), "points: all points coincide, the curve has no shape"),
        ([["a", "b", "c"]] * 4, "points: expected numbers, got list"),
    ],
)
def test_bad_points_raise_record_error(points, message):
    with pytest.raises(RecordError) as err:
        kn.classify_centreline(points)
    assert str(err.value) == message


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "31"])
def test_bad_n_directions(bad):
    with pytest.raises(ConfigError) as err:
        kn.classify_centreline(rope([knot_core("slip")], 41), n_directions=bad)
    assert str(err.value) == f"n_directions: must be an integer >= 1, got {bad!r}"


def test_bad_closure_name():
    with pytest.raises(ConfigError) as err:
        kd.project_diagram(np.eye(3), np.array([0, 0, 1.0]), closure="rays")
    assert str(err.value) == "closure: unknown value 'rays' (valid choices: over, edge)"


def test_knot_fraction_bad_frames():
    with pytest.raises(RecordError) as err:
        kn.knot_fraction(np.zeros((41, 3)))
    assert str(err.value) == "frames: expected an array of shape (k, n, 3), got shape (41, 3)"
    frames = np.stack([rope([knot_core("slip")], 41)] * 2)
    frames[1, 7, 2] = np.nan
    with pytest.raises(RecordError) as err:
        kn.knot_fraction(frames)
    assert str(err.value) == "frames[1]: 1 point(s) with NaN or inf, first at row 7"


def test_load_centreline_round_trips(tmp_path):
    p = rope([knot_core("overhand")], 41)
    np.save(tmp_path / "c.npy", p)
    np.testing.assert_array_equal(kn.load_centreline(tmp_path / "c.npy"), p)
    np.savetxt(tmp_path / "c.csv", p, delimiter=",", header="x,y,z", comments="", fmt="%.17g")
    np.testing.assert_array_equal(kn.load_centreline(str(tmp_path / "c.csv")), p)
    np.savetxt(tmp_path / "nohead.CSV", p, delimiter=", ", fmt="%.17g")
    np.testing.assert_array_equal(kn.load_centreline(tmp_path / "nohead.CSV"), p)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("a.txt", "0,0,0\n", "{path}: unknown file type '.txt' (valid choices: .csv, .npy)"),
        ("a", "0,0,0\n", "{path}: unknown file type '' (valid choices: .csv, .npy)"),
        ("a.csv", None, "{path}: no such file"),
        ("a.csv", "x,y,z\n0,0,0\n1,1\n", "{path}: line 3 has 2 columns, expected 3 (x, y, z)"),
        ("a.csv", "x,y,z\n0,0,0\n1,one,1\n", "{path}: line 3 is not numbers: '1,one,1'"),
        ("a.csv", "x,y,z\n\n", "{path}: no data rows"),
        ("a.csv", "x,y,z\n0,0,0\n1,0,0\n0,1,0\n", "{path}: need at least 4 points, got 3"),
        (
            "a.csv",
            "0,0,0\n1,0,0\n0,1,0\n0,0,nan\n",
            "{path}: 1 point(s) with NaN or inf, first at row 3",
        ),
    ],
)
def test_load_centreline_errors(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(RecordError) as err:
        kn.load_centreline(path)
    assert str(err.value) == message.format(path=path)


def test_load_npy_errors(tmp_path):
    np.save(tmp_path / "flat.npy", np.zeros(10))
    with pytest.raises(RecordError) as err:
        kn.load_centreline(tmp_path / "flat.npy")
    assert (
        str(err.value)
        == f"{tmp_path / 'flat.npy'}: expected an array of shape (n, 3), got shape (10,)"
    )
    (tmp_path / "junk.npy").write_bytes(b"not an array")
    with pytest.raises(RecordError, match=r"junk\.npy: not a readable \.npy array"):
        kn.load_centreline(tmp_path / "junk.npy")


# ------------------------------------------------------------------------------------------
# Stored fixtures (tests/data/knots): small files for the CLI and for regression


def _fixture_curves() -> dict[str, tuple[np.ndarray, str]]:
    return {
        "overhand_41.csv": (rope([knot_core("overhand")], 41), "trefoil"),
        "slip_41.npy": (rope([knot_core("slip")], 41), "unknot"),
        "free_end_above_hand_60.npy": (wandering_tail(60, 1.5), "unknot"),
        "figure_eight_41.npy": (hang_closed_knot(figure_eight(300), 0.15, 41), "4_1"),
    }


def write_fixtures() -> None:
    DATA.mkdir(parents=True, exist_ok=True)
    for name, (p, _) in _fixture_curves().items():
        if name.endswith(".csv"):
            np.savetxt(DATA / name, p, delimiter=",", header="x,y,z", comments="", fmt="%.9f")
        else:
            np.save(DATA / name, p)


@pytest.mark.parametrize("name", sorted(_fixture_curves()))
def test_stored_fixtures(name):
    p, expected = _fixture_curves()[name]
    stored = kn.load_centreline(DATA / name)
    np.testing.assert_allclose(stored, p, atol=1e-8)
    assert kn.classify_centreline(stored) == expected


if __name__ == "__main__":
    write_fixtures()

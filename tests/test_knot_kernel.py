"""The compiled crossing search returns what the array formulas of a knot diagram give."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.knot_diagram import _EPS, _edge_pairs, project_diagram
from flyknot.knot_kernel import count_hits, crossings


def _reference(u, h0, h1, strict):
    """Segment-pair crossings by array formulas: t, v from 2-D cross products."""
    m = len(u)
    i, j = _edge_pairs(m)
    a, r = u[i], u[(i + 1) % m] - u[i]
    c, s = u[j], u[(j + 1) % m] - u[j]
    w = c - a
    den = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    lr, ls = np.linalg.norm(r, axis=1), np.linalg.norm(s, axis=1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (w[:, 0] * s[:, 1] - w[:, 1] * s[:, 0]) / den
        v = (w[:, 0] * r[:, 1] - w[:, 1] * r[:, 0]) / den
        et, es = _EPS / lr, _EPS / ls
    general = np.abs(den) > 1e-12 * lr * ls
    proper = general & (t > et) & (t < 1 - et) & (v > es) & (v < 1 - es)
    near = general & ~proper & (t >= -et) & (t <= 1 + et) & (v >= -es) & (v <= 1 + es)
    if strict and near.any():
        return None
    i, j, t, v, r, s = i[proper], j[proper], t[proper], v[proper], r[proper], s[proper]
    hi = h0[i] + t * (h1[i] - h0[i])
    hj = h0[j] + v * (h1[j] - h0[j])
    if strict and np.any(np.abs(hi - hj) <= _EPS):
        return None
    up = hi > hj
    o = np.where(up[:, None], r, s)
    w2 = np.where(up[:, None], s, r)
    sign = np.sign(o[:, 0] * w2[:, 1] - o[:, 1] * w2[:, 0]).astype(int)
    return np.where(up, i + t, j + v), np.where(up, j + v, i + t), sign


_polygons = st.integers(4, 30).flatmap(
    lambda n: st.lists(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3), min_size=n, max_size=n)
)


@settings(max_examples=200, deadline=None)
@given(_polygons, st.booleans())
def test_crossings_equal_the_array_formulas(points, strict):
    p = np.array(points)
    u, h = np.ascontiguousarray(p[:, :2]), p[:, 2].copy()
    h1 = np.roll(h, -1)
    i, j = _edge_pairs(len(u))
    degenerate, over, under, sign = crossings(u, h, h1, i, j, _EPS, strict)
    want = _reference(u, h, h1, strict)
    if want is None:
        assert degenerate
        return
    # A collinear overlap is degenerate too (the reference above leaves it out): random
    # floats never make one.
    assert not degenerate
    for got, ref in zip((over, under, sign), want, strict=True):
        np.testing.assert_array_equal(got, ref)


def test_a_flat_crossing_and_an_overlap_are_degenerate():
    # A figure-eight in the plane z = 0: its strands cross at the same height.
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    flat = np.stack([np.sin(2 * t), np.sin(t), 0 * t], axis=1)
    i, j = _edge_pairs(len(flat))
    u, h = np.ascontiguousarray(flat[:, :2]), flat[:, 2].copy()
    assert crossings(u, h, h, i, j, _EPS, True)[0]
    assert not crossings(u, h, h, i, j, _EPS, False)[0]
    assert project_diagram(flat, np.array([0.0, 0.0, 1.0]), closure="edge") is None
    # Two collinear edges that overlap: 0 -> 2 and back over 1.5 -> 0.5 on the x axis.
    line = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [1.5, 0.0], [0.5, 0.0], [0.0, 1.0]])
    i, j = _edge_pairs(len(line))
    z = np.zeros(len(line))
    assert crossings(line, z, z + 1.0, i, j, _EPS, True)[0]


def test_count_hits_counts_proper_crossings():
    u = np.array([[0.0, -1.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]])  # edges x = 0, y = 1, x = 1
    a = np.array([[-1.0, 0.0], [-1.0, 0.0], [0.5, 0.0]])
    b = np.array([[2.0, 0.0], [0.5, 0.0], [0.5, 2.0]])
    skip = np.zeros(3, dtype=np.bool_)
    np.testing.assert_array_equal(count_hits(a, b, u, skip), [2, 1, 1])
    skip[0] = True
    np.testing.assert_array_equal(count_hits(a, b, u, skip), [1, 0, 1])


@pytest.mark.parametrize("closure", ["over", "edge"])
def test_a_trefoils_diagram_has_three_crossings(closure):
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    k = np.stack([np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)])
    d = project_diagram(k.T / 3.2, np.array([0.1, 0.2, 1.0]), closure=closure)
    assert d is not None and d.n_crossings >= 3 and set(np.abs(d.sign)) == {1}

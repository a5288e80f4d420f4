"""Continuous crossing check of a rope's centreline, and a loose overhand knot to pull.

Tunnelling is detected by :func:`count_crossings`: between two saved frames every vertex
moves on a straight line, and two non-adjacent centreline segments cross when their four end
points become coplanar at a time at which the segments intersect (a cubic in time, solved
exactly on monotone brackets). :func:`overhand_knot_vertices` is the start of the knot-pull
(:func:`flyknot_tools.rope_study.measures.measure_knot_pull`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from flyknot.errors import ConfigError
from flyknot_sim.rope_handle import polyline_length
from flyknot_sim.rope_table import RopeParams


# ----------------------------------------------------------------------------------------
# continuous crossing check
# ----------------------------------------------------------------------------------------
def _det3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, np.cross(b, c))


def coplanarity_cubic(
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    d: np.ndarray,
    da: np.ndarray,
    db: np.ndarray,
    dc: np.ndarray,
    dd: np.ndarray,
) -> np.ndarray:
    """Coefficients of V(t) = det[B - A, C - A, D - A] with every point moving linearly.

    With P(t) = P + t dP for P in A, B, C, D and u = B - A, v = C - A, w = D - A:
    V(t) = c0 + c1 t + c2 t^2 + c3 t^3, c0 = [u v w], c1 = [du v w] + [u dv w] + [u v dw],
    c2 = [du dv w] + [du v dw] + [u dv dw], c3 = [du dv dw] ([.] = triple product). V = 0
    exactly when the four points are coplanar.

    Args:
        a: Point A at t = 0, shape (..., 3) [m].
        b: Point B at t = 0, shape (..., 3) [m].
        c: Point C at t = 0, shape (..., 3) [m].
        d: Point D at t = 0, shape (..., 3) [m].
        da: Displacement of A over the interval, shape (..., 3) [m].
        db: Displacement of B over the interval, shape (..., 3) [m].
        dc: Displacement of C over the interval, shape (..., 3) [m].
        dd: Displacement of D over the interval, shape (..., 3) [m].

    Returns:
        Coefficients (c0, c1, c2, c3), shape (..., 4) [m^3].
    """
    u, v, w = b - a, c - a, d - a
    du, dv, dw = db - da, dc - da, dd - da
    c0 = _det3(u, v, w)
    c1 = _det3(du, v, w) + _det3(u, dv, w) + _det3(u, v, dw)
    c2 = _det3(du, dv, w) + _det3(du, v, dw) + _det3(u, dv, dw)
    c3 = _det3(du, dv, dw)
    return np.stack([c0, c1, c2, c3], axis=-1)


def cubic_roots_unit(coef: np.ndarray, iters: int = 60) -> np.ndarray:
    """Real roots in [0, 1] of cubics, by bisection on monotone brackets.

    The critical points (roots of c1 + 2 c2 t + 3 c3 t^2 in (0, 1)) split [0, 1] into up to
    three monotone pieces; a piece whose end values differ in sign (or touch zero) holds one
    root, found by ``iters`` bisections (error 2^-iters).

    Args:
        coef: (c0, c1, c2, c3), shape (P, 4).
        iters: Bisection steps per root.

    Returns:
        Roots, shape (P, 3), NaN where a piece has none.
    """
    c = np.asarray(coef, dtype=float)
    p = c.shape[0]
    qa, qb, qc = 3 * c[:, 3], 2 * c[:, 2], c[:, 1]
    crit = np.full((p, 2), np.nan)
    lin = np.abs(qa) < 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = qb * qb - 4 * qa * qc
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        r1 = (-qb - sq) / (2 * qa)
        r2 = (-qb + sq) / (2 * qa)
        crit[:, 0] = np.where(lin, -qc / qb, np.minimum(r1, r2))
        crit[:, 1] = np.where(lin, np.nan, np.maximum(r1, r2))
    crit = np.where((crit > 0) & (crit < 1), crit, np.nan)
    crit = np.sort(crit, axis=1)  # NaN last
    knots = np.column_stack([np.zeros(p), crit, np.ones(p)])
    # replace NaN knots by the next valid one so the pieces stay ordered
    for j in (2, 1):
        knots[:, j] = np.where(np.isnan(knots[:, j]), knots[:, j + 1], knots[:, j])

    def val(t: np.ndarray) -> np.ndarray:
        return ((c[:, 3:4] * t + c[:, 2:3]) * t + c[:, 1:2]) * t + c[:, 0:1]

    lo, hi = knots[:, :3].copy(), knots[:, 1:].copy()
    flo, fhi = val(lo), val(hi)
    has = (flo * fhi <= 0) & (hi > lo) | (flo == 0)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        fm = val(mid)
        left = flo * fm <= 0
        hi = np.where(left, mid, hi)
        lo = np.where(left, lo, mid)
        flo = np.where(left, flo, fm)
    roots = 0.5 * (lo + hi)
    return np.where(has, roots, np.nan)


def segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Shortest distance between segments [p1, q1] and [p2, q2], shape (...,) [m].

    Minimises |p1 + s d1 - p2 - u d2| over s, u in [0, 1]: s from the unconstrained optimum
    clamped, then u for that s clamped, then s for that u clamped (exact for segments).
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    tiny = 1e-24
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        # general case; a point-like first segment gives s = 0, a point-like second u = 0
        s = np.where(denom > 1e-12 * a * e, (b * f - c * e) / denom, 0.0)
        s = np.where(e <= tiny, -c / a, s)
        s = np.where(a <= tiny, 0.0, np.clip(s, 0.0, 1.0))
        u = np.where(e <= tiny, 0.0, (b * s + f) / e)
        u_c = np.clip(u, 0.0, 1.0)
        s_u = np.where(a <= tiny, 0.0, np.clip((b * u_c - c) / a, 0.0, 1.0))
        s = np.where(u != u_c, s_u, s)
    u = u_c
    diff = p1 + s[..., None] * d1 - p2 - u[..., None] * d2
    return np.linalg.norm(diff, axis=-1)


def count_crossings(x0: np.ndarray, x1: np.ndarray, min_gap: int = 2, tol: float = 1e-7) -> int:
    """Crossings of non-adjacent centreline segments while every vertex moves x0 -> x1.

    Segments i and j with j - i >= ``min_gap`` are tested. A crossing is a root t* in [0, 1]
    of V(t) (:func:`coplanarity_cubic`) at which the two segments are within ``tol`` of each
    other (:func:`segment_distance`). A pair is pruned first if the boxes swept by the two
    segments do not overlap.

    Args:
        x0: Vertices at the start of the interval, shape (n + 1, 3) [m].
        x1: Vertices at the end of the interval, shape (n + 1, 3) [m].
        min_gap: Smallest index difference tested (2: pairs sharing no vertex).
        tol: Distance under which coplanar segments count as intersecting [m].

    Returns:
        Number of crossing events.
    """
    x0 = np.asarray(x0, dtype=float)
    x1 = np.asarray(x1, dtype=float)
    n = x0.shape[0] - 1
    lo = np.minimum(np.minimum(x0[:-1], x0[1:]), np.minimum(x1[:-1], x1[1:]))
    hi = np.maximum(np.maximum(x0[:-1], x0[1:]), np.maximum(x1[:-1], x1[1:]))
    i, j = np.triu_indices(n, k=min_gap)
    near = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    i, j = i[near], j[near]
    if len(i) == 0:
        return 0
    d = x1 - x0
    coef = coplanarity_cubic(x0[i], x0[i + 1], x0[j], x0[j + 1], d[i], d[i + 1], d[j], d[j + 1])
    roots = cubic_roots_unit(coef)
    count = 0
    for col in range(roots.shape[1]):
        t = roots[:, col]
        ok = ~np.isnan(t)
        if not ok.any():
            continue
        tt = t[ok][:, None]
        ii, jj = i[ok], j[ok]
        dist = segment_distance(
            x0[ii] + tt * d[ii],
            x0[ii + 1] + tt * d[ii + 1],
            x0[jj] + tt * d[jj],
            x0[jj + 1] + tt * d[jj + 1],
        )
        count += int(np.sum(dist < tol))
    return count


def count_run_crossings(vertices: np.ndarray, min_gap: int = 2) -> int:
    """Sum of :func:`count_crossings` over consecutive frames of (T, n + 1, 3)."""
    return sum(
        count_crossings(vertices[k], vertices[k + 1], min_gap) for k in range(len(vertices) - 1)
    )


# ----------------------------------------------------------------------------------------
# a loose overhand knot
# ----------------------------------------------------------------------------------------
def resample_equal_chords(curve: np.ndarray, chord: float, n: int) -> np.ndarray:
    """n + 1 points on a polyline, consecutive ones exactly ``chord`` apart.

    From the current point p, the next is the first point of the polyline beyond p at
    distance ``chord`` from p (intersection of a sphere with a polyline edge, a quadratic).

    Args:
        curve: Dense polyline, shape (m, 3) [m].
        chord: Distance between consecutive output points [m].
        n: Number of chords.

    Returns:
        Points, shape (n + 1, 3) [m].

    Raises:
        ConfigError: The polyline is too short for n chords.
    """
    curve = np.asarray(curve, dtype=float)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(curve, axis=0), axis=1) > 1e-12])
    curve = curve[keep]
    out = [curve[0]]
    p, k, t0 = curve[0], 0, 0.0
    while len(out) <= n:
        found = False
        while k < len(curve) - 1:
            a, b = curve[k], curve[k + 1]
            e = b - a
            # |a + t e - p|^2 = chord^2, t in [t0, 1]
            f = a - p
            qa, qb, qc = e @ e, 2 * e @ f, f @ f - chord * chord
            disc = qb * qb - 4 * qa * qc
            if disc >= 0:
                t = (-qb + math.sqrt(disc)) / (2 * qa)
                if t0 - 1e-12 <= t <= 1.0:
                    p = a + t * e
                    out.append(p)
                    t0 = t
                    found = True
                    break
            k, t0 = k + 1, 0.0
        if not found:
            raise ConfigError("curve", f"too short for {n} chords of {chord} m")
    return np.array(out)


def overhand_knot_vertices(
    params: RopeParams,
    knot_length: float = 0.7,
    centre: Sequence[float] = (0.0, 0.0, 1.0),
    tail_below: float | None = None,
) -> np.ndarray:
    """Vertices of a loose overhand knot with straight tails, held end up, equal edges.

    The knot is the trefoil T(t) = lam (sin t + 2 sin 2t, cos t - 2 cos 2t, -sin 3t) opened at
    its outermost point t = pi/3 (where |T_xy| is largest and z = 0): the curve runs over
    [pi/3 + delta, 7 pi/3 - delta]; the upper end continues straight up, the lower end
    straight down, both pushed 2 cm outward first. lam is chosen so that the knot part is
    ``knot_length`` long. The trefoil's centre is put at ``centre`` [m].

    Returns:
        Vertices, shape (n + 1, 3) [m], vertex 0 at the top of the upper tail.
    """
    delta = 0.25
    t = np.linspace(math.pi / 3 + delta, 7 * math.pi / 3 - delta, 2000)
    unit = np.column_stack(
        [np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)]
    )
    lam = knot_length / float(polyline_length(unit))
    knot = lam * unit
    tip = lam * np.array(
        [
            math.sin(math.pi / 3) + 2 * math.sin(2 * math.pi / 3),
            math.cos(math.pi / 3) - 2 * math.cos(2 * math.pi / 3),
            0.0,
        ]
    )
    out = np.append(tip[:2] / np.linalg.norm(tip[:2]), 0.0)
    tail = params.length  # generous; resampling stops after n chords
    up = np.linspace(0, 1, 200)[:, None]
    top = knot[0] + 0.02 * out + np.array([0, 0, 0.02])
    bottom = knot[-1] + 0.02 * out - np.array([0, 0, 0.02])
    upper = np.vstack([top + np.array([0, 0, tail]) * (1 - up), knot[0][None]])
    lower = np.vstack([bottom[None], bottom + np.array([0, 0, -tail]) * up[1:]])
    curve = np.vstack(
        [
            upper[:-1],
            np.linspace(top, knot[0], 20)[:-1],
            knot,
            np.linspace(knot[-1], bottom, 20)[1:],
            lower[1:],
        ]
    )
    # start the rope so that the knot sits in the middle: drop the excess of the upper tail
    arc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    i_knot = len(upper) - 1
    below = (params.length - knot_length) / 2 if tail_below is None else tail_below
    upper_len = params.length - knot_length - below
    excess = arc[i_knot] - upper_len
    start = int(np.searchsorted(arc, excess))
    x = resample_equal_chords(curve[start:], params.segment_length, params.segments)
    return x + np.asarray(centre, dtype=float)

"""Knot diagrams of closed polygons and their Alexander polynomial (the kernel of
:mod:`flyknot.knot`).

A closed polygon seen along a direction gives a diagram: its crossings, each with the
positions of the upper and lower strand and a handedness (:func:`project_diagram`; an open
curve's ray closure is drawn, seen from far along ``+d``, as a path between its end points
that passes *over* every strand). The Alexander polynomial of that diagram (the crossing/arc
form of Alexander's matrix, J. W. Alexander, Trans. AMS 30 (1928) 275-306; evaluated at roots
of unity and recovered by an FFT, :func:`alexander_polynomial`) is looked up in topoly's table
of knot polynomials for a name in Rolfsen notation (:func:`knot_name`). Pure NumPy apart from
that table and the compiled crossing search (:mod:`flyknot.knot_kernel`); why not topoly's
own closures: see :mod:`flyknot.knot`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, RecordError
from flyknot.knot_kernel import count_hits, crossings

__all__ = [
    "OTHER",
    "TREFOIL",
    "UNKNOT",
    "Diagram",
    "alexander_matrix",
    "alexander_polynomial",
    "knot_name",
    "normalise",
    "project_diagram",
    "projection_frame",
]

UNKNOT = "unknot"
TREFOIL = "trefoil"
OTHER = "other"

_EPS = 1e-9
"""Length [-] (curves are normalised to the unit ball) below which two strands of a projection
count as touching: a crossing that close to a vertex, or strands that close in height, make
the projection degenerate."""

_N_ROOTS = 32
"""Most roots of unity at which an Alexander determinant is evaluated."""


# --------------------------------------------------------------------------------------------
# Curves and projections


def normalise(points: np.ndarray) -> np.ndarray:
    """Translate and scale a curve into the unit ball; its knot type is unchanged.

    ``q_i = (p_i - c) / s`` with ``c`` the mean point and ``s = max_i |p_i - c|``. Consecutive
    points closer than 1e-9 (after scaling) are merged.

    Args:
        points: Curve, shape (n, 3) [m].

    Returns:
        Curve, shape (m, 3) [-], m <= n.

    Raises:
        RecordError: All points coincide.
    """
    c = points.mean(axis=0)
    s = float(np.max(np.linalg.norm(points - c, axis=1)))
    if not s > 0.0:
        raise RecordError("points: all points coincide, the curve has no shape")
    q = (points - c) / s
    keep = np.ones(len(q), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(q, axis=0), axis=1) > _EPS
    return q[keep]


def projection_frame(direction: np.ndarray) -> np.ndarray:
    """Orthonormal frame ``(e1, e2, d)`` with ``e1 x e2 = d``: a viewer at ``+d`` sees e1, e2.

    ``e1 = normalize(a - (a . d) d)`` with ``a`` the coordinate axis least aligned with ``d``,
    ``e2 = d x e1``.

    Args:
        direction: Viewing direction, shape (3,) [-], need not be normalised.

    Returns:
        Rows e1, e2, d, shape (3, 3) [-].
    """
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    a = np.zeros(3)
    a[int(np.argmin(np.abs(d)))] = 1.0
    e1 = a - (a @ d) * d
    e1 /= np.linalg.norm(e1)
    e2 = [d[1] * e1[2] - d[2] * e1[1], d[2] * e1[0] - d[0] * e1[2], d[0] * e1[1] - d[1] * e1[0]]
    return np.array([e1, e2, d])


# --------------------------------------------------------------------------------------------
# Knot diagrams and the Alexander polynomial


@dataclass(frozen=True)
class Diagram:
    """Crossings of a closed polygon seen along a direction.

    Positions run along the closed polygon in edge units: edge k (from vertex k to vertex
    k + 1, the last edge back to vertex 0) covers [k, k + 1).

    Attributes:
        n_edges: Number of edges of the closed polygon.
        over: Position of the upper strand at each crossing, shape (c,) [-].
        under: Position of the lower strand at each crossing, shape (c,) [-].
        sign: +1 for a right-handed crossing, -1 for a left-handed one, shape (c,).
    """

    n_edges: int
    over: np.ndarray
    under: np.ndarray
    sign: np.ndarray

    def __post_init__(self) -> None:
        c = np.shape(self.over)
        if np.shape(self.under) != c or np.shape(self.sign) != c or len(c) != 1:
            raise ConfigError("Diagram", "over, under and sign need the same shape (c,)")

    @property
    def n_crossings(self) -> int:
        """Number of crossings c."""
        return int(np.shape(self.over)[0])


@functools.cache
def _edge_pairs(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of non-adjacent edges of a closed m-gon."""
    i, j = np.triu_indices(m, k=2)
    keep = ~((i == 0) & (j == m - 1))
    return np.ascontiguousarray(i[keep]), np.ascontiguousarray(j[keep])


def project_diagram(
    points: np.ndarray, direction: np.ndarray, *, closure: str = "over", strict: bool = True
) -> Diagram | None:
    """Knot diagram of a closed-up polygon seen from far along ``+direction``.

    Vertices ``p_k`` project to ``u_k = (e1 . p_k, e2 . p_k)`` at height ``h_k = d . p_k``
    (frame of :func:`projection_frame`). Edges k and l cross where
    ``u_k + t (u_{k+1} - u_k) = u_l + s (u_{l+1} - u_l)`` with t, s in (0, 1); the strand with
    the larger interpolated height is over, and the crossing's sign is ``sign(o x w)`` for
    the 2-D directions ``o`` of the over edge and ``w`` of the under edge.

    ``closure="over"`` closes an open curve by parallel rays along ``+d`` joined at infinity.
    Seen from ``+d`` the rays are the end points and the closing arc is a path from the last
    point back to the first that passes over every strand; any such path gives the same knot,
    so the one with fewest crossings is drawn: the straight chord, or a ray out of each end
    (best of 12 angles) joined around a circle outside the curve. Its height is ``10 + k``
    on its k-th edge, above the normalised curve (``|h| <= 1``) and rising along the path, so
    where it crosses itself it stays unknotted. ``closure="edge"`` joins the last vertex to
    the first by an ordinary edge (a closed polygon).

    Args:
        points: Vertices, shape (n, 3) [-], inside the unit ball (see :func:`normalise`).
        direction: Viewing (and closure) direction ``d``, shape (3,) [-].
        closure: ``"over"`` (open curve, ray closure) or ``"edge"`` (closed polygon).
        strict: Return None on a degenerate projection (a crossing within 1e-9 of a vertex,
            overlapping collinear edges, or crossing strands within 1e-9 in height); if
            False, such pairs are skipped.

    Returns:
        The diagram, or None if it is degenerate and ``strict`` is set.

    Raises:
        ConfigError: ``closure`` is not "over" or "edge".
    """
    if closure not in ("over", "edge"):
        raise ConfigError("closure", f"unknown value {closure!r}", ["over", "edge"])
    frame = _frame(np.asarray(direction, dtype=float).tobytes())
    q = np.asarray(points, dtype=float) @ frame.T
    u, h = q[:, :2], q[:, 2]
    if closure == "edge":
        return _crossings(u, h, np.roll(h, -1), strict)  # heights at each edge's two ends
    path = _over_path(u)
    k = len(path) + 1  # edges of the closing path
    rise = 10.0 + np.arange(k + 1, dtype=float)
    u = np.vstack([u, path]) if len(path) else u
    h0 = np.concatenate([h[:-1], rise[:-1]])
    h1 = np.concatenate([h[1:], rise[1:]])
    return _crossings(u, h0, h1, strict)


@functools.lru_cache(maxsize=256)
def _frame(direction: bytes) -> np.ndarray:
    """:func:`projection_frame` of a direction given as its float64 bytes (closures use the
    same few directions for every curve), read-only."""
    frame = projection_frame(np.frombuffer(direction, dtype=float))
    frame.flags.writeable = False
    return frame


@functools.cache
def _rays() -> np.ndarray:
    """The 12 rays out of an end point tried for the closing path, 3 (cos a, sin a) at
    a = 0.1 + k pi / 6, shape (12, 2), read-only."""
    ang = np.arange(12) * (np.pi / 6.0) + 0.1
    rays = 3.0 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    rays.flags.writeable = False
    return rays


def _over_path(u: np.ndarray) -> np.ndarray:
    """Inner vertices of the closing path from u[-1] to u[0] with fewest crossings, (k, 2)."""
    n = len(u)
    direct = _count_hits(u[-1:], u[:1], u, skip=(0, n - 2))[0]
    if direct == 0:
        return np.zeros((0, 2))
    rays = _rays()
    hit_first = _count_hits(np.repeat(u[:1], 12, 0), u[0] + rays, u, skip=(0,))
    hit_last = _count_hits(np.repeat(u[-1:], 12, 0), u[-1] + rays, u, skip=(n - 2,))
    a, b = int(np.argmin(hit_first)), int(np.argmin(hit_last))
    if hit_first[a] + hit_last[b] >= direct:
        return np.zeros((0, 2))
    start, end = u[-1] + rays[b], u[0] + rays[a]  # |start|, |end| in [2, 4]
    t0 = math.atan2(start[1], start[0])
    t1 = math.atan2(end[1], end[0])
    turn = (t1 - t0 + math.pi) % (2.0 * math.pi) - math.pi
    steps = max(1, math.ceil(abs(turn) / (math.pi / 4.0)))
    th = t0 + turn * np.arange(steps + 1) / steps
    arc = 4.0 * np.stack([np.cos(th), np.sin(th)], axis=1)  # chords stay >= 3.7 from 0
    return np.vstack([start, arc, end])


def _count_hits(a: np.ndarray, b: np.ndarray, u: np.ndarray, skip: tuple[int, ...]) -> np.ndarray:
    """Crossings of each 2-D segment a[k] -> b[k] with the open polyline u, skipping edges
    (:func:`flyknot.knot_kernel.count_hits`)."""
    mask = np.zeros(len(u) - 1, dtype=np.bool_)
    mask[list(skip)] = True
    return count_hits(np.ascontiguousarray(a), np.ascontiguousarray(b), u, mask)


def _crossings(u: np.ndarray, h0: np.ndarray, h1: np.ndarray, strict: bool) -> Diagram | None:
    """Crossings of the closed 2-D polygon u (m, 2) whose edge k rises from h0[k] to h1[k]
    (:func:`flyknot.knot_kernel.crossings` over the non-adjacent edge pairs)."""
    m = len(u)
    i, j = _edge_pairs(m)
    u = np.ascontiguousarray(u, dtype=float)
    h0 = np.ascontiguousarray(h0, dtype=float)
    h1 = np.ascontiguousarray(h1, dtype=float)
    degenerate, over, under, sign = crossings(u, h0, h1, i, j, _EPS, strict)
    if degenerate:
        return None
    return Diagram(n_edges=m, over=over, under=under, sign=sign)


def alexander_matrix(
    diagram: Diagram, *, merge_kinks: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Alexander matrix ``M(t) = M0 + t M1`` of a knot diagram, rows = crossings.

    Arcs run between consecutive under-passes; arc j starts at the j-th under-pass along the
    polygon. At a crossing with over arc k, incoming under arc i and outgoing under arc j the
    row is ``(1 - t) x_k + t x_i - x_j`` if the crossing is right-handed and
    ``(1 - t) x_k - x_i + t x_j`` if left-handed (Alexander 1928). Every row sums to zero, so
    deleting any one row and one column leaves a minor whose determinant is the Alexander
    polynomial up to a factor ``+- t^k``.

    With ``merge_kinks``, rows whose over arc is one of their under arcs (a kink, Reidemeister
    I) are eliminated: such a row is ``u (x_i - x_j)`` with u a unit (1 or t), so adding
    column j to column i and expanding along the row removes the row and column j and
    multiplies the determinant by ``+- u``. Repeated until no row is a kink, this leaves an
    r x r matrix (r <= c) of the same kind with the same minors up to units. Noisy curves
    seen along their length have many such small loops.

    Args:
        diagram: A diagram with c >= 1 crossings.
        merge_kinks: Eliminate kink rows (see above).

    Returns:
        (M0, M1), integer arrays of shape (r, r); r = c without ``merge_kinks``.
    """
    c = diagram.n_crossings
    order = np.argsort(diagram.under, kind="stable")
    under = diagram.under[order]
    over = diagram.over[order]
    sign = diagram.sign[order]
    k = (np.searchsorted(under, over, side="right") - 1) % c
    i_in = (np.arange(c) - 1) % c
    j_out = np.arange(c)
    column = np.arange(c)
    keep = np.ones(c, dtype=bool)
    if merge_kinks:
        column, keep = _merge_kinks(k, i_in, j_out)
    rows = np.flatnonzero(keep)
    k, i_in, j_out, sign = column[k[rows]], column[i_in[rows]], column[j_out[rows]], sign[rows]
    r = len(rows)
    at = np.arange(r)
    m0 = np.zeros((r, r), dtype=int)
    m1 = np.zeros((r, r), dtype=int)
    np.add.at(m0, (at, k), 1)
    np.add.at(m1, (at, k), -1)
    pos = sign > 0
    np.add.at(m1, (at[pos], i_in[pos]), 1)
    np.add.at(m0, (at[pos], j_out[pos]), -1)
    neg = ~pos
    np.add.at(m0, (at[neg], i_in[neg]), -1)
    np.add.at(m1, (at[neg], j_out[neg]), 1)
    return m0, m1


def _merge_kinks(
    k: np.ndarray, i_in: np.ndarray, j_out: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Union-find over arcs: (column index of each arc, rows kept) after merging kinks."""
    c = len(k)
    parent = list(range(c))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    keep = np.ones(c, dtype=bool)
    changed = True
    while changed:
        changed = False
        for row in np.flatnonzero(keep):
            fk, fi, fj = find(int(k[row])), find(int(i_in[row])), find(int(j_out[row]))
            if fi != fj and fk in (fi, fj):
                keep[row] = False
                parent[fj] = fi
                changed = True
    roots = np.array([find(a) for a in range(c)])
    _, column = np.unique(roots, return_inverse=True)
    return column, keep


def alexander_polynomial(diagram: Diagram, *, merge_kinks: bool = True) -> tuple[int, ...] | None:
    """Alexander polynomial of a knot diagram, normalised.

    ``D(t) = det(M0' + t M1')`` for the minor without the last row and column of the r x r
    matrix of :func:`alexander_matrix` equals ``+- t^k Delta(t)``. Its coefficients follow
    from its values at the N-th roots of unity ``w^m = exp(2 pi i m / N)`` by an FFT,
    ``b_j = (1 / N) sum_m D(w^m) w^(-m j)``, which gives ``sum_k a_k [k = j mod N]``. With
    ``N = r`` (r <= 32) this is exact, as ``deg D < r``. For larger matrices ``N = 32`` and
    the coefficients come out cyclically shifted, which is undone by cutting the cycle at its
    longest run of zeros; this is exact when ``Delta`` spans at most 31 powers of t (knots of
    up to 31 crossings; the flying knot has 3). The result is divided by its lowest power of t
    and its sign chosen so that ``Delta(1) = +1``.

    Args:
        diagram: Knot diagram, c crossings.
        merge_kinks: Eliminate kink rows first (exact, faster; see :func:`alexander_matrix`).

    Returns:
        Coefficients (a_0, ..., a_g) of ``Delta(t) = a_0 + a_1 t + ...`` (``(1,)`` for fewer
        than 3 crossings), or None if the numbers are not those of a knot polynomial (not
        integers, ``|Delta(1)| != 1`` or not palindromic), which means a numerical failure.
    """
    if diagram.n_crossings < 3:
        return (1,)
    m0, m1 = alexander_matrix(diagram, merge_kinks=merge_kinks)
    r = len(m0)
    if r < 2:
        return (1,)
    a0 = m0[:-1, :-1].astype(complex)
    a1 = m1[:-1, :-1].astype(complex)
    n = min(r, _N_ROOTS)
    w = np.exp(2j * np.pi * np.arange(n) / n)
    values = np.linalg.det(a0[None] + w[:, None, None] * a1[None])
    coef = np.fft.fft(values) / n
    rounded = np.round(coef.real)
    if not np.all(np.abs(coef - rounded) <= 1e-6):
        return None
    nz = np.flatnonzero(rounded)
    if len(nz) == 0:
        return None
    if n < r:  # aliased: cut the cycle after its longest run of zeros
        if len(nz) == n:
            return None
        gaps = np.diff(np.concatenate([nz, [nz[0] + n]]))
        rounded = np.roll(rounded, -nz[(int(np.argmax(gaps)) + 1) % len(nz)])
        nz = np.flatnonzero(rounded)
    poly = rounded[nz[0] : nz[-1] + 1].astype(int)
    total = int(poly.sum())
    if abs(total) != 1 or not np.array_equal(poly, poly[::-1]):
        return None
    return tuple(int(x) for x in poly * total)


@functools.cache
def _knot_table() -> Any:
    """topoly's lookup from Alexander coefficients to knot names (imported on first use)."""
    from topoly.invariants import find_matching_knot

    return find_matching_knot


def knot_name(poly: tuple[int, ...] | None) -> str:
    """Name of the simplest knot with Alexander polynomial ``poly``.

    Looks ``poly`` up in topoly's knot table (Rolfsen names up to 10 crossings, knotinfo names
    for 11-12, ``#`` for connected sums) and keeps the names with the fewest crossings.
    ``(1,)`` -> ``"unknot"``, ``(1, -1, 1)`` -> ``"trefoil"``.

    Args:
        poly: Normalised coefficients from :func:`alexander_polynomial`, or None.

    Returns:
        ``"unknot"``, ``"trefoil"``, a name such as ``"4_1"``, or ``"other"`` for None, an
        unknown polynomial, or several simplest knots sharing the polynomial.
    """
    if poly is None:
        return OTHER
    if poly == (1,):
        return UNKNOT
    if poly == (1, -1, 1):
        return TREFOIL
    name = _knot_table()(" ".join(str(x) for x in poly), "Alexander").strip()
    if not name or "|" in name or name in ("Unknown", "TMC") or "_" not in name:
        return OTHER
    if name == "0_1":
        return UNKNOT
    return TREFOIL if name == "3_1" else name

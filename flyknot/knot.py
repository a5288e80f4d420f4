"""Knot type of an open rope centreline, decided by a vote over ray closures.

An open curve has no knot type until it is closed. The simulated lab judges a settled rope
that hangs from the fingertip, and its free end may lie anywhere, even above the hand. A
closure tied to gravity ("held end up, free end down") invents knots when the free end is
above the hand (measured: /work/shared/notes/flying-knot-feasibility.md), so this module does
not use one. Instead, for each direction ``d`` of a fixed, near-uniform set on the unit sphere,
both ends are extended by parallel rays along ``d`` to infinity and joined there (topoly calls
this the "rays" closure, ``topoly.Closure.RAYS``, but draws ``d`` at random). The knot type of
the open curve is the most frequent type over the directions: the "dominant knot type" over
closures of Millett, Dobay & Stasiak, Macromolecules 38 (2005) 601-606. A ray closure
misleads only for directions in which a ray from an end threads the rope; for a hanging rope
with a loose tail those are a small part of the sphere, wherever the free end lies (the test
fixture of a tail coiled round the rope, its end above the hand: 31 of 31 closures say
unknot, the up/down closure says trefoil). The directions are fixed, so the answer is
reproducible.

Each closure is identified without building it in 3-D: seen from far along ``+d``, the rays
shrink to the two end points and the arc at infinity becomes a path between them that passes
*over* every strand (any such path gives the same knot, so the one with fewest crossings is
drawn). The Alexander polynomial of that diagram (the crossing/arc form of Alexander's matrix,
J. W. Alexander, Trans. AMS 30 (1928) 275-306; evaluated at roots of unity and recovered by an
FFT) is looked up in topoly's table of knot polynomials for a name in Rolfsen notation. The
Alexander polynomial does not tell mirror images apart, so both trefoils are "trefoil"; it is
also blind to a few knots (e.g. 11n34 has the unknot's polynomial), none of which a flying
knot of a 1.1 m rope can form.

Why not topoly's own closures: on this machine ``topoly.alexander`` (1.2.1) returned the
impossible polynomial ``0`` and "too many crossings" for some ray closures of a 50-point
figure-eight whose rays pass 0.01-0.05 diameters from the curve, and different answers for
rotated copies of the same closed polygon; each call also runs ``gc.collect()`` (67 ms
measured here) and by default forks a process pool. The kernel here is pure NumPy (about
0.5 ms per closure at 41 points, 4 ms at 200) and is tested against topoly on polygons where
topoly is consistent.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, RecordError

UNKNOT = "unknot"
TREFOIL = "trefoil"
OTHER = "other"

DEFAULT_DIRECTIONS = 31
"""Closure directions voted over by default (odd, so two types cannot tie)."""

MAX_CROSSINGS = 150
"""Crossings in one projected diagram above which that closure votes ``"other"``."""

CENTRELINE_SUFFIXES = (".csv", ".npy")
"""File name endings :func:`load_centreline` reads."""

_EPS = 1e-9
"""Length [-] (curves are normalised to the unit ball) below which two strands of a projection
count as touching: a crossing that close to a vertex, or strands that close in height, make
the projection degenerate."""

_TILTS = (
    1e-3 * np.array([0.6, -0.8, 0.3]),
    1e-2 * np.array([-0.3, 0.2, 0.9]),
    3e-2 * np.array([0.8, 0.5, -0.4]),
)
"""Small deterministic changes of a closure direction, tried in turn when it is degenerate."""

_N_ROOTS = 32
"""Most roots of unity at which an Alexander determinant is evaluated."""

_LEADING_DIGITS = re.compile(r"\d+")

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # [rad]


# --------------------------------------------------------------------------------------------
# Input checks and files


def check_points(points: object, source: str = "points") -> np.ndarray:
    """Return ``points`` as a float array after checking it is a usable centreline.

    Args:
        points: Centreline, shape (n, 3) [m], n >= 4, all finite.
        source: Name used in error messages (a field name or a file path).

    Returns:
        A float64 copy, shape (n, 3) [m].

    Raises:
        RecordError: Not numbers, wrong shape, fewer than 4 points, or NaN/inf values.
    """
    try:
        p = np.array(points, dtype=float)
    except (TypeError, ValueError) as exc:
        raise RecordError(f"{source}: expected numbers, got {type(points).__name__}") from exc
    if p.ndim != 2 or p.shape[1] != 3:
        raise RecordError(f"{source}: expected an array of shape (n, 3), got shape {p.shape}")
    if p.shape[0] < 4:
        raise RecordError(f"{source}: need at least 4 points, got {p.shape[0]}")
    bad = ~np.isfinite(p)
    if bad.any():
        row = int(np.argwhere(bad)[0, 0])
        raise RecordError(
            f"{source}: {int(bad.any(axis=1).sum())} point(s) with NaN or inf, first at row {row}"
        )
    return p


def load_centreline(path: str | Path) -> np.ndarray:
    """Read a centreline from ``.npy`` (an (n, 3) array) or ``.csv`` (columns x, y, z).

    A ``.csv`` file has comma-separated fields and may start with one header line (a first
    line that is not all numbers); blank lines are skipped.

    Args:
        path: File to read.

    Returns:
        Centreline, shape (n, 3) [m].

    Raises:
        RecordError: Unknown file name ending, missing file, unreadable content, wrong shape,
            fewer than 4 points or NaN/inf values.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CENTRELINE_SUFFIXES:
        raise RecordError(
            f"{path}: unknown file type {path.suffix!r} "
            f"(valid choices: {', '.join(CENTRELINE_SUFFIXES)})"
        )
    if not path.is_file():
        raise RecordError(f"{path}: no such file")
    if suffix == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise RecordError(f"{path}: not a readable .npy array ({exc})") from exc
        return check_points(data, str(path))
    return check_points(_read_csv(path), str(path))


def _read_csv(path: Path) -> np.ndarray:
    """Rows of three comma-separated numbers; one leading header line is skipped."""
    rows: list[list[float]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(f) for f in line.split(",")]
        except ValueError:
            if lineno == 1:
                continue  # header
            raise RecordError(f"{path}: line {lineno} is not numbers: {line.strip()!r}") from None
        if len(values) != 3:
            raise RecordError(
                f"{path}: line {lineno} has {len(values)} columns, expected 3 (x, y, z)"
            )
        rows.append(values)
    if not rows:
        raise RecordError(f"{path}: no data rows")
    return np.asarray(rows, dtype=float)


def _check_n_directions(n_directions: object) -> int:
    if (
        isinstance(n_directions, bool)
        or not isinstance(n_directions, (int, np.integer))
        or n_directions < 1
    ):
        raise ConfigError("n_directions", f"must be an integer >= 1, got {n_directions!r}")
    return int(n_directions)


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


# --------------------------------------------------------------------------------------------
# Closure directions


def closure_directions(n: int) -> np.ndarray:
    """Near-uniform unit vectors on the sphere, ordered so that early ones are spread out.

    Fibonacci (golden-angle) lattice, for i = 0..n-1:
    ``z_i = 1 - (2 i + 1) / n``, ``phi_i = i * pi * (3 - sqrt(5))``,
    ``d_i = (sqrt(1 - z_i^2) cos(phi_i), sqrt(1 - z_i^2) sin(phi_i), z_i)``;
    each stands for an equal area ``4 pi / n`` [sr]. Rows are then reordered by the base-2
    radical inverse of i (van der Corput order) so that any prefix covers the sphere roughly
    evenly, which lets a vote stop early.

    Args:
        n: Number of directions, >= 1.

    Returns:
        Unit vectors, shape (n, 3) [-].

    Raises:
        ConfigError: ``n`` is not an integer >= 1.
    """
    n = _check_n_directions(n)
    i = np.arange(n)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * _GOLDEN_ANGLE
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return d[_van_der_corput_order(n)]


def _van_der_corput_order(n: int) -> np.ndarray:
    """Permutation of 0..n-1 sorted by the base-2 radical inverse of the index."""
    keys = np.zeros(n)
    for i in range(n):
        x, f = i, 0.5
        while x:
            keys[i] += f * (x & 1)
            x >>= 1
            f *= 0.5
    return np.argsort(keys, kind="stable")


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
    return np.stack([e1, np.cross(d, e1), d])


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
    return i[keep], j[keep]


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
    frame = projection_frame(direction)
    q = np.asarray(points, dtype=float) @ frame.T
    u, h = q[:, :2], q[:, 2]
    h0, h1 = h, np.roll(h, -1)  # heights at the start and end of each edge
    if closure == "over":
        path = _over_path(u)
        k = len(path) + 1  # edges of the closing path
        rise = 10.0 + np.arange(k + 1, dtype=float)
        u = np.vstack([u, path])
        h0 = np.concatenate([h[:-1], rise[:-1]])
        h1 = np.concatenate([h[1:], rise[1:]])
    return _crossings(u, h0, h1, strict)


def _over_path(u: np.ndarray) -> np.ndarray:
    """Inner vertices of the closing path from u[-1] to u[0] with fewest crossings, (k, 2)."""
    n = len(u)
    direct = _count_hits(u[-1:], u[:1], u, skip=(0, n - 2))[0]
    if direct == 0:
        return np.zeros((0, 2))
    ang = np.arange(12) * (np.pi / 6.0) + 0.1
    rays = 3.0 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
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
    """Crossings of each 2-D segment a[k] -> b[k] with the open polyline u, skipping edges."""
    e0, e1 = u[:-1], u[1:]
    keep = np.ones(len(e0), dtype=bool)
    keep[list(skip)] = False
    e0, e1 = e0[keep], e1[keep]
    r = (b - a)[:, None, :]
    s = (e1 - e0)[None]
    w = e0[None] - a[:, None, :]
    den = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * s[..., 1] - w[..., 1] * s[..., 0]) / den
        v = (w[..., 0] * r[..., 1] - w[..., 1] * r[..., 0]) / den
    return np.sum((den != 0) & (t > 0) & (t < 1) & (v > 0) & (v < 1), axis=1)


def _crossings(u: np.ndarray, h0: np.ndarray, h1: np.ndarray, strict: bool) -> Diagram | None:
    """Crossings of the closed 2-D polygon u (m, 2) whose edge k rises from h0[k] to h1[k]."""
    m = len(u)
    i, j = _edge_pairs(m)
    a, r = u[i], u[(i + 1) % m] - u[i]
    c, s = u[j], u[(j + 1) % m] - u[j]
    w = c - a
    den = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    tn = w[:, 0] * s[:, 1] - w[:, 1] * s[:, 0]
    sn = w[:, 0] * r[:, 1] - w[:, 1] * r[:, 0]
    lr = np.linalg.norm(r, axis=1)
    ls = np.linalg.norm(s, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = tn / den
        v = sn / den
        et = _EPS / lr
        es = _EPS / ls
    general = np.abs(den) > 1e-12 * lr * ls
    proper = general & (t > et) & (t < 1 - et) & (v > es) & (v < 1 - es)
    degenerate = general & ~proper & (t >= -et) & (t <= 1 + et) & (v >= -es) & (v <= 1 + es)
    par = ~general
    if par.any():  # parallel or zero-length edges: degenerate if collinear and overlapping
        degenerate |= par & _collinear_overlap(a, r, c, s, lr, ls)
    if strict and degenerate.any():
        return None
    i, j, t, v = i[proper], j[proper], t[proper], v[proper]
    r, s = r[proper], s[proper]
    hi = h0[i] + t * (h1[i] - h0[i])
    hj = h0[j] + v * (h1[j] - h0[j])
    if strict and np.any(np.abs(hi - hj) <= _EPS):
        return None
    i_over = hi > hj
    over = np.where(i_over, i + t, j + v)
    under = np.where(i_over, j + v, i + t)
    ro = np.where(i_over[:, None], r, s)
    rw = np.where(i_over[:, None], s, r)
    sign = np.sign(ro[:, 0] * rw[:, 1] - ro[:, 1] * rw[:, 0]).astype(int)
    return Diagram(n_edges=m, over=over, under=under, sign=sign)


def _collinear_overlap(a, r, c, s, lr, ls) -> np.ndarray:
    """For parallel 2-D segments a + t r and c + v s: do they lie on one line and overlap?"""
    ref = np.where((lr >= ls)[:, None], r, s)
    lref = np.maximum(np.maximum(lr, ls), 1e-300)
    w = c - a
    off = np.abs(ref[:, 0] * w[:, 1] - ref[:, 1] * w[:, 0]) / lref
    # Project all four end points on the common direction and compare intervals.
    e = ref / lref[:, None]
    a0, a1 = np.zeros(len(a)), np.einsum("ij,ij->i", r, e)
    c0 = np.einsum("ij,ij->i", w, e)
    c1 = c0 + np.einsum("ij,ij->i", s, e)
    lo = np.maximum(np.minimum(a0, a1), np.minimum(c0, c1))
    hi = np.minimum(np.maximum(a0, a1), np.maximum(c0, c1))
    return (off <= _EPS) & (hi >= lo - _EPS)


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


# --------------------------------------------------------------------------------------------
# Classification


def classify_closure(points: np.ndarray, direction: np.ndarray) -> str:
    """Knot type of an open curve closed by two parallel rays along ``direction``.

    The diagram of :func:`project_diagram` with the chord over everything. If the projection
    is degenerate, the direction is tilted by about 1e-3, 1e-2 and 3e-2 rad in turn; if all
    are degenerate, the degenerate pairs of the last one are ignored (a straight or exactly
    planar curve).

    Args:
        points: Open curve, shape (n, 3) [-], normalised (see :func:`normalise`).
        direction: Closure direction, shape (3,) [-].

    Returns:
        ``"unknot"``, ``"trefoil"``, a Rolfsen name, or ``"other"`` (also for more than
        ``MAX_CROSSINGS`` crossings).
    """
    diagram = _robust_diagram(points, np.asarray(direction, dtype=float), closure="over")
    if diagram.n_crossings > MAX_CROSSINGS:
        return OTHER
    return knot_name(alexander_polynomial(diagram))


def _robust_diagram(points: np.ndarray, direction: np.ndarray, *, closure: str) -> Diagram:
    """:func:`project_diagram`, tilting a degenerate direction; lenient if all are degenerate."""
    for d in (direction, *(direction + tilt for tilt in _TILTS)):
        diagram = project_diagram(points, d, closure=closure)
        if diagram is not None:
            return diagram
    return project_diagram(points, d, closure=closure, strict=False)


def classify_polygon(points: np.ndarray) -> str:
    """Knot type of a closed polygon (the last vertex joins the first).

    Same kernel as :func:`classify_closure` with an ordinary closing edge, seen along a fixed
    generic direction (tilted as there if degenerate).

    Args:
        points: Vertices, shape (n, 3), n >= 4, finite; the first is not repeated at the end.

    Returns:
        ``"unknot"``, ``"trefoil"``, a Rolfsen name, or ``"other"``.

    Raises:
        RecordError: Bad shape, fewer than 4 points, NaN/inf, or all points coincide.
    """
    p = normalise(check_points(points))
    diagram = _robust_diagram(p, np.array([0.3, 0.5, 0.8]), closure="edge")
    if diagram.n_crossings > MAX_CROSSINGS:
        return OTHER
    return knot_name(alexander_polynomial(diagram))


def _tie_key(name: str) -> tuple[int, int, str]:
    """Order among equal vote counts: unknot, trefoil, named knots by crossings, other."""
    if name == UNKNOT:
        return (0, 0, name)
    if name == TREFOIL:
        return (1, 3, name)
    if name == OTHER:
        return (3, 0, name)
    crossings = sum(int(m.group()) for m in map(_LEADING_DIGITS.match, name.split("#")) if m)
    return (2, crossings, name)


def plurality(votes: dict[str, int]) -> str:
    """Name with the most votes; equal counts go to unknot, trefoil, then fewer crossings.

    Args:
        votes: Count per knot name, not empty.

    Returns:
        The winning name.

    Raises:
        ConfigError: ``votes`` is empty.
    """
    if not votes:
        raise ConfigError("votes", "no votes to count")
    return min(votes, key=lambda k: (-votes[k], _tie_key(k)))


def closure_votes(
    points: np.ndarray, *, n_directions: int = DEFAULT_DIRECTIONS, stop_early: bool = False
) -> dict[str, int]:
    """Knot type of each ray closure of an open curve, counted.

    One :func:`classify_closure` per direction of :func:`closure_directions`, on the curve
    normalised to the unit ball.

    Args:
        points: Open curve, shape (n, 3) [m], first point = held end.
        n_directions: Number of closure directions, >= 1.
        stop_early: Stop as soon as the leading name can no longer be caught up or tied; the
            counts are then partial, but their :func:`plurality` equals that of the full vote.

    Returns:
        Votes per knot name; they sum to ``n_directions`` unless stopped early.

    Raises:
        RecordError: ``points`` is not a finite (n, 3) array with n >= 4, or all points
            coincide.
        ConfigError: ``n_directions`` is not an integer >= 1.
    """
    p = normalise(check_points(points))
    dirs = closure_directions(n_directions)
    votes: dict[str, int] = {}
    for done, d in enumerate(dirs, start=1):
        name = classify_closure(p, d)
        votes[name] = votes.get(name, 0) + 1
        if stop_early:
            counts = [*sorted(votes.values(), reverse=True), 0]
            if counts[0] > counts[1] + (len(dirs) - done):
                break
    return votes


def classify_centreline(points: np.ndarray, *, n_directions: int = DEFAULT_DIRECTIONS) -> str:
    """Knot type of an open rope centreline (held end first).

    The dominant type over ray closures (module docstring): the :func:`plurality` of
    :func:`closure_votes`. Unchanged by rigid motions and uniform scaling of ``points`` except
    in the rare case that they move a closure across a threading direction and that decides a
    close vote.

    Args:
        points: Centreline, shape (n, 3) [m], n >= 4.
        n_directions: Closure directions voted over, >= 1 (odd avoids ties).

    Returns:
        ``"unknot"``, ``"trefoil"`` (either chirality), a Rolfsen name such as ``"4_1"`` or
        ``"3_1#3_1"``, or ``"other"`` when the knot cannot be named.

    Raises:
        RecordError: ``points`` is not a finite (n, 3) array with n >= 4, or all points
            coincide.
        ConfigError: ``n_directions`` is not an integer >= 1.
    """
    return plurality(closure_votes(points, n_directions=n_directions, stop_early=True))


def knot_fraction(
    frames: np.ndarray, *, knot: str = TREFOIL, n_directions: int = DEFAULT_DIRECTIONS
) -> float:
    """Fraction of frames whose centreline is classified as ``knot``.

    ``f = #{i : classify_centreline(frames[i]) == knot} / k``, for shaping a search score;
    one :func:`classify_centreline` per frame (a few ms each for 41 points).

    Args:
        frames: Centrelines over time, shape (k, n, 3) [m], k >= 1, n >= 4.
        knot: Name counted as knotted.
        n_directions: Closure directions per frame, >= 1.

    Returns:
        Fraction in [0, 1].

    Raises:
        RecordError: ``frames`` is not a finite (k, n, 3) array with k >= 1 and n >= 4.
    """
    try:
        f = np.asarray(frames, dtype=float)
    except (TypeError, ValueError) as exc:
        raise RecordError(f"frames: expected numbers, got {type(frames).__name__}") from exc
    if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] < 1:
        raise RecordError(f"frames: expected an array of shape (k, n, 3), got shape {f.shape}")
    hits = sum(
        classify_centreline(check_points(frame, f"frames[{i}]"), n_directions=n_directions) == knot
        for i, frame in enumerate(f)
    )
    return hits / f.shape[0]

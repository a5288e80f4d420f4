"""Knot type of an open rope centreline, decided by a vote over ray closures.

An open curve has no knot type until it is closed. The simulated lab judges a settled rope
that hangs from the fingertip; its free end may lie anywhere, even above the hand. A closure
tied to gravity ("held end up, free end down") invents knots when the free end is above the
hand (measured: /work/shared/notes/flying-knot-feasibility.md), so this module does not use
one. Instead, for each direction ``d`` of a fixed, near-uniform set on the unit sphere, both
ends are extended by parallel rays along ``d`` to beyond the convex hull and joined there
(topoly calls this the "rays" closure, ``topoly.Closure.RAYS``, but draws ``d`` at random).
The knot type of the open curve is the most frequent type over the directions: the
"dominant knot type" over closures of Millett, Dobay & Stasiak, Macromolecules 38 (2005)
601-606. A closure along ``d`` equals viewing the curve along ``-d`` and closing the two end
points by a straight arc that passes over every strand, so a wrong answer needs a ray that
threads the rope, which happens only for a small solid angle of directions around a loose
tail. The directions are fixed (not random), so the answer is reproducible.

Each closed polygon is identified with topoly's Alexander polynomial after KMT reduction
(Koniaris & Muthukumar 1991) and its table of knot names (Rolfsen notation). The Alexander
polynomial does not tell mirror images apart, so both trefoils are "trefoil".
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, RecordError

UNKNOT = "unknot"
TREFOIL = "trefoil"
OTHER = "other"

DEFAULT_DIRECTIONS = 31
"""Closure directions voted over by default (odd, so two types cannot tie)."""

MAX_CROSSINGS = 15
"""Crossings allowed after KMT reduction before topoly gives up (its default); more -> "other"."""

CENTRELINE_SUFFIXES = (".csv", ".npy")
"""File name endings :func:`load_centreline` reads."""

_REACH_FACTOR = 2.0
"""Closure rays are this many curve diameters long: the joining segment then lies beyond the
convex hull, because every point of the curve is within one diameter of each end."""

_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # [rad]


def check_points(points: object, source: str = "points") -> np.ndarray:
    """Return ``points`` as a float array after checking it is a usable centreline.

    Args:
        points: Centreline, shape (n, 3) [m], n >= 4, all finite.
        source: Name used in error messages (a field name or a file path).

    Returns:
        A float64 copy, shape (n, 3) [m].

    Raises:
        RecordError: Wrong shape, fewer than 4 points, or NaN/inf values.
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


def _check_n_directions(n_directions: object) -> int:
    if isinstance(n_directions, bool) or not isinstance(n_directions, (int, np.integer)):
        raise ConfigError("n_directions", f"must be an integer >= 1, got {n_directions!r}")
    if n_directions < 1:
        raise ConfigError("n_directions", f"must be an integer >= 1, got {n_directions!r}")
    return int(n_directions)


def closure_directions(n: int) -> np.ndarray:
    """Near-uniform unit vectors on the sphere, in an order that spreads early ones apart.

    Fibonacci (golden-angle) lattice: for i = 0..n-1,
    ``z_i = 1 - (2 i + 1) / n``, ``phi_i = i * pi * (3 - sqrt(5))``,
    ``d_i = (sqrt(1 - z_i^2) cos(phi_i), sqrt(1 - z_i^2) sin(phi_i), z_i)``.
    Each direction stands for an equal area 4 pi / n [sr]. Rows are then reordered by the
    bit-reversed index (van der Corput order) so that any prefix covers the sphere roughly
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
    """Permutation of 0..n-1 sorted by the radical inverse of (i + 0.5) / n in base 2."""
    keys = []
    for i in range(n):
        x, f, v = i, 0.5, 0.0
        while x:
            v += f * (x & 1)
            x >>= 1
            f *= 0.5
        keys.append(v)
    return np.argsort(np.asarray(keys), kind="stable")


def normalise(points: np.ndarray) -> np.ndarray:
    """Translate and scale a curve to unit size; knot type is unchanged.

    ``q_i = (p_i - c) / s`` with ``c`` the mean point and ``s`` the largest distance of a point
    from ``c``. Consecutive points closer than ``1e-9`` (after scaling) are merged.

    Args:
        points: Curve, shape (n, 3) [m].

    Returns:
        Curve, shape (m, 3) [-], m <= n, inside the unit ball.

    Raises:
        RecordError: All points coincide.
    """
    c = points.mean(axis=0)
    s = float(np.max(np.linalg.norm(points - c, axis=1)))
    if not s > 0.0:
        raise RecordError("points: all points coincide, the curve has no shape")
    q = (points - c) / s
    keep = np.ones(len(q), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(q, axis=0), axis=1) > 1e-9
    return q[keep]


def ray_closure(points: np.ndarray, direction: np.ndarray, reach: float) -> np.ndarray:
    """Close an open curve with two parallel rays along ``direction``.

    Closed polygon ``[p_0 + L d, p_0, p_1, ..., p_{n-1}, p_{n-1} + L d]``; the last vertex
    joins the first. With ``L`` larger than the curve's extent along ``d``, the joining segment
    lies beyond every point of the curve in direction ``d``.

    Args:
        points: Open curve, shape (n, 3) [m].
        direction: Unit vector ``d``, shape (3,) [-].
        reach: Ray length ``L`` [m].

    Returns:
        Closed polygon without the repeated first vertex, shape (n + 2, 3) [m].
    """
    d = np.asarray(direction, dtype=float) * reach
    return np.vstack([points[:1] + d, points, points[-1:] + d])


@functools.cache
def _topoly() -> Any:
    """Import topoly on first use (it takes about 1 s to import)."""
    import topoly  # noqa: PLC0415
    from topoly.invariants import find_matching_knot  # noqa: PLC0415

    return topoly, find_matching_knot


def knot_name(table_name: str) -> str:
    """Map a topoly knot-table entry to this module's vocabulary.

    ``"0_1"`` -> ``"unknot"``, ``"3_1"`` -> ``"trefoil"``, other single names (Rolfsen notation,
    ``"#"`` for connected sums) are returned as they are; ambiguous entries (``"a|b"``, several
    knots with the same polynomial and crossing number), ``"Unknown"`` and too-many-crossings
    entries give ``"other"``.

    Args:
        table_name: A name from topoly's polynomial table.

    Returns:
        ``"unknot"``, ``"trefoil"``, a Rolfsen name such as ``"4_1"``, or ``"other"``.
    """
    name = table_name.strip()
    if name == "0_1":
        return UNKNOT
    if name == "3_1":
        return TREFOIL
    if not name or "|" in name or name in ("Unknown", "TMC") or "_" not in name:
        return OTHER
    return name


def classify_closed(polygon: np.ndarray) -> str:
    """Knot type of a closed polygon (last vertex joins the first).

    Alexander polynomial of the KMT-reduced polygon, looked up in topoly's knot table.

    Args:
        polygon: Vertices, shape (m, 3), m >= 3, first vertex not repeated at the end.

    Returns:
        ``"unknot"``, ``"trefoil"``, a Rolfsen name such as ``"4_1"``, or ``"other"``.
    """
    topoly, find_matching_knot = _topoly()
    g = topoly.AlexanderGraph(polygon.tolist())
    g.close(method=topoly.Closure.CLOSED)
    g.reduce(method=topoly.ReduceMethod.KMT)
    g.parse_closed()
    poly = g.calc_point(max_cross=MAX_CROSSINGS)
    if "Err" in poly:
        return OTHER
    return knot_name(find_matching_knot(poly, "Alexander"))


def _tie_key(name: str) -> tuple[int, int, str]:
    """Sort key that breaks equal vote counts: unknot, trefoil, named knots, other."""
    if name == UNKNOT:
        return (0, 0, name)
    if name == TREFOIL:
        return (1, 3, name)
    if name == OTHER:
        return (3, 0, name)
    crossings = sum(int(part.split("_")[0]) for part in name.split("#") if part[:1].isdigit())
    return (2, crossings, name)


def plurality(votes: dict[str, int]) -> str:
    """Most frequent name; equal counts go to unknot, then trefoil, then fewer crossings."""
    if not votes:
        raise ValueError("plurality of no votes")
    return min(votes, key=lambda k: (-votes[k], _tie_key(k)))


def closure_votes(
    points: np.ndarray,
    *,
    n_directions: int = DEFAULT_DIRECTIONS,
    stop_early: bool = False,
    classify: Callable[[np.ndarray], str] = classify_closed,
) -> dict[str, int]:
    """Knot type of each ray closure of an open curve, counted.

    For each direction ``d_j`` of :func:`closure_directions` the curve is closed by
    :func:`ray_closure` with ``L = 2 * diameter`` and identified by ``classify``.

    Args:
        points: Open curve, shape (n, 3) [m], first point = held end.
        n_directions: Number of closure directions, >= 1.
        stop_early: Stop as soon as the leading type can no longer be caught up or tied
            (then the counts are partial, but :func:`plurality` of them is the same as of
            the full vote).
        classify: Identifies a closed polygon (m, 3); :func:`classify_closed` by default.

    Returns:
        Votes per knot name; they sum to ``n_directions`` unless stopped early.

    Raises:
        RecordError: ``points`` is not a finite (n, 3) array with n >= 4, or all points
            coincide.
        ConfigError: ``n_directions`` is not an integer >= 1.
    """
    p = normalise(check_points(points))
    dirs = closure_directions(n_directions)
    reach = _REACH_FACTOR * 2.0  # the normalised curve lies in the unit ball: diameter <= 2
    votes: dict[str, int] = {}
    for j, d in enumerate(dirs):
        name = classify(ray_closure(p, d, reach))
        votes[name] = votes.get(name, 0) + 1
        if stop_early:
            counts = sorted(votes.values(), reverse=True) + [0]
            remaining = len(dirs) - j - 1
            if counts[0] > counts[1] + remaining:
                break
    return votes


def classify_centreline(points: np.ndarray, *, n_directions: int = DEFAULT_DIRECTIONS) -> str:
    """Knot type of an open rope centreline (held end first).

    Dominant type over ray closures (see the module docstring): the plurality of
    :func:`closure_votes`; equal counts go to ``"unknot"``, then ``"trefoil"``, then the
    knot with fewer crossings. Invariant under rigid motions and uniform scaling of
    ``points`` and under reversing their order.

    Args:
        points: Centreline, shape (n, 3) [m], n >= 4.
        n_directions: Closure directions voted over, >= 1 (an odd number avoids ties).

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

    ``f = #{i : classify_centreline(frames[i]) == knot} / k``; for shaping a search score.
    Costs one :func:`classify_centreline` per frame.

    Args:
        frames: Centrelines over time, shape (k, n, 3) [m], k >= 1, n >= 4.
        knot: Name counted as knotted.
        n_directions: Closure directions per frame, >= 1.

    Returns:
        Fraction in [0, 1].

    Raises:
        RecordError: ``frames`` is not a finite (k, n, 3) array with k >= 1 and n >= 4.
    """
    f = np.asarray(frames, dtype=float)
    if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] < 1:
        raise RecordError(f"frames: expected an array of shape (k, n, 3), got shape {f.shape}")
    hits = 0
    for i, frame in enumerate(f):
        hits += classify_centreline(check_points(frame, f"frames[{i}]"), n_directions=n_directions) == knot
    return hits / f.shape[0]


def load_centreline(path: str | Path) -> np.ndarray:
    """Read a centreline from ``.npy`` (an (n, 3) array) or ``.csv`` (columns x, y, z).

    A ``.csv`` file may start with one header line (any line that is not three numbers);
    fields are separated by commas.

    Args:
        path: File to read.

    Returns:
        Centreline, shape (n, 3) [m].

    Raises:
        RecordError: Missing file, unknown file name ending, unreadable content, wrong shape,
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
    lines = path.read_text().splitlines()
    for lineno, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        fields = [f.strip() for f in line.split(",")]
        try:
            values = [float(f) for f in fields]
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

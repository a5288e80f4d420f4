"""Knot type of an open curve, decided by a vote over ray closures.

This is the topology kernel; the verdict on a rope held in the fingertip tube (the held end
continued along the tube, where the knot sits, the classes) is :mod:`flyknot.verdict`, which
closes the curve with these functions.

An open curve has no knot type until it is closed. A settled rope hangs from the fingertip,
and its free end may lie anywhere, even above the hand. A closure tied to gravity ("held end
up, free end down") invents knots when the free end is above the hand (measured while the
project was set up), so this module does not use one. Instead, for each direction ``d`` of
a fixed, near-uniform set on the unit sphere, both ends are extended by parallel rays along
``d`` to infinity and joined there (topoly calls this the "rays" closure,
``topoly.Closure.RAYS``, but draws ``d`` at random). The knot type of
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
topoly is consistent. The diagrams and the Alexander polynomial are in
:mod:`flyknot.knot_diagram`; this module checks and reads centrelines and votes over closures.
"""

from __future__ import annotations

import functools
import math
import re
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError, RecordError
from flyknot.knot_diagram import (
    OTHER,
    TREFOIL,
    UNKNOT,
    Diagram,
    alexander_polynomial,
    knot_name,
    normalise,
    project_diagram,
)

__all__ = [
    "CENTRELINE_SUFFIXES",
    "DEFAULT_DIRECTIONS",
    "MAX_CROSSINGS",
    "OTHER",
    "TREFOIL",
    "UNKNOT",
    "check_points",
    "classify_centreline",
    "classify_closure",
    "classify_polygon",
    "closure_directions",
    "closure_votes",
    "knot_fraction",
    "load_centreline",
    "plurality",
]

DEFAULT_DIRECTIONS = 31
"""Closure directions voted over by default (odd, so two types cannot tie)."""

MAX_CROSSINGS = 150
"""Crossings in one projected diagram above which that closure votes ``"other"``."""

CENTRELINE_SUFFIXES = (".csv", ".npy")
"""File name endings :func:`load_centreline` reads."""

_TILTS = (
    1e-3 * np.array([0.6, -0.8, 0.3]),
    1e-2 * np.array([-0.3, 0.2, 0.9]),
    3e-2 * np.array([0.8, 0.5, -0.4]),
)
"""Small deterministic changes of a closure direction, tried in turn when it is degenerate."""

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
    return _directions(_check_n_directions(n)).copy()


@functools.cache
def _directions(n: int) -> np.ndarray:
    """:func:`closure_directions` for a checked ``n``, computed once, read-only."""
    i = np.arange(n)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * _GOLDEN_ANGLE
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)[_van_der_corput_order(n)]
    d.flags.writeable = False
    return d


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
    dirs = _directions(_check_n_directions(n_directions))
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

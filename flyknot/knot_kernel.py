"""The crossing search of :mod:`flyknot.knot_diagram`, compiled (numba).

A knot verdict classifies its rope along some 31 closure directions, and a knot history does
that for every judged frame of a trial: millions of small segment-pair tests, where NumPy
spends its time creating arrays. These loops do the same arithmetic, in the same order and
without fast-math, so they return the same numbers as the array formulas they replace
(``tests/test_knot_kernel.py`` checks them against a plain implementation).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def count_hits(a: np.ndarray, b: np.ndarray, u: np.ndarray, skip: np.ndarray) -> np.ndarray:
    """Proper crossings of each 2-D segment ``a[k] -> b[k]`` with the open polyline ``u``.

    Segment ``a + t r`` (``r = b - a``) meets edge ``e0 + v s`` where ``t, v in (0, 1)``, with
    ``den = r x s``, ``t = (w x s) / den``, ``v = (w x r) / den``, ``w = e0 - a``; parallel
    edges (``den = 0``) never count.

    Args:
        a: Segment starts, shape (K, 2) [-].
        b: Segment ends, shape (K, 2) [-].
        u: Polyline vertices, shape (n, 2) [-]; its edges are ``u[l] -> u[l + 1]``.
        skip: Mask of edges to leave out, shape (n - 1,) (bool).

    Returns:
        Crossing count per segment, shape (K,) (int).
    """
    out = np.zeros(a.shape[0], dtype=np.int64)
    for k in range(a.shape[0]):
        r0 = b[k, 0] - a[k, 0]
        r1 = b[k, 1] - a[k, 1]
        for e in range(u.shape[0] - 1):
            if skip[e]:
                continue
            s0 = u[e + 1, 0] - u[e, 0]
            s1 = u[e + 1, 1] - u[e, 1]
            w0 = u[e, 0] - a[k, 0]
            w1 = u[e, 1] - a[k, 1]
            den = r0 * s1 - r1 * s0
            if den == 0.0:
                continue
            t = (w0 * s1 - w1 * s0) / den
            v = (w0 * r1 - w1 * r0) / den
            if t > 0.0 and t < 1.0 and v > 0.0 and v < 1.0:
                out[k] += 1
    return out


@numba.njit(cache=True)
def _collinear_overlap(a0, a1, r0, r1, c0, c1, s0, s1, lr, ls, eps) -> bool:
    """Parallel segments ``a + t r`` and ``c + v s``: on one line and overlapping?"""
    if lr >= ls:
        f0, f1 = r0, r1
    else:
        f0, f1 = s0, s1
    lref = max(max(lr, ls), 1e-300)
    w0 = c0 - a0
    w1 = c1 - a1
    off = abs(f0 * w1 - f1 * w0) / lref
    e0 = f0 / lref
    e1 = f1 / lref
    p1 = r0 * e0 + r1 * e1
    q0 = w0 * e0 + w1 * e1
    q1 = q0 + (s0 * e0 + s1 * e1)
    lo = max(min(0.0, p1), min(q0, q1))
    hi = min(max(0.0, p1), max(q0, q1))
    return off <= eps and hi >= lo - eps


@numba.njit(cache=True)
def crossings(
    u: np.ndarray,
    h0: np.ndarray,
    h1: np.ndarray,
    i_pairs: np.ndarray,
    j_pairs: np.ndarray,
    eps: float,
    strict: bool,
):
    """Crossings of the closed 2-D polygon ``u`` whose edge k rises from ``h0[k]`` to
    ``h1[k]``, over the edge pairs ``(i_pairs[p], j_pairs[p])`` in that order.

    Edges ``a + t r`` and ``c + v s`` cross properly where ``t, v`` lie in ``(eps / |r|,
    1 - eps / |r|)`` and ``(eps / |s|, 1 - eps / |s|)``; a pair that touches within ``eps``
    (or is collinear and overlapping) is degenerate. The upper strand is the one with the
    larger interpolated height; the sign is ``sign(o x w)`` for the upper strand's 2-D
    direction ``o`` and the lower's ``w``.

    Returns:
        ``(degenerate, over, under, sign)``: with ``strict``, ``degenerate`` is True (and the
        arrays empty) as soon as a degenerate pair or two crossing strands within ``eps`` in
        height are found; otherwise such pairs are skipped. ``over``/``under`` are the
        positions (edge index + parameter) of the upper/lower strand, shape (c,).
    """
    m = u.shape[0]
    n_pairs = i_pairs.shape[0]
    over = np.empty(n_pairs)
    under = np.empty(n_pairs)
    sign = np.empty(n_pairs, dtype=np.int64)
    hit_i = np.empty(n_pairs, dtype=np.int64)
    hit_j = np.empty(n_pairs, dtype=np.int64)
    hit_t = np.empty(n_pairs)
    hit_v = np.empty(n_pairs)
    c = 0
    for p in range(n_pairs):
        i = i_pairs[p]
        j = j_pairs[p]
        i1 = (i + 1) % m
        j1 = (j + 1) % m
        a0, a1 = u[i, 0], u[i, 1]
        r0, r1 = u[i1, 0] - a0, u[i1, 1] - a1
        c0, c1 = u[j, 0], u[j, 1]
        s0, s1 = u[j1, 0] - c0, u[j1, 1] - c1
        w0, w1 = c0 - a0, c1 - a1
        den = r0 * s1 - r1 * s0
        lr = np.sqrt(r0 * r0 + r1 * r1)
        ls = np.sqrt(s0 * s0 + s1 * s1)
        if not abs(den) > 1e-12 * lr * ls:  # parallel or zero-length edges
            if strict and _collinear_overlap(a0, a1, r0, r1, c0, c1, s0, s1, lr, ls, eps):
                return True, over[:0], under[:0], sign[:0]
            continue
        t = (w0 * s1 - w1 * s0) / den
        v = (w0 * r1 - w1 * r0) / den
        et = eps / lr
        es = eps / ls
        if t > et and t < 1 - et and v > es and v < 1 - es:
            hit_i[c], hit_j[c], hit_t[c], hit_v[c] = i, j, t, v
            c += 1
        elif t >= -et and t <= 1 + et and v >= -es and v <= 1 + es and strict:
            return True, over[:0], under[:0], sign[:0]
    n = 0
    for q in range(c):
        i, j, t, v = hit_i[q], hit_j[q], hit_t[q], hit_v[q]
        hi = h0[i] + t * (h1[i] - h0[i])
        hj = h0[j] + v * (h1[j] - h0[j])
        if strict and abs(hi - hj) <= eps:
            return True, over[:0], under[:0], sign[:0]
        i1 = (i + 1) % m
        j1 = (j + 1) % m
        r0, r1 = u[i1, 0] - u[i, 0], u[i1, 1] - u[i, 1]
        s0, s1 = u[j1, 0] - u[j, 0], u[j1, 1] - u[j, 1]
        if hi > hj:
            over[n], under[n] = i + t, j + v
            x = r0 * s1 - r1 * s0
        else:
            over[n], under[n] = j + v, i + t
            x = s0 * r1 - s1 * r0
        sign[n] = 1 if x > 0 else (-1 if x < 0 else 0)
        n += 1
    return False, over[:n], under[:n], sign[:n]

"""The rope's air drag, compiled (numba): :func:`flyknot_sim.aero.rope_drag_forces` in two calls.

The lab recomputes the drag every command tick; the NumPy function's ~25 small array
operations cost ~60 us a call. :func:`segment_flow` and :func:`drag_into` do the same
operations, element by element, in the same order and without fast-math (the dot products
summed as NumPy's ``einsum`` sums three terms); the drag coefficient's power and the end
weight's speed stay NumPy's own (its SIMD power and BLAS dot product round differently from
the C library's), so the forces are the NumPy function's bit for bit. The summation order is
NumPy's choice, so :func:`flyknot_sim.aero.compiled_drag_matches` checks the two on random
states once per process and the lab uses the kernel only when they agree bit for bit;
:func:`flyknot_sim.aero.rope_drag_forces` stays the readable reference.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["drag_into", "segment_flow"]


@numba.njit(cache=True)
def _dot3(a, b):
    """a . b summed as NumPy's ``einsum("ij,ij->i")`` sums three terms: (x + z) + y."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


@numba.njit(cache=True)
def segment_flow(x, v, seg_out):
    """Per segment i, into ``seg_out[i]`` (n, 9): length l [m], |v_n| [m/s], v_t . t [m/s],
    then v_n (3) and v_t (3) [m/s] (module :mod:`flyknot_sim.aero`'s quantities).

    Args:
        x: Vertex positions (n + 1, 3) [m].
        v: Vertex velocities relative to still air (n + 1, 3) [m/s].
        seg_out: Output (n, 9), overwritten.
    """
    n = x.shape[0] - 1
    seg = np.empty(3)
    t = np.empty(3)
    vs = np.empty(3)
    for i in range(n):
        for a in range(3):
            seg[a] = x[i + 1, a] - x[i, a]
        length = math.sqrt(_dot3(seg, seg))
        scale = max(length, 1e-12)
        for a in range(3):
            t[a] = seg[a] / scale
            vs[a] = 0.5 * (v[i + 1, a] + v[i, a])
        vt_mag = _dot3(vs, t)
        for a in range(3):
            seg_out[i, 6 + a] = vt_mag * t[a]
            seg_out[i, 3 + a] = vs[a] - seg_out[i, 6 + a]
        seg_out[i, 0] = length
        seg_out[i, 1] = math.sqrt(_dot3(seg_out[i, 3:6], seg_out[i, 3:6]))
        seg_out[i, 2] = vt_mag


@numba.njit(cache=True)
def drag_into(flow, cd, c_n, c_t, v_end, end_coef, out):
    """Drag forces on the vertices into ``out`` (n + 1, 3) [N] from :func:`segment_flow`.

    Per segment ``f = -1/2 (k_n v_n + k_t v_t)`` with ``k_n = c_n l C_D |v_n|`` and
    ``k_t = c_t l |v_t . t|``, split equally onto its two vertices; then ``-end_coef v_end``
    on the last vertex (the end weight's drag; 0: none).

    Args:
        flow: :func:`segment_flow`'s output (n, 9).
        cd: Cross-flow drag coefficient per segment (n,) [-].
        c_n: 1/2 rho D [kg/m^2].
        c_t: 1/2 rho C_t pi D [kg/m^2].
        v_end: The last vertex's velocity (3,) [m/s].
        end_coef: 1/2 rho C_D,s pi R^2 |v_end| [kg/s].
        out: Output (n + 1, 3), overwritten [N].
    """
    n = flow.shape[0]
    f_seg = np.empty((n, 3))
    for i in range(n):
        kn = c_n * flow[i, 0] * cd[i] * flow[i, 1]
        kt = c_t * flow[i, 0] * abs(flow[i, 2])
        for a in range(3):
            f_seg[i, a] = -0.5 * (kn * flow[i, 3 + a] + kt * flow[i, 6 + a])
    for k in range(n + 1):  # as NumPy: f = 0; f[1:] += f_seg; f[:-1] += f_seg
        for a in range(3):
            out[k, a] = 0.0
            if k > 0:
                out[k, a] += f_seg[k - 1, a]
            if k < n:
                out[k, a] += f_seg[k, a]
    if end_coef != 0.0:
        for a in range(3):
            out[n, a] -= end_coef * v_end[a]

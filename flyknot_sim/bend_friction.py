"""Hysteretic (frictional) bending of the rope: a Grosberg frictional couple at every joint.

A yarn or fabric bends against the friction of its fibres sliding on each other: its bending
moment is M = M_0 sgn(dkappa/dt) + B kappa (P. Grosberg, "The mechanical properties of woven
fabrics part II: the bending of woven fabrics", Textile Research Journal 36 (1966) 205-211).
The elastic part B kappa is MuJoCo's rod elasticity (``flyknot_sim.rope``); this module adds
the frictional couple M_0 sgn(dkappa/dt), computed here, vectorised over the joints, and
applied as passive forces on the vertices' world-axis slides (``qfrc_applied``) before every
step, like the air drag (:mod:`flyknot_sim.aero`).

Kinematics. Vertices x_0..x_n, velocities v_0..v_n. Segment j (x_j to x_{j+1}),
e_j = x_{j+1} - x_j, turns at the perpendicular angular velocity
w_j = e_j x (v_{j+1} - v_j) / |e_j|^2 (its spin about e_j is invisible to point vertices).
At an interior vertex (joint) k = 1..n-1 the relative rotation rate is dw_k = w_k - w_{k-1}.

Objectivity (a deviation from using dw_k as it is). A rigid rotation Omega of a *bent* rope
gives w_j = Omega - (Omega . t_j) t_j, so dw_k = (Omega . t_{k-1}) t_{k-1} - (Omega . t_k) t_k
is not zero when Omega has a component in the joint's bending plane (e.g. a bent rope whirled
about the vertical): a couple on dw_k would brake rigid rotations. The part of dw_k in
span(t_{k-1}, t_k) is exactly what the unknown segment spins can change, so the rate used is
the rest: r_k = P_k dw_k with P_k the projector onto the complement of span(t_{k-1}, t_k). At
a bent joint r_k = (b_k . dw_k) b_k, b_k the unit binormal: the rate of the joint's turning
angle. At a straight joint the span is one line and r_k = dw_k (bending in any direction).
The projector is Tikhonov-regularised (:data:`SPAN_REGULARISATION`) so that it passes
smoothly between the two; it stays symmetric with eigenvalues in [0, 1]. The rotation of a
bent joint's plane about its bisector is rigid for its three vertices and draws no couple
(without twist dofs the rope has no material frame to tell it from bending).

Couple. M_k = -M_0 r_k / sqrt(|r_k|^2 + r_0^2) (Grosberg's sgn, regularised by
:data:`RATE0`), taken at the end of the step (below). M_k acts +M_k on segment k and -M_k
on segment k - 1 (equal and opposite: no net couple). A couple C on segment j is applied as
the force F = (C x e_j) / |e_j|^2 at x_{j+1} and -F at x_j (moment e_j x F = C minus its
component along e_j, the twist, which is dropped; M_k is perpendicular to both of its segments,
so nothing is dropped at a bent joint). The forces sum to zero; their power is
sum_k M_k . dw_k, which is -sum_k c_k dw_k . P_k dw_k <= 0 at the current rates and
-dw . (K^-1 + dt A)^-1 dw <= 0 at the end of the step (P_k symmetric with eigenvalues in
[0, 1]): they never add energy.

Stability. Near r_k = 0 the couple is a viscous damper M = -c r, c = M_0 / r_0. The couples
move the joint rates by d(dw)/dt = A M, A = J m^-1 J^T (J: dw = J v; m: vertex masses); for a
straight uniform rope (vertex mass m, segment length l) A's rows are [1, -4, 6, -4, 1] / (m l^2),
largest eigenvalue 16 / (m l^2). Explicit Euler on the damper is stable for
c dt 16 / (m l^2) < 2 and does not overshoot (cannot reverse r_k in one step) for

    M_0 / r_0 = c <= m l^2 / (16 dt).

Rope 1 (m = 0.04 kg/m * 36.7 mm = 1.47 g, l = 36.7 mm) at dt = 1 ms: c <= 1.2e-4 N m s, i.e.
M_0 <= 6e-6 N m at r_0 = 0.05 rad/s -- three orders of magnitude below the magnitudes below
(and any r_0 large enough to satisfy it, ~80 rad/s at M_0 = 0.01 N m, turns the friction into a
weak viscous damper; capping c at that bound was tried: the swing then barely decays). So the
couples are not taken at the current rates but at the end of the step (``dt > 0`` in
:func:`rope_bend_friction_forces`, what :class:`RopeBendFriction` uses): linearised backward
Euler of the couples alone,

    (I + dt A K) y = dw,   K = blockdiag(c_k P_k),   M = -K y,

with c_k = M_0 / sqrt(|P_k y_k|^2 + r_0^2) refined by :data:`IMPLICIT_ITERATIONS` fixed-point
passes (starting from the current rates). It is stable for any M_0, r_0, dt; the eigenvalues of
(I + dt A K)^-1 lie in (0, 1], so the couples can stop the joints' relative rotation within a
step but never reverse it; a joint slips at ~M_0 when stopping it would need more, and sticks
(creeps at <~ r_0) otherwise. Other forces (gravity, elasticity, constraints) stay explicit in
the solve, so a bend held by a static moment below M_0 still creeps at about dt A Q. A is
built from the vertex masses with the held vertices 0 and 1 as infinitely heavy; it is
block-pentadiagonal and solved banded (LAPACK ``dgbsv``, half-bandwidth 8).

Measured (rope 1 held at its top, released at 20 degrees, air drag on, dt = 1 ms): the free
end's speed stays below 3 cm/s after 6.3 s for M_0 = 0.02 N m and 12.5 s for 0.01; with 0.005,
0.002 and 0 it still moves (0.06, 0.39, 0.72 m/s peaks) in the 20th second. The swing decays
like a Coulomb-damped pendulum: the top joint slips at ~M_0, ~4 M_0 / K = 0.1 rad of amplitude
per cycle for M_0 = 0.01 N m (K = 0.42 N m/rad the rope's gravity stiffness about the hold).

Magnitude. Kawabata's KES-FB2 pure-bending tester measures the hysteresis width 2HB = 2 M_0
of fabrics. A rope's M_0 = (HB / B) EI comes from its ``bend_hysteresis`` HB / B
(``assets/ropes.toml``: 54 1/m for cotton, bracket 23-54 1/m from cotton-type fabrics, no
published value for cords); ropes without it (latex, the chain) have no couple.

Link friction (a chain: the lab's rope 6; none unless a rope sets ``link_friction_radius``).
A link chain has no bending stiffness, but its links rub where they bear on each other: a
joint that turns slides one link's wire over the next one's under the chain's tension T, and
the friction force mu T acts at about the wire's radius r from the joint's axis, a couple
mu T r against the turn. With a rope's
``link_friction_radius`` r > 0 the couple of joint k is

    M_0,k = M_0 + mu r T_k      (mu: the rope's ``friction``; ``RopeParams.link_friction_arm``)

and everything above holds per joint (c_k = M_0,k / sqrt(|r_k|^2 + r_0^2); the end-of-step
solve already treats the joints one by one, and a joint with M_0,k = 0 has c_k = 0). A
segment spans about two links (a 5 mm short-link chain's pitch is 21 mm, a segment 37 mm);
joints in series carry the same moment, so a segment's joint slips at the couple of one link
joint, mu T r.

The tension T_k is the one the simulation carries: the constraint forces MuJoCo solved at
the previous step for the rope's edge-length equality (one row per edge; edge j's tension is
-efc_force of its row, :func:`edge_tensions`), the mean of the two edges meeting at joint k,
a compressed edge counted as 0; joint 1 takes the edge below's alone, edge 0 lying between
the two held vertices whose hold equalities take part of its load (:func:`joint_tensions`).
Not the quasi-static weight below, T_k = g (m_end + lambda (L - s_k)): that is the tension
of a rope hanging still from its held end only, and wrong wherever the rope does anything
else -- many times larger in a throw, zero in a slack chain in flight (links free), set by
the capstan over a rod, by the knot in a knot, by the floor where it lies. The constraint
forces are solved anyway; reading them costs one pass over the equality rows per step. At
rest they are the weight below (rope 6 hanging still: edges 1..29 carry g (m_end + lambda l
(n - j - 1/2)) within 1e-8 of it, relative), so the joints' means equal g (m_end + lambda (L
- s_k)) exactly for k >= 2 and joint 1 carries half a segment's weight less (1.6 % on rope
6). They are one step (1 ms) old, and noisy in contact; neither can add energy: for any
M_0,k >= 0 the couples only oppose the joints' rates (the power above). Before any
constraint was solved (no rows in ``data``, e.g. before the first ``mj_forward``) T = 0: the
constant M_0 alone.

r for the lab's chain (rope 6, "3/8 inch chain", 0.514 kg/m, 20 mm wide): not its US trade
size, which names the wire (3/8" = 9.5 mm; a rule of thumb of anchor-chain makers puts a
chain's weight at 10 d^2 lb/ft, d the wire in inches: 1.4 lb/ft = 2.1 kg/m at 3/8", four
times rope 6's; the same rule gives rope 6 a 4.7 mm wire), but a 5 mm short-link chain: DIN
5685A 5 x 21, outside width 20 mm, 0.50 kg/m (manufacturers' DIN 5685A tables; DIN 766 5 x
18.5, 17 mm wide, is the near alternative). r = 2.5 mm (``assets/ropes.toml``), mu r =
1.4e-3 m: M_0,k from 8.2e-3 N m at the top joint to 9.6e-4 N m at the last (T 5.8 to 0.68 N
hanging still).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.linalg import lapack

from flyknot.errors import ConfigError, check_nonnegative, check_positive
from flyknot.geometry import skew

__all__ = [
    "RATE0",
    "SPAN_REGULARISATION",
    "BendFrictionParams",
    "RopeBendFriction",
    "bend_rates",
    "edge_tensions",
    "joint_moments",
    "joint_tensions",
    "rope_bend_friction_forces",
]

RATE0 = 0.05
"""Regularisation rate r_0 of the sign in M_0 sgn(r) [rad/s].

Below it the couple behaves as a viscous damper (coefficient M_0 / r_0) instead of switching
sign as the joint's rate crosses zero (a sticking joint creeps at <~ r_0). 0.05 rad/s is ~4 %
of the top joint's rate in a 20 degree swing of rope 1 (~1.3 rad/s), so a slipping joint
meets > 99.8 % of M_0. Explicitly (couples at the current rates) this damper would be stable
only for M_0 / r_0 <= m l^2 / (16 dt), ~1.2e-4 N m s for rope 1 at 1 ms, which no useful M_0
meets; stability comes from the end-of-step solve, not from r_0 (module docstring)."""

SPAN_REGULARISATION = 1e-10
"""Tikhonov weight lambda of the projector off span(t_{k-1}, t_k) [-].

The projector switches from two dimensions (bent joint) to one (straight joint) around a
turning angle ~sqrt(2 lambda) = 1.4e-5 rad; a rigid rotation Omega leaves a rate of at most
|Omega| sqrt(lambda / 2) = 7e-6 |Omega| (7e-5 rad/s at 10 rad/s, ~1e-3 of r_0)."""

IMPLICIT_ITERATIONS = 3
"""Fixed-point iterations c_k <- M_0 / sqrt(|P_k y_k|^2 + r_0^2) of the end-of-step solve."""

_HALF_BAND = 8  # scalar half-bandwidth of the block-pentadiagonal joint system (3 * 2 + 2)
_TINY = 1e-24  # floor of |e|^2 [m^2] (a zero-length segment carries no couple)


@dataclass(frozen=True)
class BendFrictionParams:
    """Frictional (hysteretic) bending couple of the rope, as a lab switch.

    Attributes:
        moment: Grosberg's frictional couple M_0 = HB [N m], or None (the default): the rope's
            own, ``RopeParams.frictional_couple`` (its material's ``bend_hysteresis`` times
            its EI, ``assets/ropes.toml``); 0 turns the couple off.
    """

    moment: float | None = None

    def __post_init__(self) -> None:
        if self.moment is not None:
            check_nonnegative("moment", self.moment)

    def moment_for(self, rope) -> float:
        """M_0 [N m] for ``rope`` (a :class:`flyknot_sim.rope_table.RopeParams`)."""
        return rope.frictional_couple if self.moment is None else float(self.moment)


def bend_rates(x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Objective relative rotation rates of the rope's joints (module docstring).

    Args:
        x: Vertex positions, shape (n + 1, 3) [m], n >= 2.
        v: Vertex velocities, shape (n + 1, 3) [m/s].

    Returns:
        (r, e, inv_l2): the rates r_k of the joints k = 1..n-1, shape (n - 1, 3) [rad/s]; the
        segments e_j, shape (n, 3) [m]; 1 / |e_j|^2, shape (n,) [1/m^2].
    """
    e = x[1:] - x[:-1]
    l2 = np.einsum("ij,ij->i", e, e)
    inv_l2 = 1.0 / np.maximum(l2, _TINY)
    w = np.cross(e, v[1:] - v[:-1]) * inv_l2[:, None]
    dw = w[1:] - w[:-1]
    t = e * np.sqrt(inv_l2)[:, None]
    ta, tb = t[:-1], t[1:]
    c = np.einsum("ij,ij->i", ta, tb)
    a1 = np.einsum("ij,ij->i", dw, ta)
    a2 = np.einsum("ij,ij->i", dw, tb)
    g = 1.0 + SPAN_REGULARISATION
    det = g * g - c * c
    s1 = (g * a1 - c * a2) / det
    s2 = (g * a2 - c * a1) / det
    r = dw - s1[:, None] * ta - s2[:, None] * tb
    return r, e, inv_l2


def joint_tensions(edge_tension: np.ndarray) -> np.ndarray:
    """The tension T_k at each joint k = 1..n-1 from the edges' tensions (module docstring,
    link friction): the mean of the two edges meeting there, compressions counted as 0; at
    joint 1 the edge below's alone (edge 0 lies between the two held vertices, whose hold
    equalities take part of its load).

    Args:
        edge_tension: Tension of each edge j = 0..n-1, shape (n,) [N] (negative: compressed).

    Returns:
        Shape (n - 1,) [N], >= 0.
    """
    t = np.maximum(np.asarray(edge_tension, dtype=float), 0.0)
    above = t[:-1].copy()
    above[0] = t[1]
    return 0.5 * (above + t[1:])


def edge_tensions(data, edge_equality: int, n: int) -> np.ndarray | None:
    """The tension of each of the rope's n edges [N] from the constraint forces MuJoCo solved
    last (``data.efc_force`` of the edge equality's rows, one per edge in edge order, tension
    = -efc_force), shape (n,); None when ``data`` holds no such n rows (no constraint solved
    yet, e.g. before the first ``mj_forward``)."""
    rows = np.flatnonzero(
        (data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY) & (data.efc_id == edge_equality)
    )
    if len(rows) != n:
        return None
    return -data.efc_force[rows]


def joint_moments(moment: float, arm: float, edge_tension: np.ndarray | None, n: int) -> np.ndarray:
    """Each joint's frictional couple M_0 + arm T_k, shape (n - 1,) [N m] (module docstring,
    link friction; ``arm`` = mu r [m], T_k by :func:`joint_tensions`; ``edge_tension`` None:
    T = 0)."""
    out = np.full(n - 1, float(moment))
    if arm > 0 and edge_tension is not None:
        out += arm * joint_tensions(edge_tension)
    return out


def _projectors(e: np.ndarray, inv_l2: np.ndarray) -> np.ndarray:
    """The regularised projectors P_k off span(t_{k-1}, t_k), shape (n - 1, 3, 3)."""
    t = e * np.sqrt(inv_l2)[:, None]
    ta, tb = t[:-1], t[1:]
    c = np.einsum("ij,ij->i", ta, tb)
    g = 1.0 + SPAN_REGULARISATION
    det = g * g - c * c
    aa = np.einsum("ij,ik->ijk", ta, ta)
    bb = np.einsum("ij,ik->ijk", tb, tb)
    ab = np.einsum("ij,ik->ijk", ta, tb)
    sym = g * (aa + bb) - c[:, None, None] * (ab + ab.transpose(0, 2, 1))
    return np.eye(3) - sym / det[:, None, None]


def _joint_blocks(e: np.ndarray, inv_l2: np.ndarray) -> list[np.ndarray]:
    """The 3x3 blocks of J (dw = J v) of joint k on vertices k - 1, k, k + 1, each (n - 1, 3, 3)."""
    sk = skew(e) * inv_l2[:, None, None]  # w_j = sk_j (v_{j+1} - v_j)
    return [sk[:-1], -sk[1:] - sk[:-1], sk[1:]]


def _joint_mobility(blocks: list[np.ndarray], inv_mass: np.ndarray) -> list[np.ndarray]:
    """The block diagonals d = 0, 1, 2 of A = J m^-1 J^T (joint rates per joint couple).

    Joints k and k + d share the vertices k + d - 1 .. k + 1, so A is block-pentadiagonal;
    returns A_{k,k+d}, each (n - 1 - d, 3, 3).
    """
    nj = len(blocks[0])
    diags = []
    for d in range(min(3, nj)):
        blk = np.zeros((nj - d, 3, 3))
        for b in range(3 - d):
            im = inv_mass[b + d : b + d + nj - d][:, None, None]
            lhs = blocks[b + d][: nj - d] * im
            rhs = blocks[b][d:]
            blk += (lhs[:, :, None, :] * rhs[:, None, :, :]).sum(-1)
        diags.append(blk)
    return diags


@functools.lru_cache(maxsize=8)
def _band_index(nj: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (band row, column, dense row) of the band storage of a (3 nj)^2 matrix with
    half-bandwidth 8 in LAPACK dgbsv's layout (8 extra rows on top for the LU fill-in):
    ab[16 + i - j, j] = a[i, j]."""
    size = 3 * nj
    i, j = np.nonzero(np.abs(np.subtract.outer(np.arange(size), np.arange(size))) <= _HALF_BAND)
    return 2 * _HALF_BAND + i - j, j, i


def _solve_end_rates(
    diags: list[np.ndarray], stiff: np.ndarray, dt: float, dw: np.ndarray
) -> np.ndarray:
    """Solve (I + dt A K) y = dw for the joints' end-of-step rates y, shape (n - 1, 3)."""
    nj = len(stiff)
    a4 = np.zeros((nj, 3, nj, 3))
    idx = np.arange(nj)
    for d, blk in enumerate(diags):
        ii = idx[: nj - d]
        # (A K)_{k,k+d} = A_{k,k+d} K_{k+d}; (A K)_{k+d,k} = A_{k,k+d}^T K_k.
        a4[ii, :, ii + d, :] = dt * (blk[:, :, :, None] * stiff[d:][:, None, :, :]).sum(2)
        if d:
            up = blk.transpose(0, 2, 1)
            a4[ii + d, :, ii, :] = dt * (up[:, :, :, None] * stiff[: nj - d][:, None, :, :]).sum(2)
    lhs = a4.reshape(3 * nj, 3 * nj)
    lhs[np.diag_indices(3 * nj)] += 1.0
    brow, col, row = _band_index(nj)
    ab = np.zeros((3 * _HALF_BAND + 1, 3 * nj))
    ab[brow, col] = lhs[row, col]
    _, _, y, info = lapack.dgbsv(_HALF_BAND, _HALF_BAND, ab, dw.reshape(-1), overwrite_ab=1)
    if info != 0:  # pragma: no cover - I + dt A K is non-singular (A, K positive semidefinite)
        raise np.linalg.LinAlgError(f"dgbsv failed with info {info}")
    return y.reshape(nj, 3)


def rope_bend_friction_forces(
    x: np.ndarray,
    v: np.ndarray,
    moment: float,
    rate0: float = RATE0,
    inv_mass: np.ndarray | None = None,
    dt: float = 0.0,
) -> np.ndarray:
    """Forces of the frictional bending couples on the rope's vertices (module docstring).

    Args:
        x: Vertex positions, held end first, shape (n + 1, 3) [m], n >= 2.
        v: Vertex velocities, shape (n + 1, 3) [m/s].
        moment: Frictional couple M_0 [N m] (>= 0): one for every joint, or each joint's,
            shape (n - 1,) (e.g. :func:`joint_moments`, with the links' friction).
        rate0: Regularisation rate r_0 of the sign [rad/s] (> 0).
        inv_mass: Inverse vertex masses 1 / m_v, shape (n + 1,) [1/kg] (0 for a held vertex);
            needed when ``dt > 0``.
        dt: Time step the forces are applied over [s]; > 0: the couples are taken at the end
            of the step (linearised backward Euler, module docstring), 0: at the current rates
            (explicit; for analysis, unstable in a simulation for any useful M_0).

    Returns:
        Forces on the vertices, shape (n + 1, 3) [N]; they sum to zero.
    """
    r, e, inv_l2 = bend_rates(x, v)
    moment = np.broadcast_to(np.asarray(moment, dtype=float), (len(r),))
    coef = moment / np.sqrt(np.einsum("ij,ij->i", r, r) + rate0 * rate0)
    if dt > 0:
        if inv_mass is None:
            raise ValueError("inv_mass is needed when dt > 0")
        blocks = _joint_blocks(e, inv_l2)
        proj = _projectors(e, inv_l2)
        diags = _joint_mobility(blocks, np.asarray(inv_mass, dtype=float))
        dw = (
            np.einsum("kij,kj->ki", blocks[0], v[:-2])
            + np.einsum("kij,kj->ki", blocks[1], v[1:-1])
            + np.einsum("kij,kj->ki", blocks[2], v[2:])
        )
        for it in range(IMPLICIT_ITERATIONS):
            stiff = coef[:, None, None] * proj  # K_k = c_k P_k
            y = _solve_end_rates(diags, stiff, dt, dw)
            if it + 1 < IMPLICIT_ITERATIONS:
                ry = np.einsum("kij,kj->ki", proj, y)
                coef = moment / np.sqrt(np.einsum("ij,ij->i", ry, ry) + rate0 * rate0)
        m = -np.einsum("kij,kj->ki", stiff, y)
    else:
        m = -coef[:, None] * r
    couple = np.zeros_like(e)
    couple[1:] += m
    couple[:-1] -= m
    f_seg = np.cross(couple, e) * inv_l2[:, None]
    f = np.zeros_like(x, dtype=float)
    f[1:] += f_seg
    f[:-1] -= f_seg
    return f


_NO_ROWS = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0))
"""Empty constraint rows (efc_type, efc_id, efc_force) for the kernel when the links' friction
is off: the same types as ``data``'s, so that the kernel is compiled once."""


@functools.lru_cache(maxsize=1)
def _warm_kernel() -> None:
    """Compile (or load from numba's cache) the kernel now, once per process: not at the first
    step of a trial, which may run against a clock (the real-time fake lab)."""
    from flyknot_sim.bend_kernel import add_bend_friction, bend_friction_forces

    x = np.column_stack([np.arange(4.0), np.zeros(4), np.zeros(4)])
    bend_friction_forces(x, np.zeros((4, 3)), np.full(2, 1e-3), RATE0, np.ones(4), 1e-3,
                         SPAN_REGULARISATION, IMPLICIT_ITERATIONS, _TINY)  # fmt: skip
    idx = np.arange(12).reshape(4, 3)
    params = np.array([1e-3, RATE0, 1e-3, SPAN_REGULARISATION, _TINY, 0.0])
    add_bend_friction(x.ravel(), np.zeros(12), np.zeros(12), idx, idx, np.zeros((4, 3)),
                      np.zeros((4, 3)), np.zeros((4, 3)), False, params, np.ones(4),
                      IMPLICIT_ITERATIONS, *_NO_ROWS, 0)  # fmt: skip


class RopeBendFriction:
    """Adds :func:`rope_bend_friction_forces` to a bound rope's ``qfrc_applied`` every step.

    Order: the drag (:class:`flyknot_sim.aero.RopeDrag`) *writes* ``qfrc_applied`` of the
    rope's dofs (``=``); this applier *adds* (``+=``), so call it after the drag, before
    ``mj_step``, at every step (its forces are the end-of-step couples for
    ``model.opt.timestep``, so they must not be held for several steps the way the drag is held
    for 4 ms). It replaces its own previous contribution: if ``qfrc_applied`` of the rope's
    dofs is unchanged since its last call (the drag was held, not rewritten), it first subtracts
    what it added then; if something rewrote them, it adds on top of the new values.

    The vertex masses are the model's (``data.model``); the two held vertices count as
    infinitely heavy (the hold equalities pin them). With the links' friction (``link_arm``
    > 0) each joint's couple is M_0 + link_arm T_k, T_k from the edge constraint forces of the
    last step (module docstring, link friction).
    """

    def __init__(self, rope, moment: float, rate0: float = RATE0, link_arm: float | None = None):
        """Bind to ``rope`` (a :class:`flyknot_sim.rope_handle.BoundRope`) with M_0 = ``moment``
        [N m] (0 = off), regularisation rate ``rate0`` [rad/s] and the links' couple per newton
        of tension ``link_arm`` = mu r [m] (None: the rope's own,
        ``RopeParams.link_friction_arm``, 0 unless its ``link_friction_radius`` is set; 0 =
        off)."""
        check_nonnegative("moment", moment)
        check_positive("rate0", rate0)
        if link_arm is None:
            link_arm = rope.params.link_friction_arm
        check_nonnegative("link_arm", link_arm)
        self.rope = rope
        self.moment = float(moment)
        self.rate0 = float(rate0)
        self.link_arm = float(link_arm)
        self._inv_mass: np.ndarray | None = None
        self._model_id: int | None = None
        self._edge_eq: int = -1
        self._added: np.ndarray | None = None
        self._after: np.ndarray | None = None
        self._has_prev = False
        self._kernel_args: tuple | None = None
        if self.on:
            _warm_kernel()

    @property
    def on(self) -> bool:
        """The applier adds forces: M_0 > 0 or the links' friction is on."""
        return self.moment > 0 or self.link_arm > 0

    def inv_mass(self, model) -> np.ndarray:
        """Inverse vertex masses for ``model``, held vertices 0 and 1 at 0 [1/kg] (cached)."""
        if self._inv_mass is None or self._model_id != id(model):
            inv = 1.0 / model.body_mass[self.rope.vert_body]
            inv[:2] = 0.0
            self._inv_mass = inv
            self._edge_eq = self._edge_equality(model) if self.link_arm > 0 else -1
            self._model_id = id(model)
        return self._inv_mass

    def _edge_equality(self, model) -> int:
        """The id of the rope's edge equality in ``model``, checked to give one constraint row
        per edge (no rigid edge)."""
        eq = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_EQUALITY, self.rope.handle.edge_equality)
        if eq < 0:
            raise ConfigError("link_arm", "the rope has no edge equality to read tensions from")
        f = self.rope.flex_id
        adr, num = int(model.flex_edgeadr[f]), int(model.flex_edgenum[f])
        if num != self.rope.n_segments or model.flexedge_rigid[adr : adr + num].any():
            raise ConfigError("link_arm", "needs one edge-equality row per edge (no rigid edge)")
        return eq

    def moments(self, data) -> np.ndarray:
        """Each joint's frictional couple M_0 + link_arm T_k for ``data``'s last solved
        constraint forces, shape (n - 1,) [N m] (:func:`joint_moments`)."""
        self.inv_mass(data.model)
        n = self.rope.n_segments
        tension = edge_tensions(data, self._edge_eq, n) if self.link_arm > 0 else None
        return joint_moments(self.moment, self.link_arm, tension, n)

    def forces(self, data) -> np.ndarray:
        """The couples' forces for ``data``'s current state, shape (n + 1, 3) [N]: those of
        :func:`rope_bend_friction_forces` at the model's step, computed by the compiled
        :func:`flyknot_sim.bend_kernel.bend_friction_forces`."""
        r, model = self.rope, data.model
        x = data.qpos[r.vert_qpos] + r.body_pos0
        v = data.qvel[r.vert_dof]
        from flyknot_sim.bend_kernel import bend_friction_forces  # numba: compiled on demand

        return bend_friction_forces(
            np.ascontiguousarray(x, dtype=float),
            np.ascontiguousarray(v, dtype=float),
            self.moments(data),
            self.rate0,
            self.inv_mass(model),
            float(model.opt.timestep),
            SPAN_REGULARISATION,
            IMPLICIT_ITERATIONS,
            _TINY,
        )

    def apply(self, data) -> None:
        """Add the couples' forces of ``data``'s current state to ``data.qfrc_applied``
        (compiled: :func:`flyknot_sim.bend_kernel.add_bend_friction` gathers the state and the
        joints' tensions, solves and scatters without a numpy temporary)."""
        if not self.on:
            return
        r, model = self.rope, data.model
        if self._kernel_args is None or self._model_id != id(model):
            from flyknot_sim.bend_kernel import add_bend_friction  # numba: compiled on demand

            params = np.array(
                [self.moment, self.rate0, float(model.opt.timestep), SPAN_REGULARISATION, _TINY,
                 self.link_arm]
            )  # fmt: skip
            self._added, self._after = np.zeros(r.vert_dof.shape), np.zeros(r.vert_dof.shape)
            self._has_prev = False
            inv_mass = self.inv_mass(model)
            self._kernel_args = (add_bend_friction, params, inv_mass)
        kernel, params, inv_mass = self._kernel_args
        rows = (data.efc_type, data.efc_id, data.efc_force) if self.link_arm > 0 else _NO_ROWS
        kernel(
            data.qpos, data.qvel, data.qfrc_applied, r.vert_qpos, r.vert_dof, r.body_pos0,
            self._added, self._after, self._has_prev, params, inv_mass, IMPLICIT_ITERATIONS,
            *rows, self._edge_eq,
        )  # fmt: skip
        self._has_prev = True

"""Measurements that chose the rope model: stretch, tunnelling, knot-pull, speed, flying knot.

Run ``python -m flyknot_tools.rope_measure`` (a few minutes on one core) to print the table of
``docs/rope-model.md``; ``--help`` lists the options.

The harness is a "holder" body with three slide and three hinge joints (about y, then x,
then z), each driven by a stiff position servo plus a velocity servo fed with the target's
derivative (feed-forward, so a 4 m/s hand does not lag). The rope hangs from the holder: a
1D flex built by :func:`flyknot_sim.rope.add_rope`, or, for comparison, a chain of capsules
on ball joints (:func:`add_capsule_chain`).

Tests:

* **fast motion**: the reference hand motion that tied a flying knot in the feasibility study
  (``tests/data/reference_hand_motion_rope1.csv``, peak hand speed 3.9 m/s, 180+ degree wrist
  turns), then 1.5 s still. Measured: largest stretch of the whole rope and of one edge,
  centreline crossings (tunnelling), wall seconds per simulated second, knot at the end.
* **knot-pull**: a loose overhand knot (an opened trefoil with straight tails) whose lower end
  is fixed while the holder pulls the upper end up at 4 m/s with a force cap, then holds.
  Measured: crossings, and whether the knot is still a trefoil after the pull.

Tunnelling is detected by :func:`count_crossings`: between two saved frames every vertex
moves on a straight line, and two non-adjacent centreline segments cross when their four end
points become coplanar at a time at which the segments intersect (a cubic in time, solved
exactly on monotone brackets). With self-collision off every test rope crosses itself, so
the check can fail.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

from flyknot.constants import REPO_ROOT
from flyknot.errors import ConfigError
from flyknot.geometry import min_rotation
from flyknot_sim.rope import (
    ROPE_CONAFFINITY,
    ROPE_CONTYPE,
    RopeParams,
    SimSettings,
    add_rope,
    get_rope,
    load_sim_settings,
    polyline_length,
)

REFERENCE_MOTION = REPO_ROOT / "tests" / "data" / "reference_hand_motion_rope1.csv"
"""The flying-knot hand motion of the feasibility study (rope 1), 200 Hz."""

MODEL_KINDS = ("flex", "chain")
HOLDER = "holder"
HOLDER_JOINTS = ("hx", "hy", "hz", "hb", "ha", "hc")
"""Slides along world x, y, z, then hinges about y (b), x (a), z (c): R = Ry(b) Rx(a) Rz(c)."""

SETTLE_S = 1.5


# ----------------------------------------------------------------------------------------
# hand motion
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class HandMotion:
    """A hand trajectory sampled in time.

    Attributes:
        t: Times, shape (k,) [s], increasing.
        pos: Hand positions, shape (k, 3) [m].
        quat: Hand orientations (w, x, y, z), shape (k, 4).
    """

    t: np.ndarray
    pos: np.ndarray
    quat: np.ndarray

    @classmethod
    def load(cls, path: str | Path = REFERENCE_MOTION) -> HandMotion:
        """Read a CSV with columns t, x, y, z, qw, qx, qy, qz (``#`` comments, one header)."""
        a = np.loadtxt(path, delimiter=",", comments="#", skiprows=2)
        return cls(a[:, 0], a[:, 1:4], a[:, 4:8])

    @property
    def duration(self) -> float:
        """t[-1] [s]."""
        return float(self.t[-1])


def hand_angles(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous angles (a, b) with R(quat) = Ry(b) Rx(a) (the holder's hinge chain).

    With R = Ry(b) Rx(a): R e_x = (cos b, 0, -sin b), so b = atan2(-R_20, R_00); and
    M = Ry(b)^T R = Rx(a), so a = atan2(M_21, M_11) with M_21 = sin(b) R_01 + cos(b) R_21,
    M_11 = R_11. Both are unwrapped in time. Orientations with a z-rotation part are not
    representable (the reference motion has none: its residual is < 1e-5 rad).

    Args:
        quat: Unit quaternions (w, x, y, z), shape (k, 4).

    Returns:
        a, b: Angles about x and y, shape (k,) each [rad].
    """
    w, x, y, z = np.asarray(quat, dtype=float).T
    r00 = 1 - 2 * (y * y + z * z)
    r20 = 2 * (x * z - w * y)
    r01 = 2 * (x * y - w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r21 = 2 * (y * z + w * x)
    b = np.unwrap(np.arctan2(-r20, r00))
    a = np.unwrap(np.arctan2(np.sin(b) * r01 + np.cos(b) * r21, r11))
    return a, b


def holder_targets(
    motion: HandMotion, times: np.ndarray, home: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Holder joint targets and their rates at ``times`` (held at the last sample after it).

    q = (x - x_home, y - y_home, z - z_home, b, a, 0), linearly interpolated; qd is the
    interpolated central difference of q, zero after the motion ends.

    Args:
        motion: Hand trajectory.
        times: Query times, shape (T,) [s].
        home: Holder body position at zero joints, shape (3,) [m].

    Returns:
        q (T, 6) [m, rad] and qd (T, 6) [m/s, rad/s].
    """
    a, b = hand_angles(motion.quat)
    q = np.column_stack([motion.pos - home, b, a, np.zeros_like(a)])
    qd = np.gradient(q, motion.t, axis=0)
    qi = np.column_stack([np.interp(times, motion.t, q[:, i]) for i in range(6)])
    qdi = np.column_stack([np.interp(times, motion.t, qd[:, i]) for i in range(6)])
    qdi[times > motion.t[-1]] = 0.0
    return qi, qdi


# ----------------------------------------------------------------------------------------
# capsule chain (comparison model)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CapsuleChain:
    """A rope made of capsules on ball joints, nested under the anchor body.

    The first capsule is welded to the anchor (it leaves along the axis, like the flex's
    held first segment); each further capsule hangs from the previous one on a ball joint
    with stiffness k = EI / l [N m/rad] and damping beta k.
    """

    params: RopeParams
    bodies: tuple[str, ...]
    joints: tuple[str, ...]
    axis: np.ndarray

    def vertex_positions(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Joint centres plus the free tip, shape (n + 1, 3) [m]."""
        ids = [model.body(b).id for b in self.bodies]
        tip = data.xpos[ids[-1]] + data.xmat[ids[-1]].reshape(3, 3) @ (
            self.axis * self.params.segment_length
        )
        return np.vstack([data.xpos[ids], tip])

    def set_vertices(self, model: mujoco.MjModel, data: mujoco.MjData, x: np.ndarray) -> None:
        """Set ball joints so the centreline passes through ``x`` (n + 1, 3) (first segment
        must lie along the anchor's axis); zero the chain's velocities; run mj_kinematics."""
        mujoco.mj_kinematics(model, data)
        parent_r = data.xmat[model.body(self.bodies[0]).id].reshape(3, 3).copy()
        for k, jn in enumerate(self.joints, start=1):
            d = x[k + 1] - x[k]
            r_world = min_rotation(parent_r @ self.axis, d) @ parent_r
            q = np.empty(4)
            mujoco.mju_mat2Quat(q, (parent_r.T @ r_world).ravel())
            j = model.joint(jn)
            data.qpos[j.qposadr[0] : j.qposadr[0] + 4] = q
            data.qvel[j.dofadr[0] : j.dofadr[0] + 3] = 0.0
            parent_r = r_world
        mujoco.mj_kinematics(model, data)


def add_capsule_chain(
    spec: mujoco.MjSpec,
    params: RopeParams,
    *,
    anchor_body: str,
    axis: Sequence[float] = (0.0, 0.0, -1.0),
    settings: SimSettings | None = None,
    prefix: str = "chain",
) -> CapsuleChain:
    """Add a capsule chain with ``params.segments`` capsules under ``anchor_body``."""
    s = load_sim_settings() if settings is None else settings
    ax = np.asarray(axis, dtype=float)
    ax = ax / np.linalg.norm(ax)
    n, seg, r = params.segments, params.segment_length, params.radius
    k = params.bending_stiffness / seg
    parent = spec.body(anchor_body)
    bodies, joints = [], []
    pos = ax * params.clearance
    for i in range(n):
        b = parent.add_body(name=f"{prefix}_{i}", pos=pos)
        if i > 0:
            j = b.add_joint(
                name=f"{prefix}_j{i}",
                type=mujoco.mjtJoint.mjJNT_BALL,
                stiffness=[k],
                damping=params.damping * k,
                armature=1e-7,
            )
            joints.append(j.name)
        b.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[0, 0, 0, *(ax * seg)],
            size=[r, 0, 0],
            mass=params.density * seg,
            contype=ROPE_CONTYPE,
            conaffinity=ROPE_CONAFFINITY,
            friction=[params.friction, 0.005, 0.0001],
            solref=[s.contact_timeconst, s.contact_dampratio],
            solimp=[*s.contact_solimp, 0.5, 2],
        )
        if i == n - 1:
            b.add_geom(
                type=mujoco.mjtGeom.mjGEOM_SPHERE,
                pos=ax * seg,
                size=[params.end_radius, 0, 0],
                mass=params.end_mass,
                contype=ROPE_CONTYPE,
                conaffinity=ROPE_CONAFFINITY,
            )
        bodies.append(b.name)
        parent, pos = b, ax * seg
    return CapsuleChain(params, tuple(bodies), tuple(joints), ax)


# ----------------------------------------------------------------------------------------
# harness
# ----------------------------------------------------------------------------------------
@dataclass
class Harness:
    """A compiled test scene: holder, rope, actuators (``ctrl[0::2]`` position targets,
    ``ctrl[1::2]`` velocity targets of the six holder joints)."""

    model: mujoco.MjModel
    data: mujoco.MjData
    rope: object  # BoundRope or CapsuleChain: vertex_positions(model, data)
    kind: str
    params: RopeParams
    home: np.ndarray

    def vertices(self) -> np.ndarray:
        """Current centreline vertices, (n + 1, 3) [m]."""
        return self.rope.vertex_positions(self.model, self.data)


def build_harness(
    params: RopeParams,
    *,
    kind: str = "flex",
    settings: SimSettings | None = None,
    timestep: float | None = None,
    home: Sequence[float] = (0.0, 0.0, 1.5),
    axis: Sequence[float] = (0.0, 0.0, -1.0),
    integrator: str = "discrete",
    slide_force: float | None = None,
    free_end_at: Sequence[float] | None = None,
    holder_mass: float = 0.5,
    twist: bool = False,
) -> Harness:
    """Compile a holder + rope scene for the measurements.

    Args:
        params: The rope (``segments`` etc. as given).
        kind: ``flex`` (production model) or ``chain`` (capsules on ball joints).
        settings: Solver settings (default: the rope table's).
        timestep: Step [s] (default: ``params.timestep``).
        home: Holder position at zero joints [m].
        axis: Direction the rope leaves the holder in [-].
        integrator: ``discrete``, ``implicit`` or ``implicitfast`` (the latter two only for
            the chain: flex elasticity requires ``discrete``).
        slide_force: Force cap of the holder's slide servos [N] (None: uncapped).
        free_end_at: If given, a connect equality pins the free end to this world point [m].
        holder_mass: Mass of the holder [kg] (gravity-compensated); servo gains scale with it.
        twist: Flex with per-edge twist joints (``flexcomp``), see :func:`add_rope`.
    """
    if kind not in MODEL_KINDS:
        raise ConfigError("kind", f"unknown value {kind!r}", MODEL_KINDS)
    s = load_sim_settings() if settings is None else settings
    spec = mujoco.MjSpec()
    opt = spec.option
    opt.timestep = params.timestep if timestep is None else timestep
    opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{integrator.upper()}")
    opt.solver = getattr(mujoco.mjtSolver, f"mjSOL_{s.solver.upper()}")
    opt.iterations, opt.ls_iterations, opt.tolerance = s.iterations, s.ls_iterations, s.tolerance
    if not s.refsafe:
        opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    spec.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], contype=1, conaffinity=1
    )
    home = np.asarray(home, dtype=float)
    h = spec.worldbody.add_body(name=HOLDER, pos=home, gravcomp=1.0)
    h.add_geom(
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[0.01, 0, 0],
        mass=holder_mass,
        contype=0,
        conaffinity=0,
    )
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 1, 0), (1, 0, 0), (0, 0, 1)]
    for i, (name, ax) in enumerate(zip(HOLDER_JOINTS, axes, strict=True)):
        slide = i < 3
        h.add_joint(
            name=name,
            axis=ax,
            armature=0.0 if slide else 0.01,
            type=mujoco.mjtJoint.mjJNT_SLIDE if slide else mujoco.mjtJoint.mjJNT_HINGE,
        )
        kp, inertia = (4e4 * holder_mass, holder_mass) if slide else (500.0, 0.01)
        a = spec.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=kp)
        v = spec.add_actuator(name=f"{name}_vel", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        v.set_to_velocity(kv=2 * math.sqrt(kp * inertia))
        if slide and slide_force is not None:
            for act in (a, v):
                act.forcelimited = True
                act.forcerange = [-slide_force / 2, slide_force / 2]
    if kind == "flex":
        handle = add_rope(spec, params, anchor_body=HOLDER, axis=axis, settings=s, twist=twist)
        rope_last = handle.vertex_bodies[-1]
    else:
        chain = add_capsule_chain(spec, params, anchor_body=HOLDER, axis=axis, settings=s)
        rope_last = chain.bodies[-1]
    if free_end_at is not None:
        tip = np.zeros(3) if kind == "flex" else chain.axis * params.segment_length
        spec.body(rope_last).add_site(name="free_end", pos=tip)
        spec.worldbody.add_site(name="world_end", pos=np.asarray(free_end_at, dtype=float))
        spec.add_equality(
            type=mujoco.mjtEq.mjEQ_CONNECT,
            objtype=mujoco.mjtObj.mjOBJ_SITE,
            name1="free_end",
            name2="world_end",
            solref=[s.edge_timeconst, 1.0],
        )
    model = spec.compile()
    data = mujoco.MjData(model)
    rope = handle.bind(model) if kind == "flex" else chain
    mujoco.mj_forward(model, data)
    return Harness(model, data, rope, kind, params, home)


# ----------------------------------------------------------------------------------------
# simulation
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Run:
    """A recorded simulation.

    Attributes:
        t: Times of the saved frames, shape (T,) [s].
        vertices: Centreline vertices, shape (T, n + 1, 3) [m].
        wall: Wall time spent in ``mj_step`` [s].
        sim_time: Simulated time [s].
        diverged: Whether MuJoCo reported a divergence (NaN state, auto-reset).
    """

    t: np.ndarray
    vertices: np.ndarray
    wall: float
    sim_time: float
    diverged: bool

    @property
    def wall_per_sim(self) -> float:
        """Wall seconds per simulated second (mj_step only)."""
        return self.wall / self.sim_time


def simulate(h: Harness, q: np.ndarray, qd: np.ndarray) -> Run:
    """Step once per row of the targets, saving the centreline after every step."""
    m, d = h.model, h.data
    n_steps = len(q)
    verts = np.empty((n_steps + 1, *h.vertices().shape))
    verts[0] = h.vertices()
    t0 = d.time
    wall = 0.0
    diverged = False
    for k in range(n_steps):
        d.ctrl[0::2] = q[k]
        d.ctrl[1::2] = qd[k]
        tic = time.perf_counter()
        mujoco.mj_step(m, d)
        wall += time.perf_counter() - tic
        if d.time < t0 + (k + 0.5) * m.opt.timestep:  # auto-reset after a divergence
            diverged = True
        verts[k + 1] = h.vertices()
    if not np.all(np.isfinite(verts)):
        diverged = True
    t = t0 + m.opt.timestep * np.arange(n_steps + 1)
    return Run(t, verts, wall, n_steps * m.opt.timestep, diverged)


def edge_strain(vertices: np.ndarray, segment_length: float) -> np.ndarray:
    """Edge strains |x_{k+1} - x_k| / l - 1, shape (..., n) for vertices (..., n + 1, 3)."""
    return np.linalg.norm(np.diff(vertices, axis=-2), axis=-1) / segment_length - 1.0


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
        a, b, c, d: Points at t = 0, shape (..., 3) [m].
        da, db, dc, dd: Displacements over the interval, shape (..., 3) [m].

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
        x0, x1: Vertices at the start and end of the interval, shape (n + 1, 3) [m].
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
    params: RopeParams, knot_length: float = 0.7, centre: Sequence[float] = (0.0, 0.0, 1.0)
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
    excess = arc[i_knot] - (params.length - knot_length) / 2
    start = int(np.searchsorted(arc, excess))
    x = resample_equal_chords(curve[start:], params.segment_length, params.segments)
    return x + np.asarray(centre, dtype=float)


def place_vertices(h: Harness, x: np.ndarray) -> None:
    """Put the rope's vertices at ``x`` (n + 1, 3) at rest (holder stays where it is)."""
    r = h.rope
    m, d = h.model, h.data
    r.set_vertices(m, d, x)
    mujoco.mj_forward(m, d)


# ----------------------------------------------------------------------------------------
# the tests
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Config:
    """One model configuration to measure."""

    rope: int = 1
    kind: str = "flex"
    segments: int | None = None
    timestep: float | None = None
    integrator: str = "discrete"
    settings: SimSettings | None = None
    twist: bool = False

    def rope_params(self) -> RopeParams:
        """The rope with this configuration's overrides."""
        p = get_rope(self.rope)
        over = {}
        if self.segments is not None:
            over["segments"] = self.segments
        if self.timestep is not None:
            over["timestep"] = self.timestep
        return replace(p, **over) if over else p

    def label(self) -> str:
        """Short description for tables."""
        p = self.rope_params()
        s = self.settings or load_sim_settings()
        return (
            f"rope {self.rope} {self.kind} n={p.segments} dt={p.timestep * 1e3:g}ms "
            f"{self.integrator} {s.solver} it={s.iterations}/{s.ls_iterations} "
            f"tol={s.tolerance:g} self={s.selfcollide}"
        )


def measure_fast_motion(
    cfg: Config,
    settle_s: float = SETTLE_S,
    motion: HandMotion | None = None,
    judge_knot: bool = True,
) -> dict:
    """Replay the reference hand motion, then hold still ``settle_s``; see module docstring."""
    p = cfg.rope_params()
    motion = HandMotion.load() if motion is None else motion
    h = build_harness(
        p, kind=cfg.kind, settings=cfg.settings, integrator=cfg.integrator, home=motion.pos[0]
    )
    dt = h.model.opt.timestep
    n_steps = round((motion.duration + settle_s) / dt)
    times = dt * np.arange(1, n_steps + 1)
    q, qd = holder_targets(motion, times, h.home)
    mujoco.mj_kinematics(h.model, h.data)  # holder at home (zero joints)
    if cfg.kind == "flex":
        h.rope.set_hanging(h.model, h.data)
    run = simulate(h, q, qd)
    strain = edge_strain(run.vertices, p.segment_length)
    total = polyline_length(run.vertices) / p.length - 1
    moving = run.t <= motion.duration + 0.2
    out = {
        "config": cfg.label(),
        "diverged": run.diverged,
        "wall_per_sim": run.wall_per_sim,
        "max_stretch": float(np.max(total[moving])),
        "max_edge_strain": float(np.max(strain[moving])),
        "crossings": count_run_crossings(run.vertices),
    }
    if judge_knot and not run.diverged:
        from flyknot.knot import classify_centreline

        out["knot_end"] = classify_centreline(run.vertices[-1])
        out["knot_any"] = any(
            classify_centreline(v) == "trefoil" for v in run.vertices[:: max(1, int(0.05 / dt))]
        )
    return out


def time_fast_motion(cfg: Config, repeats: int = 3, settle_s: float = 0.5) -> float:
    """Best-of-``repeats`` wall seconds per simulated second (``mj_step`` only) of the
    reference motion plus ``settle_s``; the best run is the least disturbed by other load."""
    p = cfg.rope_params()
    motion = HandMotion.load()
    h = build_harness(
        p,
        kind=cfg.kind,
        settings=cfg.settings,
        integrator=cfg.integrator,
        home=motion.pos[0],
        twist=cfg.twist,
    )
    dt = h.model.opt.timestep
    n_steps = round((motion.duration + settle_s) / dt)
    q, qd = holder_targets(motion, dt * np.arange(1, n_steps + 1), h.home)
    best = math.inf
    for _ in range(repeats):
        mujoco.mj_resetData(h.model, h.data)
        mujoco.mj_kinematics(h.model, h.data)
        if cfg.kind == "flex":
            h.rope.set_hanging(h.model, h.data)
        best = min(best, simulate(h, q, qd).wall_per_sim)
    return best


PULL_FORCE_FACTOR = 25.0
"""Knot-pull force cap in rope weights (rope + end weight): about the peak tension at the hand
in the fast reference motion (rope 1: 12.8 N = 21 weights; rope 4: 4.8 N = 24; rope 5:
21.8 N = 11)."""


PULL_HOLDER_MASS = 0.05
"""Holder mass in the knot-pull [kg]: light, so the force cap (not the holder's momentum)
bounds the tension when the knot jams."""


def measure_knot_pull(
    cfg: Config,
    speed: float = 4.0,
    hold_s: float = 0.4,
    force_cap: float | None = None,
    self_collide: bool = True,
    knot_length: float = 0.7,
) -> dict:
    """Pull a loose overhand knot tight at ``speed`` (see module docstring).

    Args:
        cfg: Model configuration.
        speed: Pull speed of the holder [m/s].
        hold_s: Time held still after the pull [s].
        force_cap: Force cap of the holder's slides [N] (default ``PULL_FORCE_FACTOR`` times
            the weight of rope + end weight).
        self_collide: False disables all contacts (to show that the crossing check works).
        knot_length: Rope length in the initial loose knot [m].
    """
    from flyknot.knot import classify_centreline

    p = cfg.rope_params()
    if force_cap is None:
        force_cap = PULL_FORCE_FACTOR * (p.mass + p.end_mass) * 9.81
    x = overhand_knot_vertices(p, knot_length)
    axis = x[1] - x[0]
    settings = cfg.settings or load_sim_settings()
    home = x[0] - p.clearance * axis / np.linalg.norm(axis)
    h = build_harness(
        p,
        kind=cfg.kind,
        settings=settings,
        integrator=cfg.integrator,
        home=home,
        axis=axis,
        slide_force=force_cap,
        free_end_at=x[-1],
        holder_mass=PULL_HOLDER_MASS,
    )
    place_vertices(h, x)
    knot0 = classify_centreline(h.vertices())
    dt = h.model.opt.timestep
    pull_s = 0.6 / speed
    n_steps = round((pull_s + hold_s) / dt)
    times = dt * np.arange(1, n_steps + 1)
    q = np.zeros((n_steps, 6))
    qd = np.zeros((n_steps, 6))
    q[:, 2] = speed * np.minimum(times, pull_s)
    qd[:, 2] = np.where(times < pull_s, speed, 0.0)
    if not self_collide:
        h.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    run = simulate(h, q, qd)
    return {
        "config": cfg.label(),
        "force_cap": force_cap,
        "knot_before": knot0,
        "diverged": run.diverged,
        "crossings": count_run_crossings(run.vertices),
        "knot_after": classify_centreline(run.vertices[-1]) if not run.diverged else "-",
        "max_edge_strain": float(edge_strain(run.vertices, p.segment_length).max()),
        "end_gap": float(np.linalg.norm(run.vertices[-1, 0] - run.vertices[-1, -1])),
        "wall_per_sim": run.wall_per_sim,
    }


KNOT_LENGTHS = (0.6, 0.636, 0.671, 0.707, 0.743, 0.779, 0.814, 0.85)
"""Initial loose-knot sizes of the repeated knot-pull (the outcome is sensitive to details)."""


def measure_knot_pulls(
    cfg: Config, knot_lengths: Sequence[float] = KNOT_LENGTHS, self_collide: bool = True
) -> dict:
    """:func:`measure_knot_pull` once per initial knot size; counts kept knots and crossings."""
    runs = [measure_knot_pull(cfg, knot_length=k, self_collide=self_collide) for k in knot_lengths]
    return {
        "config": cfg.label(),
        "force_cap": runs[0]["force_cap"],
        "kept": sum(r["knot_after"] == "trefoil" for r in runs),
        "trials": len(runs),
        "crossings": sum(r["crossings"] for r in runs),
        "diverged": sum(r["diverged"] for r in runs),
        "max_edge_strain": max(r["max_edge_strain"] for r in runs),
        "wall_per_sim": float(np.mean([r["wall_per_sim"] for r in runs])),
    }


def measure_shape_error(cfg: Config, ref: Config, t_end: float = 0.5) -> dict:
    """Marker deviation of ``cfg`` from a finer ``ref`` model under the reference motion.

    Both replay the reference hand motion up to ``t_end`` (before the rope first touches
    itself); the 11 markers are compared at the coarser model's frames:
    e = |m_cfg(t) - m_ref(t)| per marker and time.

    Returns:
        ``rms`` and ``max`` of e [m].
    """
    motion = HandMotion.load()
    marks = []
    for c in (cfg, ref):
        p = c.rope_params()
        h = build_harness(
            p,
            kind=c.kind,
            settings=c.settings,
            integrator=c.integrator,
            home=motion.pos[0],
            twist=c.twist,
        )
        dt = h.model.opt.timestep
        n_steps = round(t_end / dt)
        times = dt * np.arange(1, n_steps + 1)
        q, qd = holder_targets(motion, times, h.home)
        mujoco.mj_kinematics(h.model, h.data)
        if c.kind == "flex":
            h.rope.set_hanging(h.model, h.data)
        run = simulate(h, q, qd)
        from flyknot_sim.rope import marker_arclengths, points_at_arclength

        mk = points_at_arclength(run.vertices, p.segment_length, marker_arclengths(p.length))
        marks.append((run.t, mk))
    (t0, m0), (t1, m1) = marks
    idx = np.clip(np.searchsorted(t1, t0 - 1e-9), 0, len(t1) - 1)
    e = np.linalg.norm(m0 - m1[idx], axis=-1)
    return {"rms": float(np.sqrt(np.mean(e**2))), "max": float(e.max())}


VARIANTS: dict[str, dict] = {
    "chosen": {},
    "twist dofs (flexcomp)": {"twist": True},
    "40 segments": {"segments": 40},
    "20 segments": {"segments": 20},
    "dt 2 ms": {"timestep": 0.002},
    "contact solref 4 ms": {"settings": {"contact_timeconst": 0.004}},
    "capsule chain, implicit": {"kind": "chain", "integrator": "implicit"},
}
"""Model variants of the comparison table (changes from the rope table's settings)."""


def variant_config(rope: int, changes: dict) -> Config:
    """The :class:`Config` of a variant of :data:`VARIANTS` for one rope."""
    ch = dict(changes)
    over = ch.pop("settings", None)
    settings = replace(load_sim_settings(), **over) if over else None
    return Config(rope=rope, settings=settings, **ch)


def measure_variant(rope: int, name: str) -> dict:
    """All measurements of one rope and variant (fast motion, 8 knot-pulls, best-of-4 timing
    of the fast motion)."""
    cfg = variant_config(rope, VARIANTS[name])
    t0 = time.perf_counter()
    fast = measure_fast_motion(cfg)
    pull = measure_knot_pulls(cfg)
    fast["wall_per_sim"] = min(fast["wall_per_sim"], time_fast_motion(cfg))
    return {
        "rope": rope,
        "variant": name,
        "config": cfg.label(),
        "fast": fast,
        "pull": pull,
        "elapsed_s": time.perf_counter() - t0,
    }


def format_row(r: dict) -> str:
    """One markdown table row of :func:`measure_variant`'s result."""
    f, p = r["fast"], r["pull"]
    knot = (
        "diverged"
        if f["diverged"]
        else f"{f.get('knot_end', '-')}"
        + (" (formed)" if f.get("knot_any") and f.get("knot_end") != "trefoil" else "")
    )
    return (
        f"| {r['rope']} | {r['variant']} | {f['wall_per_sim']:.3f} | "
        f"{100 * f['max_stretch']:.2f} | {100 * f['max_edge_strain']:.1f} | "
        f"{f['crossings']} | {knot} | {p['kept']}/{p['trials']} | {p['crossings']} |"
    )


TABLE_HEADER = (
    "| rope | variant | wall s / sim s | max stretch % | max edge strain % | crossings "
    "(fast) | knot at end (fast) | knot-pull kept | crossings (pull) |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def main(argv: Sequence[str] | None = None) -> None:
    """Print the comparison table of ``docs/rope-model.md`` (markdown), optionally as JSON."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--ropes", type=int, nargs="*", default=[1, 4, 5, 6])
    ap.add_argument(
        "--variants",
        nargs="*",
        default=list(VARIANTS),
        choices=list(VARIANTS),
        metavar="NAME",
        help=f"any of: {', '.join(VARIANTS)}",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument(
        "--shape",
        action="store_true",
        help="also print marker deviations from a 60-segment, 0.5 ms reference",
    )
    args = ap.parse_args(argv)
    seen: dict[str, int] = {}

    def count_warning(msg: str) -> None:
        key = msg.split(". Time =")[0].strip()
        seen[key] = seen.get(key, 0) + 1

    mujoco.set_mju_user_warning(count_warning)
    rows = []
    print(TABLE_HEADER, flush=True)
    for rope in args.ropes:
        for name in args.variants:
            r = measure_variant(rope, name)
            rows.append(r)
            print(format_row(r), flush=True)
    if args.shape:
        ref = Config(rope=1, segments=60, timestep=0.0005)
        for name in ("chosen", "40 segments", "20 segments", "dt 2 ms"):
            e = measure_shape_error(variant_config(1, VARIANTS[name]), ref)
            print(
                f"shape error rope 1 {name}: rms {1e3 * e['rms']:.1f} mm, "
                f"max {1e3 * e['max']:.1f} mm",
                flush=True,
            )
            rows.append({"shape": name, **e})
    for msg, k in sorted(seen.items()):
        print(f"MuJoCo warning x{k}: {msg}")
    if args.json is not None:
        import json

        args.json.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()

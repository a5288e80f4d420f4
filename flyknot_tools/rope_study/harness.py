"""The rope study's harness: a hand motion, a holder + rope scene, and its simulation.

The holder body has three slide and three hinge joints (about y, then x, then z), each driven
by a stiff position servo plus a velocity servo fed with the target's derivative
(feed-forward, so a 4 m/s hand does not lag). The rope hangs from the holder: a 1D flex built
by :func:`flyknot_sim.rope.add_rope`, or, for comparison, a chain of capsules on ball joints
(:func:`add_capsule_chain`). See :mod:`flyknot_tools.rope_study`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from flyknot.errors import ConfigError
from flyknot.geometry import min_rotation
from flyknot_sim.rope import ROPE_CONAFFINITY, ROPE_CONTYPE, add_rope
from flyknot_sim.rope_table import RopeParams, SimSettings, load_sim_settings

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
"""The offline tools' data (``flyknot_tools/data``)."""

REFERENCE_MOTION = DATA_DIR / "reference_hand_motion_rope1.csv"
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
    rod: tuple[Sequence[float], float, float] | None = None,
    gravity: bool = True,
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
        rod: A fixed horizontal rod along world y: (centre [m], radius [m], friction [-]);
            the rope's contact with it has the larger of the two friction coefficients
            (MuJoCo's default mixing).
        gravity: False: no gravity (the rope floats).
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
    opt.cone = getattr(mujoco.mjtCone, f"mjCONE_{s.cone.upper()}")
    opt.impratio = s.impratio
    if not s.refsafe:
        opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    spec.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.1], contype=1, conaffinity=1
    )
    if not gravity:
        opt.gravity = [0.0, 0.0, 0.0]
    if rod is not None:
        centre, radius, mu = rod
        spec.worldbody.add_geom(
            name="rod",
            type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            pos=np.asarray(centre, dtype=float),
            quat=[math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0],  # its z axis along world y
            size=[radius, 0.1, 0],
            friction=[mu, 0.005, 0.0001],
            contype=1,
            conaffinity=1,
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


def place_vertices(h: Harness, x: np.ndarray) -> None:
    """Put the rope's vertices at ``x`` (n + 1, 3) at rest (holder stays where it is)."""
    r = h.rope
    m, d = h.model, h.data
    r.set_vertices(m, d, x)
    mujoco.mj_forward(m, d)

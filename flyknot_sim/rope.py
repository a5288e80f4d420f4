"""The rope of the simulated lab: a MuJoCo 4 one-dimensional flex (discrete elastic rod).

Model (chosen by measurement, see ``docs/rope-model.md``):

* a ``dim=1`` flex of ``segments`` capsules built directly with ``MjSpec``: its vertices are
  point-mass bodies with three world-axis slide joints under the world body (MuJoCo's fast
  path for flex stiffness under Newton);
* stretching held by the flex edge equality (one constraint row per edge; a soft one, a
  spring-damper of the rope's EA, when the rope has a ``stretch_modulus``:
  :func:`stretch_solref`), bending by MuJoCo's
  discrete-elastic-rod elasticity (``young``, Rayleigh ``damping``), integrated implicitly by
  the ``discrete`` integrator. No per-edge twist hinges by default (bending is the same, the
  step ~40 % cheaper); ``add_rope(..., twist=True)`` builds MuJoCo's ``flexcomp`` with them;
* the held end: two ``connect`` equalities pin vertex 0 and vertex 1 to sites on the anchor
  body (a dynamic body moved by joints, e.g. the robot's ``link7``), so the first segment
  leaves along ``axis`` like a rope leaving a tube; the first segment may spin about its own
  axis (a held rope slips in its tube);
* the end weight: its mass is added to the last vertex body, plus a massless steel sphere there
  for contact;
* contact: flex self-collision (elements sharing a vertex never collide), with the floor and
  with every geom whose ``contype`` has bit 0 or bit 1 set (rope ``contype`` 1,
  ``conaffinity`` 3).

The held end (vertex 0) sits ``clearance = radius + 1 mm`` beyond the anchor point along the
axis, so the first capsule does not touch a tube that ends at the anchor (MuJoCo's body-pair
``exclude`` does not filter flex-geom contacts). Arc length, markers and :meth:`length` are
measured from vertex 0.

Rope ids, names, sizes and material data live in ``assets/ropes.toml`` (see
:func:`flyknot_sim.rope_table.load_rope_table`); simulation options in its ``[simulation]``
table (:func:`flyknot_sim.rope_table.load_sim_settings`, :func:`configure_options`). The
handles that read and write a built rope's state are in :mod:`flyknot_sim.rope_handle`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import mujoco
import numpy as np

from flyknot.errors import ConfigError
from flyknot.geometry import quat_from_x_to
from flyknot_sim.rope_handle import RopeHandle
from flyknot_sim.rope_table import (
    STRETCH_IMPEDANCE,
    RopeParams,
    SimSettings,
    load_sim_settings,
)

__all__ = [
    "ROPE_CONAFFINITY",
    "ROPE_CONTYPE",
    "add_rope",
    "configure_options",
    "stretch_solref",
]

ROPE_CONTYPE = 1
"""Rope contype: bit 0, so geoms with conaffinity bit 0 (floor, robot links) touch it."""
ROPE_CONAFFINITY = 3
"""Rope conaffinity: bits 0 and 1, so geoms with contype 1 (floor) or 2 (robot) touch it."""

_RGBA = {
    "cotton": (0.92, 0.88, 0.78, 1.0),
    "steel": (0.55, 0.57, 0.6, 1.0),
    "latex": (0.93, 0.62, 0.25, 1.0),
}


def configure_options(
    spec: mujoco.MjSpec, ropes: Iterable[RopeParams], settings: SimSettings | None = None
) -> None:
    """Set the spec's simulation options for these ropes.

    The timestep is the smallest of the ropes' validated timesteps; integrator, solver,
    iterations, line-search iterations, tolerance, friction cone and impratio come from
    ``settings`` (default: the ``[simulation]`` table of ``assets/ropes.toml``). Noslip stays
    off (MuJoCo refuses it with flex under the ``discrete`` integrator).

    Raises:
        ConfigError: ``ropes`` is empty.
    """
    ropes = list(ropes)
    if not ropes:
        raise ConfigError("ropes", "need at least one rope")
    s = load_sim_settings() if settings is None else settings
    opt = spec.option
    opt.timestep = min(r.timestep for r in ropes)
    opt.integrator = mujoco.mjtIntegrator.mjINT_DISCRETE
    opt.solver = getattr(mujoco.mjtSolver, f"mjSOL_{s.solver.upper()}")
    opt.iterations = s.iterations
    opt.ls_iterations = s.ls_iterations
    opt.tolerance = s.tolerance
    opt.noslip_iterations = 0
    opt.cone = getattr(mujoco.mjtCone, f"mjCONE_{s.cone.upper()}")
    opt.impratio = s.impratio
    if s.refsafe:
        opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    else:
        opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)


# ----------------------------------------------------------------------------------------
# building
# ----------------------------------------------------------------------------------------
def _flexcomp_xml(
    params: RopeParams, settings: SimSettings, pos: np.ndarray, quat: np.ndarray, name: str
) -> str:
    n, seg = params.segments, params.segment_length
    f = _fmt
    rgba = " ".join(f(c) for c in _RGBA[params.material])
    return (
        "<mujoco><worldbody>"
        f'<flexcomp name="{name}" type="grid" dim="1" count="{n + 1} 1 1" '
        f'spacing="{f(seg)} {f(seg)} {f(seg)}" radius="{f(params.radius)}" '
        f'mass="{f(params.mass)}" pos="{" ".join(f(x) for x in pos)}" '
        f'quat="{" ".join(f(x) for x in quat)}" rgba="{rgba}">'
        f'<edge equality="true" solref="{f(settings.edge_timeconst)} 1"/>'
        f'<elasticity young="{f(params.bend_modulus)}" shear="{f(params.shear_modulus)}" '
        f'damping="{f(params.damping)}"/>'
        f'<contact selfcollide="{settings.selfcollide}" contype="{ROPE_CONTYPE}" '
        f'conaffinity="{ROPE_CONAFFINITY}" condim="{params.condim}" '
        f'friction="{" ".join(f(v) for v in params.friction_triple)}" '
        f'solref="{f(settings.contact_timeconst)} {f(settings.contact_dampratio)}" '
        f'solimp="{" ".join(f(v) for v in settings.contact_solimp)} 0.5 2"/>'
        "</flexcomp></worldbody></mujoco>"
    )


def stretch_solref(params: RopeParams) -> tuple[list[float], list[float]] | None:
    """The edge equality's direct solref (-k, -b) and solimp of a rope that stretches.

    k = :attr:`~flyknot_sim.rope_table.RopeParams.stretch_spring` makes every interior edge a
    spring of EA / l; b = tau k adds the Kelvin-Voigt damping tau EA / l, tau the rope's
    ``damping`` time (as its bending's); the impedance is d = :data:`STRETCH_IMPEDANCE`
    throughout. The end edges differ (one flex equality has one solref): the first lies in the
    holder (both its vertices held); the last, to the end weight, has A = 1 / (rho l) + 1 /
    (rho l / 2 + m_end) and is stiffer by 2 / (rho l A) (1.9x for the tube). None for an
    inextensible rope (``stretch_modulus`` 0).
    """
    if params.stretch_modulus <= 0:
        return None
    d, k = STRETCH_IMPEDANCE, params.stretch_spring
    return [-k, -params.damping * k], [d, d, 0.001, 0.5, 2.0]


def _fmt(x: float) -> str:
    return repr(float(x))


def _add_raw_flex(
    spec: mujoco.MjSpec, params: RopeParams, settings: SimSettings, x0: np.ndarray, name: str
) -> None:
    """Vertex bodies ``<name>_<k>`` at ``x0`` (n + 1, 3) on x/y/z slides under the world, a
    ``dim=1`` flex through them with rod elasticity (bending only: no twist joints) and the
    flex edge-length equality (named by the caller)."""
    n = params.segments
    box = 0.005  # inertia box side [m] (point masses; rotational inertia unused)
    for k in range(n + 1):
        b = spec.worldbody.add_body(name=f"{name}_{k}", pos=x0[k])
        b.explicitinertial = True
        b.mass = 1.0  # set by add_rope
        b.inertia = [box * box / 6] * 3
        for i, ax in enumerate(np.eye(3)):
            b.add_joint(name=f"{name}_{k}_{'xyz'[i]}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=ax)
    f = spec.add_flex()
    f.name = name
    f.dim = 1
    f.radius = params.radius
    f.vertbody = [f"{name}_{k}" for k in range(n + 1)]
    f.vert = [0.0] * (3 * (n + 1))
    f.elem = [v for k in range(n) for v in (k, k + 1)]
    f.young = params.bend_modulus
    f.shear = params.shear_modulus
    f.damping = params.damping
    f.selfcollide = getattr(mujoco.mjtFlexSelf, f"mjFLEXSELF_{settings.selfcollide.upper()}")
    f.contype = ROPE_CONTYPE
    f.conaffinity = ROPE_CONAFFINITY
    f.condim = params.condim
    f.friction = params.friction_triple
    f.solref = [settings.contact_timeconst, settings.contact_dampratio]
    f.solimp = [*settings.contact_solimp, 0.5, 2.0]
    f.rgba = _RGBA[params.material]
    spec.add_equality(
        type=mujoco.mjtEq.mjEQ_FLEX, name1=name, solref=[settings.edge_timeconst, 1.0]
    )


def _anchor_world_pose(spec: mujoco.MjSpec, anchor_body: str) -> tuple[np.ndarray, np.ndarray]:
    """World position (3,) and rotation matrix (3, 3) of a body at qpos0 (compiles a copy)."""
    try:
        model = spec.copy().compile()
    except ValueError as exc:
        raise ConfigError("spec", f"does not compile before adding the rope: {exc}") from exc
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, anchor_body)
    return data.xpos[bid].copy(), data.xmat[bid].reshape(3, 3).copy()


def add_rope(
    spec: mujoco.MjSpec,
    params: RopeParams,
    *,
    anchor_body: str,
    anchor_pos: Sequence[float] = (0.0, 0.0, 0.0),
    axis: Sequence[float] = (0.0, 0.0, -1.0),
    prefix: str = "rope",
    settings: SimSettings | None = None,
    twist: bool = False,
) -> RopeHandle:
    """Add a rope to ``spec`` held by ``anchor_body``.

    The rope is built hanging straight along ``axis`` from the anchor's pose at ``qpos0``
    (a copy of the spec is compiled to find it), so a freshly reset model is consistent.
    Call :meth:`BoundRope.set_hanging` to place it at the anchor's current pose.

    Args:
        spec: Spec to edit; must compile without the rope.
        params: The rope.
        anchor_body: Name of a dynamic body (moved by joints, not mocap) holding the rope.
        anchor_pos: Anchor point in the anchor body's frame, shape (3,) [m].
        axis: Direction the rope leaves in, in the anchor body's frame, shape (3,).
        prefix: Name prefix of everything added (bodies ``<prefix>_flex_<k>``, ...).
        settings: Simulation settings (default: ``[simulation]`` of ``assets/ropes.toml``).
        twist: Build with MuJoCo's ``flexcomp``, which adds a twist hinge per edge (rod
            torsion); the default builds the flex directly without them (bending only, ~30 %
            faster; torsion is not driven anyway, since the held first edge may spin in its
            tube). See ``docs/rope-model.md``.

    Returns:
        The rope's handle (names); bind it to the compiled model with
        :meth:`RopeHandle.bind`.

    Raises:
        ConfigError: Unknown anchor body, mocap anchor, zero axis, bad vectors, name clash.
    """
    settings = load_sim_settings() if settings is None else settings
    body, pos, ax = _checked_anchor(spec, anchor_body, anchor_pos, axis, prefix)
    flex_name = f"{prefix}_flex"
    n, seg, c = params.segments, params.segment_length, params.clearance
    xb, rb = _anchor_world_pose(spec, anchor_body)
    ax_w = rb @ ax
    p0 = xb + rb @ (pos + c * ax)
    if twist:
        centre = p0 + ax_w * params.length / 2
        child = mujoco.MjSpec.from_string(
            _flexcomp_xml(params, settings, centre, quat_from_x_to(ax_w), "flex")
        )
        frame = spec.worldbody.add_frame()
        spec.attach(child, frame=frame, prefix=f"{prefix}_")
    else:
        x0 = p0 + seg * np.arange(n + 1)[:, None] * ax_w
        _add_raw_flex(spec, params, settings, x0, flex_name)

    vbodies = tuple(f"{flex_name}_{k}" for k in range(n + 1))
    end_geom = _add_masses(spec, params, settings, vbodies, prefix)
    _add_lock_up(spec, params, vbodies, prefix)
    holds = (pos + c * ax, pos + (c + seg) * ax)
    sites, eqs = _add_holds(spec, body, holds, vbodies, prefix, settings)
    edge_eq = f"{prefix}_edges"
    stretch = stretch_solref(params)
    for e in spec.equalities:
        if e.type == mujoco.mjtEq.mjEQ_FLEX and e.name1 == flex_name:
            e.name = edge_eq
            if stretch is not None:
                e.solref, e.solimp = stretch
    twist = tuple(j.name for j in spec.joints if j.name.startswith(f"{flex_name}_twist"))
    return RopeHandle(
        params=params,
        prefix=prefix,
        flex=flex_name,
        vertex_bodies=vbodies,
        twist_joints=twist,
        end_geom=end_geom,
        anchor_body=anchor_body,
        hold_sites=sites,
        hold_equalities=eqs,
        edge_equality=edge_eq,
    )


def _checked_anchor(
    spec: mujoco.MjSpec,
    anchor_body: str,
    anchor_pos: Sequence[float],
    axis: Sequence[float],
    prefix: str,
) -> tuple[mujoco.MjsBody, np.ndarray, np.ndarray]:
    """The anchor body, the anchor point (3,) [m] and the unit axis (3,) in its frame,
    checked (:func:`add_rope`'s Raises)."""
    body = spec.body(anchor_body)
    if body is None:
        names = [b.name for b in spec.bodies if b.name and b.name != "world"]
        raise ConfigError("anchor_body", f"no body named {anchor_body!r}", names)
    if body.mocap:
        raise ConfigError(
            "anchor_body",
            f"{anchor_body!r} is a mocap body; flex elasticity needs a body moved by joints",
        )
    pos = _vec3("anchor_pos", anchor_pos)
    ax = _vec3("axis", axis)
    if np.linalg.norm(ax) < 1e-9:
        raise ConfigError("axis", f"must be a non-zero vector, got {tuple(axis)}")
    ax = ax / np.linalg.norm(ax)
    if not isinstance(prefix, str) or not prefix:
        raise ConfigError("prefix", f"must be a non-empty string, got {prefix!r}")
    flex_name = f"{prefix}_flex"
    if spec.body(f"{flex_name}_0") is not None or spec.flex(flex_name) is not None:
        raise ConfigError("prefix", f"a rope with prefix {prefix!r} is already in the spec")
    return body, pos, ax


def _add_masses(
    spec: mujoco.MjSpec,
    params: RopeParams,
    settings: SimSettings,
    vbodies: tuple[str, ...],
    prefix: str,
) -> str:
    """The rope's mass lumped on its vertex bodies (trapezoidal: l rho per interior vertex,
    l rho / 2 at the ends) and the end weight (its mass and its sphere, which collides like
    the rope); returns the sphere's name."""
    n, seg = params.segments, params.segment_length
    for k, bname in enumerate(vbodies):
        b = spec.body(bname)
        b.mass = params.density * seg * (0.5 if k in (0, n) else 1.0)
    last = spec.body(vbodies[-1])
    last.mass = last.mass + params.end_mass
    end_geom = f"{prefix}_end_weight"
    last.add_geom(
        name=end_geom,
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[params.end_radius, 0, 0],
        mass=0.0,
        contype=ROPE_CONTYPE,
        conaffinity=ROPE_CONAFFINITY,
        condim=params.condim,
        friction=params.friction_triple,
        solref=[settings.contact_timeconst, settings.contact_dampratio],
        solimp=[*settings.contact_solimp, 0.5, 2.0],
        rgba=[0.3, 0.3, 0.32, 1.0],
    )
    return end_geom


def lock_chord(params: RopeParams) -> float:
    """The shortest chord between vertices k - 1 and k + 1 [m] that the rope's lock-up angle
    theta allows: two segments of length l turned by theta span c = 2 l cos(theta / 2)."""
    return 2.0 * params.segment_length * math.cos(math.radians(params.lock_angle) / 2.0)


def _add_lock_up(
    spec: mujoco.MjSpec, params: RopeParams, vbodies: Sequence[str], prefix: str
) -> None:
    """A link chain's lock-up (``params.lock_angle`` > 0): at every interior vertex k a spatial
    tendon from vertex k - 1 to k + 1 limited below at :func:`lock_chord`, so the solver holds
    the turn between the two segments at or under the angle at which real links jam (a
    one-sided constraint, active only at the limit)."""
    if params.lock_angle <= 0.0:
        return
    for k, name in enumerate(vbodies):
        spec.body(name).add_site(name=f"{prefix}_lock_site{k}", group=5)
    for k in range(1, len(vbodies) - 1):
        t = spec.add_tendon(name=f"{prefix}_lock{k}")
        t.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        t.range = [lock_chord(params), 2.0 * params.segment_length + 1.0]
        t.wrap_site(f"{prefix}_lock_site{k - 1}")
        t.wrap_site(f"{prefix}_lock_site{k + 1}")


def _add_holds(
    spec: mujoco.MjSpec,
    body: mujoco.MjsBody,
    holds: tuple[np.ndarray, np.ndarray],
    vbodies: tuple[str, ...],
    prefix: str,
    settings: SimSettings,
) -> tuple[tuple[str, str], tuple[str, str]]:
    """The grip: the rope's first two vertices connected to sites of the anchor ``body`` at
    ``holds`` (its frame, (3,) each [m]); returns the sites' and the equalities' names."""
    sites = (f"{prefix}_hold0", f"{prefix}_hold1")
    for name, pos in zip(sites, holds, strict=True):
        body.add_site(name=name, pos=pos, group=5)
    eqs = (f"{prefix}_hold0", f"{prefix}_hold1")
    for k in range(2):
        vsite = f"{prefix}_vertex{k}"
        spec.body(vbodies[k]).add_site(name=vsite, group=5)
        spec.add_equality(
            name=eqs[k],
            type=mujoco.mjtEq.mjEQ_CONNECT,
            objtype=mujoco.mjtObj.mjOBJ_SITE,
            name1=vsite,
            name2=sites[k],
            solref=[settings.edge_timeconst, 1.0],
        )
    return sites, eqs


def _vec3(name: str, v: Sequence[float]) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(name, f"must be 3 numbers, got {v!r}") from exc
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(name, f"must be 3 finite numbers, got {v!r}")
    return a

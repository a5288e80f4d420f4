"""Frictional bending couple (flyknot_sim.bend_friction): invariants and a damped swing."""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot_sim.aero import AeroParams, RopeDrag
from flyknot_sim.bend_friction import (
    IMPLICIT_ITERATIONS,
    RATE0,
    SPAN_REGULARISATION,
    BendFrictionParams,
    RopeBendFriction,
    bend_rates,
    edge_tensions,
    joint_moments,
    joint_tensions,
    rope_bend_friction_forces,
)
from flyknot_sim.bend_kernel import bend_friction_forces
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_table import get_rope, load_rope_table

N = 10
L = 0.04
M0 = 0.01
INV_MASS = np.r_[0.0, 0.0, np.full(N - 1, 1 / 1.5e-3)]  # held vertices 0, 1: infinitely heavy
MODES = [{"dt": 0.0}, {"dt": 1e-3, "inv_mass": INV_MASS}]  # explicit and end-of-step couples


def _bent(jitter):
    """A rope of N segments of ~L with random bends (|jitter| <= 0.3 L per coordinate)."""
    x = L * np.arange(N + 1)[:, None] * np.array([1.0, 0.0, 0.0])
    return x + L * np.asarray(jitter).reshape(N + 1, 3)


coords = st.lists(st.floats(-0.3, 0.3), min_size=3 * (N + 1), max_size=3 * (N + 1))
speeds = st.lists(st.floats(-3, 3), min_size=3 * (N + 1), max_size=3 * (N + 1))


@pytest.mark.parametrize("mode", MODES)
@given(jitter=coords, vel=speeds)
@settings(max_examples=60, deadline=None)
def test_forces_sum_to_zero_and_never_add_power(mode, jitter, vel):
    x, v = _bent(jitter), np.asarray(vel).reshape(N + 1, 3)
    f = rope_bend_friction_forces(x, v, M0, **mode)
    assert np.all(np.isfinite(f))
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-12 * max(1.0, np.abs(f).max()))
    assert np.sum(f * v) <= 1e-12


@given(
    jitter=coords,
    vel=speeds,
    moment=st.sampled_from([1e-4, 2e-3, 0.02]),
    dt=st.sampled_from([1e-3, 2e-3]),
)
@settings(max_examples=60, deadline=None)
def test_compiled_kernel_equals_the_numpy_equations(jitter, vel, moment, dt):
    x, v = _bent(jitter), np.asarray(vel).reshape(N + 1, 3)
    ref = rope_bend_friction_forces(x, v, moment, RATE0, INV_MASS, dt)
    fast = bend_friction_forces(
        x, v, np.full(N - 1, moment), RATE0, INV_MASS, dt, SPAN_REGULARISATION,
        IMPLICIT_ITERATIONS, 1e-24,
    )  # fmt: skip
    # to 1e-6 of the largest force: fastmath and another pivoting order round differently, and
    # the fixed-point passes amplify that where a joint's rate is near r_0 (measured: 3.6e-8 in
    # 20,000 random draws); a wrong term is off by the force itself
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


def test_applier_uses_the_compiled_kernel_on_a_rope():
    model, data, bound = _hanging_rope()
    bound.set_hanging(model, data, sway_angle=0.3, sway_rate=1.0)
    applier = RopeBendFriction(bound, M0)
    x = data.qpos[bound.vert_qpos] + bound.body_pos0
    v = data.qvel[bound.vert_dof]
    ref = rope_bend_friction_forces(x, v, M0, RATE0, applier.inv_mass(model), 1e-3)
    np.testing.assert_allclose(applier.forces(data), ref, rtol=0, atol=1e-6 * np.abs(ref).max())


@pytest.mark.parametrize("mode", MODES)
@given(jitter=coords, u=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
@settings(max_examples=30, deadline=None)
def test_translation_draws_no_force(mode, jitter, u):
    x = _bent(jitter)
    v = np.tile(u, (N + 1, 1))
    np.testing.assert_allclose(rope_bend_friction_forces(x, v, M0, **mode), 0.0, atol=1e-12)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("bent", [False, True])
@given(
    jitter=coords,
    omega=st.lists(st.floats(-10, 10), min_size=3, max_size=3),
    u=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
)
@settings(max_examples=30, deadline=None)
def test_rigid_rotation_draws_no_force(mode, bent, jitter, omega, u):
    """r_k = 0 for v = Omega x x + u: about any axis, for a straight and a 3D-bent rope (the
    joint rates are projected off the segments' span, where the unseen spins act)."""
    x = _bent(jitter) if bent else _bent(np.zeros(3 * (N + 1)))
    v = np.cross(np.asarray(omega), x) + np.asarray(u)
    r, _, _ = bend_rates(x, v)
    assert np.abs(r).max() <= 1e-3 * RATE0
    f = rope_bend_friction_forces(x, v, M0, **mode)
    assert np.abs(f).max() <= 1e-3 * M0 / L


def _two_segment_bend(rate, angle):
    """Segment 0 still along x; segment 1 at ``angle`` in the xy plane turning at ``rate``
    about z (vertex 2 moves, the joint vertex 1 and vertex 0 are still)."""
    t1 = np.array([math.cos(angle), math.sin(angle), 0.0])
    x = np.array([[0.0, 0.0, 0.0], [L, 0.0, 0.0], [L, 0.0, 0.0] + L * t1])
    v = np.zeros((3, 3))
    v[2] = rate * np.cross([0.0, 0.0, 1.0], L * t1)
    return x, v


@pytest.mark.parametrize("rate", [0.01, 0.05, 0.3, 4.0, -2.0])
@pytest.mark.parametrize("angle", [0.0, 0.4, 2.0])
def test_couple_on_a_two_segment_bend(rate, angle):
    """The forces on the distal segment have the moment M_0 r / sqrt(r^2 + r_0^2) about the
    joint, opposing the rate; the moment of all the forces is zero."""
    x, v = _two_segment_bend(rate, angle)
    f = rope_bend_friction_forces(x, v, M0)
    joint = x[1]
    distal = np.cross(x[2] - joint, f[2])
    expected = -M0 * rate / math.sqrt(rate**2 + RATE0**2)
    np.testing.assert_allclose(distal, [0.0, 0.0, expected], rtol=1e-9, atol=1e-15)
    total = sum(np.cross(x[i] - joint, f[i]) for i in range(3))
    np.testing.assert_allclose(total, 0.0, atol=1e-15)


def test_end_of_step_couple_stops_but_never_reverses():
    """With the masses and the step, a fast bend meets the full couple; a slow one is stopped
    within the step, never reversed (the explicit couple would reverse it ~100-fold)."""
    inv_mass = np.array([0.0, 0.0, 1 / 1.5e-3])
    dt = 1e-3
    for rate, slips in [(50.0, True), (0.5, False)]:
        x, v = _two_segment_bend(rate, 0.4)
        f = rope_bend_friction_forces(x, v, M0, inv_mass=inv_mass, dt=dt)
        couple = np.cross(x[2] - x[1], f[2])[2]
        v_end = v + dt * inv_mass[:, None] * f
        rate_end = np.cross(x[2] - x[1], v_end[2])[2] / L**2
        assert 0.0 <= rate_end / rate < 1.0
        if slips:
            assert couple == pytest.approx(-M0 * math.copysign(1, rate), rel=1e-3)
        else:
            assert abs(rate_end) < 1.5 * RATE0
            assert abs(couple) < M0


def test_params():
    rope = replace(get_rope(1), bend_hysteresis=54.0)
    assert BendFrictionParams().moment is None  # the rope's own
    assert BendFrictionParams().moment_for(rope) == rope.frictional_couple > 0
    lab = get_rope(1)  # the lab's cotton: 54 1/m x EI (assets/ropes.toml)
    assert BendFrictionParams().moment_for(lab) == pytest.approx(54.0 * lab.bending_stiffness)
    assert BendFrictionParams().moment_for(get_rope(7)) == 0.0  # latex: elastic
    assert rope.frictional_couple == pytest.approx(rope.bend_hysteresis * rope.bending_stiffness)
    assert BendFrictionParams(moment=0.0).moment_for(rope) == 0.0
    assert BendFrictionParams(moment=0.01).moment_for(rope) == 0.01
    for bad, shown in [(-0.1, "-0.1"), (float("nan"), "nan"), (True, "True")]:
        with pytest.raises(ConfigError) as e:
            BendFrictionParams(moment=bad)
        assert str(e.value) == f"moment: must be a finite number >= 0, got {shown}"


def _hanging_rope(rope=None):
    """``rope`` (None: rope 1) held at its top by a holder on stiff, damped, heavy slides
    (add_rope wants an anchor moved by joints)."""
    rope = get_rope(1) if rope is None else rope
    spec = mujoco.MjSpec()
    holder = spec.worldbody.add_body(name="holder", pos=[0, 0, 1.5])
    for k, axis in enumerate(np.eye(3)):
        holder.add_joint(
            name=f"s{k}",
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=list(axis),
            armature=1e4,
            stiffness=1e5,
            damping=1e3,
        )
    holder.add_geom(
        type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.001, 0, 0], mass=1e-3, contype=0, conaffinity=0
    )
    handle = add_rope(spec, rope, anchor_body="holder")
    configure_options(spec, [rope])
    model = spec.compile()
    data = mujoco.MjData(model)
    bound = handle.bind(model)
    mujoco.mj_forward(model, data)
    return model, data, bound


def _swing(moment, seconds):
    """Release rope 1 tilted 20 degrees; the free end's speeds over the last second [m/s]."""
    model, data, bound = _hanging_rope()
    bound.set_hanging(model, data, sway_angle=math.radians(20.0))
    drag = RopeDrag(bound, AeroParams())
    friction = RopeBendFriction(bound, moment)
    n = round(seconds / model.opt.timestep)
    last = []
    for i in range(n):
        drag.apply(data)  # writes qfrc_applied of the rope's dofs
        friction.apply(data)  # adds to it
        mujoco.mj_step(model, data)
        if i >= n - round(1.0 / model.opt.timestep):
            last.append(np.linalg.norm(data.qvel[bound.vert_dof[-1]]))
    assert np.all(np.isfinite(data.qvel))
    return np.array(last)


def test_frictionless_rope_still_swings_after_5_s():
    assert _swing(0.0, 5.0).max() > 0.5


def test_frictional_rope_swing_decays():
    """M_0 = 0.01 N m: the swing is damped (free end <= 0.54 m/s in the 5th second vs 1.2 m/s
    without friction; Coulomb-like, ~0.1 rad of amplitude lost per cycle at the top joint; at
    rest only after ~12.5 s); M_0 = 0.02 N m: at rest (< 3 cm/s, measured 6.3 s) by 9 s."""
    assert _swing(0.01, 5.0).max() < 0.7
    assert _swing(0.02, 9.0).max() < 0.03


def test_applier_replaces_its_own_previous_contribution():
    model, data, bound = _hanging_rope()
    bound.set_hanging(model, data, sway_angle=0.3, sway_rate=1.0)
    friction = RopeBendFriction(bound, M0)
    dof = bound.vert_dof
    data.qfrc_applied[dof] = 0.25  # e.g. a drag written (=) and held over several steps
    friction.apply(data)
    once = data.qfrc_applied[dof].copy()
    friction.apply(data)  # same state, drag not rewritten: no double counting
    np.testing.assert_array_equal(data.qfrc_applied[dof], once)
    np.testing.assert_allclose(once - 0.25, friction.forces(data), atol=1e-15)
    data.qfrc_applied[dof] = 0.5  # drag rewritten: added on top of the new values
    friction.apply(data)
    np.testing.assert_allclose(data.qfrc_applied[dof] - 0.5, friction.forces(data), atol=1e-15)
    assert np.abs(friction.forces(data)).max() > 0
    off = RopeBendFriction(bound, 0.0)
    off.apply(data)
    np.testing.assert_allclose(data.qfrc_applied[dof] - 0.5, friction.forces(data), atol=1e-15)


@given(
    a=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    b=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    straight=st.sampled_from([0.0, 1e-12, 1e-6, 1.0]),
)
@settings(max_examples=80, deadline=None)
def test_the_kernels_square_root_squares_to_the_projector(a, b, straight):
    """R = P^(1/2) in closed form (flyknot_sim/bend_kernel.py): R symmetric, R R = P, for bent,
    nearly straight and straight joints."""
    from flyknot_sim.bend_friction import _projectors
    from flyknot_sim.bend_kernel import _sqrt_projector

    ta = np.asarray(a) + np.array([0.0, 0.0, 1.5])
    ta /= np.linalg.norm(ta)
    tb = ta + straight * np.asarray(b)
    tb /= np.linalg.norm(tb)
    root = np.empty((3, 3))
    _sqrt_projector(ta, tb, 1.0 + SPAN_REGULARISATION, root)
    e = np.stack([ta, tb])
    (proj,) = _projectors(e, np.ones(2))
    np.testing.assert_allclose(root, root.T, atol=1e-12)
    # near straight, g - c ~ lambda = 1e-10 is known to ~1e-6 relative in either form (the
    # cancellation in 1 + lambda - t_a . t_b): P's in-plane entries then agree to ~5e-7
    np.testing.assert_allclose(root @ root, proj, atol=1e-5)


# --- the links' friction: M_0,k = M_0 + mu r T_k ---------------------------------------------
_couple = st.sampled_from([0.0, 1e-4, 2e-3, 0.02])
moments = st.lists(_couple, min_size=N - 1, max_size=N - 1).map(np.array)


@pytest.mark.parametrize("mode", MODES)
@given(jitter=coords, vel=speeds, moment=moments)
@settings(max_examples=60, deadline=None)
def test_per_joint_couples_sum_to_zero_and_never_add_power(mode, jitter, vel, moment):
    """Each joint its own M_0,k >= 0 (some 0, as at a slack joint): the forces still sum to
    zero, their power is never positive, and a joint without a couple draws none."""
    x, v = _bent(jitter), np.asarray(vel).reshape(N + 1, 3)
    f = rope_bend_friction_forces(x, v, moment, **mode)
    assert np.all(np.isfinite(f))
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-12 * max(1.0, np.abs(f).max()))
    assert np.sum(f * v) <= 1e-12
    if not moment.any():
        assert np.array_equal(f, np.zeros_like(f))


@given(jitter=coords, vel=speeds, moment=moments, dt=st.sampled_from([1e-3, 2e-3]))
@settings(max_examples=60, deadline=None)
def test_compiled_kernel_equals_the_numpy_equations_per_joint(jitter, vel, moment, dt):
    x, v = _bent(jitter), np.asarray(vel).reshape(N + 1, 3)
    ref = rope_bend_friction_forces(x, v, moment, RATE0, INV_MASS, dt)
    fast = bend_friction_forces(
        x, v, moment, RATE0, INV_MASS, dt, SPAN_REGULARISATION, IMPLICIT_ITERATIONS, 1e-24
    )
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-6 * max(np.abs(ref).max(), 1e-12))


def test_a_constant_couple_is_the_same_per_joint_bit_for_bit():
    """M_0 for every joint as a number or as an array: the same forces, to the bit."""
    rng = np.random.default_rng(5)
    x, v = _bent(rng.uniform(-0.3, 0.3, 3 * (N + 1))), rng.uniform(-3, 3, (N + 1, 3))
    for mode in MODES:
        a = rope_bend_friction_forces(x, v, M0, **mode)
        b = rope_bend_friction_forces(x, v, np.full(N - 1, M0), **mode)
        assert np.array_equal(a, b)


def test_joint_tensions_and_moments():
    """T_k: the mean of the two edges at joint k, compressions as 0, joint 1 the edge below's
    (edge 0 is held); M_0,k = M_0 + arm T_k; no tensions read: M_0."""
    edges = np.array([-1.0, 6.0, 4.0, -2.0, 1.0])
    np.testing.assert_array_equal(joint_tensions(edges), [6.0, 5.0, 2.0, 0.5])
    np.testing.assert_allclose(joint_moments(0.1, 0.01, edges, 5), [0.16, 0.15, 0.12, 0.105],
                               rtol=1e-15)  # fmt: skip
    np.testing.assert_array_equal(joint_moments(0.1, 0.01, None, 5), np.full(4, 0.1))
    np.testing.assert_array_equal(joint_moments(0.1, 0.0, edges, 5), np.full(4, 0.1))


def test_the_chain_alone_of_the_lab_has_link_friction():
    """Rope 6's links rub at half their 5 mm wire (DIN 5685A); the cords and the tube have no
    links, and a rope file that says nothing gives none."""
    for rope_id, rope in load_rope_table().items():
        want = 0.0025 if rope_id == 6 else 0.0
        assert rope.link_friction_radius == want
    assert get_rope(6).link_friction_arm == pytest.approx(0.57 * 0.0025)
    assert replace(get_rope(6), link_friction_radius=0.0).link_friction_arm == 0.0


RADIUS = 0.0025
"""The wire radius of a 5 mm short-link chain [m] (flyknot_sim/bend_friction.py)."""


def _settled_chain(seconds=1.0):
    """Rope 6 with the links' friction, hanging straight from its holder, stepped with its
    frictional couples (and air drag) for ``seconds``: at rest."""
    p = replace(get_rope(6), link_friction_radius=RADIUS)
    model, data, bound = _hanging_rope(p)
    # the holder's vertical slide where its spring carries the chain (else it bobs)
    slide = model.joint("s2")
    weight = -model.opt.gravity[2] * (p.mass + p.end_mass + 1e-3)
    data.qpos[slide.qposadr[0]] = -weight / model.jnt_stiffness[slide.id]
    mujoco.mj_kinematics(model, data)
    bound.set_hanging(model, data)
    friction = RopeBendFriction(bound, p.frictional_couple)
    for _ in range(round(seconds / model.opt.timestep)):
        data.qfrc_applied[:] = 0.0
        friction.apply(data)
        mujoco.mj_step(model, data)
    return p, model, data, bound, friction


def test_link_couple_of_a_hanging_chain_is_mu_t_r():
    """Hanging still, every joint's couple is mu r T_k, T_k the weight below it:
    g (m_end + lambda (L - s_k)), at joint 1 half a segment's weight less (it reads the edge
    below; module docstring), from the constraint forces MuJoCo solves."""
    p, model, data, bound, friction = _settled_chain()
    assert np.abs(data.qvel[bound.vert_dof]).max() < 1e-6
    assert friction.link_arm == p.friction * RADIUS and friction.moment == 0.0
    k = np.arange(1, p.segments)
    weight = 9.81 * (p.end_mass + p.density * (p.length - k * p.segment_length))
    weight[0] -= 9.81 * p.density * p.segment_length / 2
    m = friction.moments(data)
    g = -model.opt.gravity[2]
    np.testing.assert_allclose(m, p.friction * RADIUS * weight * g / 9.81, rtol=1e-6)
    assert m[0] == pytest.approx(8.2e-3, abs=1e-4) and m[-1] == pytest.approx(9.6e-4, abs=1e-5)
    # the edges' tensions are the weights below them (trapezoidal lumping, end weight)
    edges = edge_tensions(data, friction._edge_eq, p.segments)
    np.testing.assert_allclose(edges[1:], weight[0] - g * p.density * p.segment_length * (k - 1),
                               rtol=1e-6)  # fmt: skip


def test_the_applier_adds_the_link_couples_it_reads():
    """The compiled applier reads the same tensions as :meth:`RopeBendFriction.moments`:
    it adds exactly :meth:`RopeBendFriction.forces` of a swinging chain."""
    _, model, data, bound, friction = _settled_chain(0.2)
    bound.set_hanging(model, data, sway_angle=0.3, sway_rate=1.0)
    mujoco.mj_forward(model, data)
    dof = bound.vert_dof
    data.qfrc_applied[:] = 0.0
    friction._has_prev = False
    friction.apply(data)
    f = friction.forces(data)
    assert np.abs(f).max() > 0
    np.testing.assert_array_equal(data.qfrc_applied[dof], f)
    moment = friction.moments(data)
    assert moment.min() > 0 and moment.max() / moment.min() > 5  # top vs bottom of the chain
    x = data.qpos[bound.vert_qpos] + bound.body_pos0
    ref = rope_bend_friction_forces(x, data.qvel[dof], moment, RATE0, friction.inv_mass(model),
                                    model.opt.timestep)  # fmt: skip
    np.testing.assert_allclose(f, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


def test_before_any_solve_the_link_couple_reads_no_tension():
    p = replace(get_rope(6), link_friction_radius=RADIUS)
    model, _, bound = _hanging_rope(p)
    data = mujoco.MjData(model)  # no constraint solved: no rows
    friction = RopeBendFriction(bound, 1e-3)
    assert edge_tensions(data, friction._edge_equality(model), p.segments) is None
    np.testing.assert_array_equal(friction.moments(data), np.full(p.segments - 1, 1e-3))
    friction.apply(data)  # the constant couple alone, no failure
    assert np.all(np.isfinite(data.qfrc_applied))


def test_without_link_friction_the_tensions_are_not_read():
    """The field at 0 (every lab rope but the chain): the applier reads no constraint force
    (scrambling them changes nothing, to the bit), and a chain without M_0 or link friction is
    off (adds nothing)."""
    model, data, bound = _hanging_rope()
    bound.set_hanging(model, data, sway_angle=0.3, sway_rate=1.0)
    mujoco.mj_forward(model, data)
    friction = RopeBendFriction(bound, M0)
    assert friction.link_arm == 0.0
    before = friction.forces(data)
    data.qfrc_applied[:] = 0.0
    friction.apply(data)
    added = data.qfrc_applied.copy()
    data.efc_force[:] = 1e3
    assert np.array_equal(friction.forces(data), before)
    data.qfrc_applied[:] = 0.0
    friction._has_prev = False
    friction.apply(data)
    assert np.array_equal(data.qfrc_applied, added)
    bare = replace(get_rope(6), link_friction_radius=0.0)
    _, data6, bound6 = _hanging_rope(bare)
    chain = RopeBendFriction(bound6, bare.frictional_couple)
    assert not chain.on
    data6.qfrc_applied[:] = 0.25
    chain.apply(data6)
    assert np.all(data6.qfrc_applied == 0.25)


def test_link_arm_is_checked():
    _, _, bound = _hanging_rope()
    with pytest.raises(ConfigError, match="link_arm: must be a finite number >= 0"):
        RopeBendFriction(bound, M0, link_arm=-1e-3)

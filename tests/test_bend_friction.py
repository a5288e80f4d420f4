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
    rope_bend_friction_forces,
)
from flyknot_sim.bend_kernel import bend_friction_forces
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_table import get_rope

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
        x, v, moment, RATE0, INV_MASS, dt, SPAN_REGULARISATION, IMPLICIT_ITERATIONS, 1e-24
    )
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


def _hanging_rope():
    """Rope 1 held at its top by a holder on stiff, damped, heavy slides (add_rope wants an
    anchor moved by joints)."""
    rope = get_rope(1)
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

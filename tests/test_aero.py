"""Air drag on the rope (flyknot_sim.aero): the formulas and a terminal-velocity fall."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot_sim.aero import (
    AIR_DENSITY,
    AIR_KINEMATIC_VISCOSITY,
    AeroParams,
    RopeDrag,
    cylinder_cd,
    rope_drag_forces,
    sphere_cd,
)
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_table import get_rope


def test_cd_curves_at_known_points():
    # White's fits: cylinder 1 + 10 Re^(-2/3); sphere 24/Re + 6/(1 + sqrt Re) + 0.4.
    assert cylinder_cd(1000.0) == pytest.approx(1.1)
    assert cylinder_cd(1.0) == pytest.approx(11.0)
    assert sphere_cd(100.0) == pytest.approx(0.24 + 6 / 11 + 0.4)
    assert np.all(np.diff(cylinder_cd(np.logspace(0, 5, 50))) < 0)


def _straight(n=10, length=1.0, axis=(1.0, 0.0, 0.0)):
    return np.linspace(0, length, n + 1)[:, None] * np.asarray(axis)[None, :]


def test_broadside_drag_matches_the_formula():
    x = _straight()
    v = np.tile([0.0, 0.0, -2.0], (11, 1))
    p = AeroParams()
    f = rope_drag_forces(x, v, 0.009, 0.0, p)
    re = 2.0 * 0.009 / AIR_KINEMATIC_VISCOSITY
    expected = 0.5 * AIR_DENSITY * float(cylinder_cd(re)) * 0.009 * 1.0 * 4.0
    np.testing.assert_allclose(f.sum(axis=0), [0.0, 0.0, expected], rtol=1e-12)
    # Half a segment's share at each end vertex, a whole one inside.
    assert f[0, 2] == pytest.approx(f[5, 2] / 2)


def test_axial_drag_is_skin_friction_only():
    x = _straight()
    v = np.tile([3.0, 0.0, 0.0], (11, 1))
    f = rope_drag_forces(x, v, 0.009, 0.0, AeroParams())
    expected = -0.5 * AIR_DENSITY * 0.01 * math.pi * 0.009 * 1.0 * 9.0
    np.testing.assert_allclose(f.sum(axis=0), [expected, 0.0, 0.0], rtol=1e-12)


def test_end_sphere_drag():
    x = _straight()
    v = np.zeros((11, 3))
    v[-1] = [0.0, 1.5, 0.0]
    r = 0.008
    f = rope_drag_forces(x, v, 0.009, r, AeroParams(cd=1.0, tangential_ct=0.0))
    seg = 0.5 * AIR_DENSITY * 1.0 * 0.009 * 0.1 * (0.5 * 1.5) ** 2  # last segment, mean v
    sph = 0.5 * AIR_DENSITY * float(sphere_cd(1.5 * 2 * r / AIR_KINEMATIC_VISCOSITY))
    sph *= math.pi * r**2 * 1.5**2
    assert f[-1, 1] == pytest.approx(-(seg / 2 + sph), rel=1e-12)


@given(
    st.lists(st.floats(-5, 5), min_size=33, max_size=33),
    st.lists(st.floats(-0.05, 0.05), min_size=33, max_size=33),
)
@settings(max_examples=60, deadline=None)
def test_drag_never_adds_power(vel, jitter):
    x = _straight() + np.asarray(jitter).reshape(11, 3)
    v = np.asarray(vel).reshape(11, 3)
    f = rope_drag_forces(x, v, 0.012, 0.01, AeroParams())
    assert np.sum(f * v) <= 1e-12


def test_disabled_drag_writes_nothing():
    p = AeroParams(enabled=False)
    assert p.enabled is False


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"air_density": 0.0}, "air_density: must be a finite number > 0, got 0.0"),
        ({"tangential_ct": -0.1}, "tangential_ct: must be a finite number >= 0, got -0.1"),
        ({"cd": float("nan")}, "cd: must be a finite number > 0, got nan"),
    ],
)
def test_aero_params_errors(kwargs, message):
    with pytest.raises(ConfigError) as e:
        AeroParams(**kwargs)
    assert str(e.value) == message


def test_terminal_velocity_of_a_rope_falling_broadside():
    """A level rope (no end weight) falls in MuJoCo under gravity and drag; its speed tends
    to v_t with rho_l g = 1/2 rho C_D(Re) D v_t^2 (all vertices alike: uniform loading)."""
    rope = dataclasses.replace(get_rope(1), end_mass=0.0, bend_modulus=0.0, segments=20)
    spec = mujoco.MjSpec()
    holder = spec.worldbody.add_body(name="holder", pos=[0, 0, 0])
    for k, axis in enumerate(np.eye(3)):
        holder.add_joint(name=f"s{k}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=list(axis))
    holder.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.001, 0, 0], mass=1e-5)
    handle = add_rope(spec, rope, anchor_body="holder", axis=(1.0, 0.0, 0.0))
    configure_options(spec, [rope])
    model = spec.compile()
    data = mujoco.MjData(model)
    bound = handle.bind(model)
    mujoco.mj_forward(model, data)
    p0 = data.site_xpos[bound.hold_sites[0]]
    level = p0 + rope.segment_length * np.arange(rope.segments + 1)[:, None] * [1.0, 0, 0]
    bound.set_vertices(model, data, level)
    drag = RopeDrag(bound, AeroParams(), end_radius=0.0)
    for _ in range(round(3.0 / model.opt.timestep)):
        drag.apply(data)
        mujoco.mj_step(model, data)
    vz = -data.qvel[bound.vert_dof][:, 2]
    # Solve rho_l g = 1/2 rho C_D(v D / nu) D v^2 for v by fixed-point iteration.
    v = 5.0
    for _ in range(50):
        cd = float(cylinder_cd(v * rope.diameter / AIR_KINEMATIC_VISCOSITY))
        v = math.sqrt(rope.density * 9.81 / (0.5 * AIR_DENSITY * cd * rope.diameter))
    assert np.median(vz) == pytest.approx(v, rel=0.02)


def test_the_compiled_drag_is_the_numpy_drag_bit_for_bit():
    """The lab uses the compiled kernels only where they match; on this machine they must."""
    from flyknot_sim.aero import _drag_compiled, compiled_drag_matches

    assert compiled_drag_matches()
    rng = np.random.default_rng(7)
    for k in range(40):  # other states than the check's own
        x = np.cumsum(0.04 * rng.standard_normal((31, 3)), axis=0)
        v = 3.0 * rng.standard_normal((31, 3))
        params = AeroParams(cd=None if k % 2 else 0.9, tangential_ct=0.02)
        out = np.empty_like(x)
        _drag_compiled(x, v, 0.007, 0.005 * (k % 3), params, out)
        ref = rope_drag_forces(x, v, 0.007, 0.005 * (k % 3), params)
        np.testing.assert_array_equal(out, ref)


def test_a_trial_is_the_same_with_the_compiled_drag(monkeypatch):
    import flyknot_sim.aero as aero
    from flyknot_sim.commands import swing_command
    from flyknot_sim.lab import LabParams, SimLab

    records = []
    for compiled in (True, False):
        monkeypatch.setattr(aero, "COMPILED", compiled)
        records.append(SimLab(LabParams(rope=4, settle_s=0.3)).run(swing_command()))
    a, b = records
    assert set(a.truth) == set(b.truth) and "centreline" in a.truth
    for key in a.truth:
        np.testing.assert_array_equal(a.truth[key], b.truth[key])
    np.testing.assert_array_equal(a.q_meas, b.q_meas)
    np.testing.assert_array_equal(a.markers, b.markers)

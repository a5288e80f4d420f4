"""A rope that stretches: the soft edge equality is a spring of the rope's EA, and the hung
rope stretches and bounces as Hooke's law and a spring's period say."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from flyknot.errors import ConfigError
from flyknot_sim.rope import stretch_solref
from flyknot_sim.rope_table import STRETCH_IMPEDANCE, get_rope
from flyknot_tools.rope_validate.bench import RopeModel
from flyknot_tools.rope_validate.common import G, hung
from flyknot_tools.rope_validate.rest_after_motion import hanging_at_home
from flyknot_tools.rope_validate.stretch import STRETCH_TOL, hung_stretch, stretch


def test_only_the_tube_stretches_and_its_ea_is_from_its_wall():
    assert [get_rope(i).stretch_modulus for i in range(1, 7)] == [0.0] * 6
    assert all(stretch_solref(get_rope(i)) is None for i in range(1, 7))
    tube = get_rope(7)
    # 1.2 MPa on the wall's 0.026 / 930 m^2 (assets/ropes.toml)
    assert tube.axial_stiffness == pytest.approx(1.2e6 * 0.026 / 930, rel=0.01)
    (k, b), solimp = stretch_solref(tube)
    assert k < 0 and b < 0 and b / k == pytest.approx(tube.damping)
    assert solimp[:2] == [STRETCH_IMPEDANCE, STRETCH_IMPEDANCE]


def test_an_interior_edge_at_rest_is_a_spring_of_ea_over_its_length():
    """MuJoCo's own row force over the row's stretch, the tube hung still: EA / l within 2 %."""
    p = get_rope(7)
    b = hung(RopeModel(p), hanging_at_home(p))
    b.run(1.5)
    m, d = b.model, b.data
    eq = [i for i in range(m.neq) if m.eq_type[i] == mujoco.mjtEq.mjEQ_FLEX]
    rows = [
        r
        for r in range(d.nefc)
        if d.efc_type[r] == mujoco.mjtConstraint.mjCNSTR_EQUALITY and d.efc_id[r] in eq
    ]
    force, stretch_m = d.efc_force[rows], d.efc_pos[rows]
    interior = slice(2, -2)  # the first edge lies in the holder, the last holds the end weight
    k_edge = np.abs(force[interior] / stretch_m[interior])
    assert np.allclose(k_edge, p.axial_stiffness / p.segment_length, rtol=0.02)


@settings(max_examples=30, deadline=None)
@given(
    ea_scale=st.floats(0.2, 5.0),
    end=st.floats(1e-4, 0.1),
    length=st.floats(0.5, 2.0),
)
def test_the_hung_law_integrates_the_tension_and_solves_the_mode(ea_scale, end, length):
    p = dataclasses.replace(  # a short step: no stretch here is too fast for it
        get_rope(7), stretch_modulus=5e5 * ea_scale, end_mass=end, length=length, timestep=1e-4
    )
    delta, period = hung_stretch(p)
    tension = lambda s: G * (p.end_mass + p.density * (p.length - s))  # noqa: E731
    assert delta == pytest.approx(quad(tension, 0, p.length)[0] / p.axial_stiffness, rel=1e-9)
    stiff = dataclasses.replace(p, stretch_modulus=4 * p.stretch_modulus)
    assert hung_stretch(stiff) == pytest.approx((delta / 4, period / 2), rel=1e-9)
    beta = 2 * math.pi * p.length / (period * math.sqrt(p.axial_stiffness / p.density))
    assert beta * math.tan(beta) == pytest.approx(p.mass / p.end_mass, rel=1e-6)


def test_the_modes_limits_a_bar_and_a_spring_with_a_third_of_its_mass():
    bare = dataclasses.replace(get_rope(7), end_mass=0.0)
    c = math.sqrt(bare.axial_stiffness / bare.density)
    assert hung_stretch(bare)[1] == pytest.approx(4 * bare.length / c)  # a quarter wave
    heavy = dataclasses.replace(get_rope(7), end_mass=10.0)
    spring = (
        2
        * math.pi
        * math.sqrt(heavy.length * (heavy.end_mass + heavy.mass / 3) / heavy.axial_stiffness)
    )
    assert hung_stretch(heavy)[1] == pytest.approx(spring, rel=1e-4)


def test_the_tube_stretches_and_bounces_as_a_spring_and_the_cord_does_not():
    tube = stretch(RopeModel(get_rope(7)))
    assert tube.applies and tube.passed, tube.detail
    delta, period = hung_stretch(get_rope(7))
    assert tube.measured["elongation_m"] == pytest.approx(delta, rel=STRETCH_TOL)
    assert tube.measured["period_s"] == pytest.approx(period, rel=STRETCH_TOL)
    bare = stretch(RopeModel(dataclasses.replace(get_rope(7), end_mass=0.0)))
    assert bare.passed, bare.detail  # its own mass alone: the quarter wave
    cord = stretch(RopeModel(get_rope(1)), seconds=1.5)
    assert not cord.applies and abs(cord.measured["elongation_m"]) < 1e-3 * get_rope(1).length


def test_a_stiffer_tube_stretches_less_in_the_lab():
    """The case would fail if the edge ignored the modulus: at 4x E (and half the step, which
    such a stiff edge needs) the tube stretches a quarter."""
    tube = get_rope(7)
    stiff = dataclasses.replace(tube, stretch_modulus=4 * tube.stretch_modulus, timestep=5e-4)
    r = stretch(RopeModel(stiff), seconds=2.0)
    assert r.passed, r.detail
    assert r.measured["elongation_m"] < 0.3 * hung_stretch(get_rope(7))[0]


def test_a_stretch_faster_than_the_step_is_refused_naming_the_bound():
    """MuJoCo's soft constraint follows a time constant of at least two steps (its refsafe
    rule); the tube's own is inside it (5.27e5 of at most 8.48e5 Pa)."""
    with pytest.raises(ConfigError) as e:
        dataclasses.replace(get_rope(7), stretch_modulus=2e6)
    assert str(e.value) == (
        "stretch_modulus: 2e+06 Pa makes an edge's spring faster than MuJoCo's soft constraint "
        "follows at the rope's 0.001 s step (its time constant under twice the step); use at "
        "most 8.479e+05 Pa, or 0 for an inextensible rope"
    )
    at_bound = dataclasses.replace(get_rope(7), stretch_modulus=8.47e5)
    (k, _), _ = stretch_solref(at_bound)
    assert -k * (2 * at_bound.timestep * STRETCH_IMPEDANCE) ** 2 == pytest.approx(1, rel=2e-3)

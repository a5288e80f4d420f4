"""Tests of the rope model (flyknot_sim.rope, rope_table, rope_handle) and the rope study's
measurement kernels (flyknot_tools.rope_study)."""

from __future__ import annotations

import math
from dataclasses import replace

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import ASSETS_DIR, MARKER_SPACING, N_MARKERS, ROPE_LENGTH
from flyknot.errors import ConfigError
from flyknot.geometry import quat_from_x_to
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_handle import (
    hanging_vertices,
    points_at_arclength,
    polyline_length,
    sway_direction,
)
from flyknot_sim.rope_table import (
    RopeParams,
    SimSettings,
    get_rope,
    load_rope_table,
    load_sim_settings,
    parse_rope_table,
)
from flyknot_tools.rope_study import crossings, harness, measures

# The paper's rope table (appendix "Rope Parameters"): id -> (name, material, diameter [mm],
# density [kg/m], end weight [g]).
PAPER = {
    1: ("#10 sash spot cord", "cotton", 9, 0.040, 18),
    2: ("#14 spot cord", "cotton", 12, 0.081, 80),
    3: ("soft braided", "cotton", 15, 0.076, 80),
    4: ("shoe lace", "cotton", 7, 0.014, 5),
    5: ("thick twisted", "cotton", 25, 0.139, 50),
    6: ('3/8" chain', "steel", 20, 0.514, 50),
    7: ('3/8" surgical tubing', "latex", 9, 0.026, 18),
}

finite = st.floats(-10, 10, allow_nan=False)


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------
def hand_scene(params: RopeParams, *, mocap: bool = False, axis=(0.0, 0.0, -1.0), settings=None):
    """A hand at (0, 0, 1.5) on three slides held by stiff position servos, plus a floor."""
    spec = mujoco.MjSpec()
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[2, 2, 0.1],
        contype=1,
        conaffinity=1,
    )
    hand = spec.worldbody.add_body(name="hand", pos=[0, 0, 1.5], mocap=mocap)
    hand.add_geom(
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[0.01, 0, 0],
        mass=0.5,
        contype=0,
        conaffinity=0,
    )
    if not mocap:
        for i, ax in enumerate(np.eye(3)):
            hand.add_joint(name=f"s{i}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=ax)
            a = spec.add_actuator(target=f"s{i}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
            a.set_to_position(kp=2e4, kv=200)
    handle = add_rope(spec, params, anchor_body="hand", axis=axis, settings=settings)
    configure_options(spec, [params], settings)
    model = spec.compile()
    data = mujoco.MjData(model)
    return spec, handle, model, data


@pytest.fixture(scope="module")
def rope1():
    _, handle, model, data = hand_scene(get_rope(1))
    return handle, model, data


# ------------------------------------------------------------------------------------------
# the table
# ------------------------------------------------------------------------------------------
def test_table_matches_paper():
    table = load_rope_table()
    assert sorted(table) == list(PAPER)
    for rid, (name, material, d_mm, density, end_g) in PAPER.items():
        p = table[rid]
        assert (p.id, p.name, p.material) == (rid, name, material)
        assert p.diameter == pytest.approx(d_mm / 1000, abs=1e-12)
        assert p.density == pytest.approx(density, abs=1e-12)
        assert p.end_mass == pytest.approx(end_g / 1000, abs=1e-12)
        assert p.length == ROPE_LENGTH
        assert p.segment_length > p.diameter
        assert get_rope(rid) == p


def test_cotton_bending_follows_the_linear_density():
    """The lab's cotton: EI = b tex, b = 5.64e-10 N m^2/tex (free-slip scaling, see
    ropes.toml): every cotton rope has the same elastic bending length (EI / w)^(1/3), 3.9 cm,
    and the same HB/B."""
    for p in load_rope_table().values():
        if p.material == "cotton":
            tex = p.density * 1e6
            assert p.bending_stiffness == pytest.approx(5.64e-10 * tex, rel=0.01)
            c = (p.bending_stiffness / (p.density * 9.81)) ** (1 / 3)
            assert c == pytest.approx(0.039, abs=0.001)
            assert p.bend_hysteresis == 54.0
            assert p.frictional_couple == pytest.approx(54.0 * p.bending_stiffness)


def test_unknown_rope_id_message():
    with pytest.raises(ConfigError) as e:
        get_rope(9)
    assert str(e.value) == "rope: unknown rope id 9 (valid choices: 1, 2, 3, 4, 5, 6, 7)"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "material",
            "wool",
            "material: unknown value 'wool' (valid choices: cotton, steel, latex)",
        ),
        ("diameter", -0.01, "diameter: must be a finite number > 0, got -0.01"),
        ("end_mass", -1.0, "end_mass: must be a finite number >= 0, got -1.0"),
        ("segments", 2.5, "segments: must be an integer, got 2.5"),
        ("segments", 1, "segments: must be >= 2, got 1"),
        ("id", 0, "id: must be an integer >= 1, got 0"),
        ("name", "", "name: must be a non-empty string, got ''"),
    ],
)
def test_rope_params_messages(field, value, message):
    with pytest.raises(ConfigError) as e:
        replace(get_rope(1), **{field: value})
    assert str(e.value) == message


def test_segments_longer_than_diameter_message():
    with pytest.raises(ConfigError) as e:
        replace(get_rope(5), segments=50)
    assert str(e.value) == (
        "segments: segment length 0.022 m must exceed the diameter 0.025 m (elements sharing "
        "no vertex would touch at rest); use at most 43 segments"
    )


def test_parse_table_messages():
    rope = {
        k: getattr(get_rope(1), k)
        for k in (
            "id",
            "name",
            "material",
            "diameter",
            "density",
            "end_mass",
            "length",
            "segments",
            "timestep",
        )
    }
    mats = {"cotton": {"bend_modulus": 1e6, "shear_modulus": 3e5, "damping": 0.01, "friction": 0.5}}
    assert parse_rope_table({"materials": mats, "rope": [rope]})[1].bend_modulus == 1e6
    with pytest.raises(ConfigError) as e:
        parse_rope_table({"materials": mats, "rope": [{**rope, "colour": "red"}]})
    assert str(e.value).startswith("rope[0].colour: unknown key (valid choices: id, name,")
    with pytest.raises(ConfigError) as e:
        parse_rope_table({"materials": {}, "rope": [rope]})
    assert str(e.value) == "rope[0]: missing key(s) bend_modulus, shear_modulus, damping, friction"
    with pytest.raises(ConfigError) as e:
        parse_rope_table({"materials": mats, "rope": [rope, rope]})
    assert str(e.value) == "rope[1].id: duplicate rope id 1"
    with pytest.raises(ConfigError) as e:
        parse_rope_table({"rope": []})
    assert str(e.value) == "rope: the table needs at least one [[rope]] entry"


def test_sim_settings_messages():
    assert load_sim_settings().integrator == "discrete"
    with pytest.raises(ConfigError) as e:
        SimSettings(solver="PGS")
    assert str(e.value) == "solver: unknown value 'PGS' (valid choices: Newton, CG)"
    with pytest.raises(ConfigError) as e:
        SimSettings(iterations=0)
    assert str(e.value) == "iterations: must be an integer >= 1, got 0"
    with pytest.raises(ConfigError) as e:
        SimSettings(contact_solimp=(0.9, 1.5, 0.001))
    assert str(e.value) == (
        "contact_solimp: need 0 < d0, d_width < 1 and width > 0, got (0.9, 1.5, 0.001)"
    )


def test_configure_options_takes_smallest_timestep():
    spec = mujoco.MjSpec()
    a, b = get_rope(1), replace(get_rope(4), timestep=0.0005)
    configure_options(spec, [a, b])
    s = load_sim_settings()
    assert spec.option.timestep == 0.0005
    assert spec.option.integrator == mujoco.mjtIntegrator.mjINT_DISCRETE
    assert spec.option.iterations == s.iterations
    refsafe_off = bool(spec.option.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    assert refsafe_off == (not s.refsafe)
    with pytest.raises(ConfigError) as e:
        configure_options(spec, [])
    assert str(e.value) == "ropes: need at least one rope"


# ------------------------------------------------------------------------------------------
# building
# ------------------------------------------------------------------------------------------
def test_mass_is_density_times_length_plus_end_weight(rope1):
    handle, model, _ = rope1
    p = handle.params
    b = handle.bind(model)
    masses = model.body_mass[b.vert_body]
    assert masses.sum() == pytest.approx(p.density * p.length + p.end_mass, rel=1e-12)
    assert masses[-1] - p.end_mass == pytest.approx(p.density * p.segment_length / 2, rel=1e-12)
    assert masses[1:-1] == pytest.approx(np.full(p.segments - 1, p.density * p.segment_length))
    geom = model.geom(handle.end_geom)
    assert geom.size[0] == pytest.approx(p.end_radius)
    assert geom.bodyid[0] == b.vert_body[-1]


def test_end_radius_is_a_steel_sphere():
    p = get_rope(1)
    assert 4 / 3 * math.pi * p.end_radius**3 * 7850 == pytest.approx(p.end_mass, rel=1e-12)
    assert get_rope(5).end_radius == get_rope(5).radius  # 50 g steel ball is thinner


def test_at_qpos0_rope_hangs_from_the_anchor(rope1):
    handle, model, data = rope1
    mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)
    x = handle.vertex_positions(model, data)
    p = handle.params
    assert x[0] == pytest.approx([0, 0, 1.5 - p.clearance], abs=1e-9)
    assert x[-1] == pytest.approx([0, 0, 1.5 - p.clearance - p.length], abs=1e-9)
    assert not handle.self_contact(model, data)


def test_add_rope_errors():
    p = get_rope(1)
    spec = mujoco.MjSpec()
    spec.worldbody.add_body(name="hand")
    with pytest.raises(ConfigError) as e:
        add_rope(spec, p, anchor_body="hnd")
    assert str(e.value) == "anchor_body: no body named 'hnd' (valid choices: hand)"
    with pytest.raises(ConfigError) as e:
        add_rope(spec, p, anchor_body="hand", axis=(0, 0, 0))
    assert str(e.value) == "axis: must be a non-zero vector, got (0, 0, 0)"
    with pytest.raises(ConfigError) as e:
        add_rope(spec, p, anchor_body="hand", anchor_pos=(0, 0))
    assert str(e.value) == "anchor_pos: must be 3 finite numbers, got (0, 0)"
    add_rope(spec, p, anchor_body="hand")
    with pytest.raises(ConfigError) as e:
        add_rope(spec, p, anchor_body="hand")
    assert str(e.value) == "prefix: a rope with prefix 'rope' is already in the spec"
    mocap = mujoco.MjSpec()
    mocap.worldbody.add_body(name="m", mocap=True)
    with pytest.raises(ConfigError) as e:
        add_rope(mocap, p, anchor_body="m")
    assert str(e.value) == (
        "anchor_body: 'm' is a mocap body; flex elasticity needs a body moved by joints"
    )


def test_bind_to_a_model_without_the_rope_fails(rope1):
    handle, _, _ = rope1
    other = mujoco.MjModel.from_xml_string("<mujoco/>")
    with pytest.raises(ConfigError) as e:
        handle.bind(other)
    assert str(e.value) == "flex: no flex named 'rope_flex' in the model"


# ------------------------------------------------------------------------------------------
# read-out and state
# ------------------------------------------------------------------------------------------
def test_markers_every_tenth_of_a_metre_at_rest(rope1):
    handle, model, data = rope1
    mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)
    x = handle.centreline(model, data)
    mk = handle.markers(model, data)
    assert mk.shape == (N_MARKERS, 3)
    assert np.linalg.norm(mk[0] - x[0]) == pytest.approx(MARKER_SPACING, abs=1e-12)
    assert np.linalg.norm(np.diff(mk, axis=0), axis=1) == pytest.approx(
        np.full(N_MARKERS - 1, MARKER_SPACING), abs=1e-12
    )
    assert mk[-1] == pytest.approx(x[-1], abs=1e-12)
    assert handle.length(model, data) == pytest.approx(ROPE_LENGTH, abs=1e-12)


def test_set_hanging_straight_at_rest_and_length_kept():
    _, handle, model, data = hand_scene(get_rope(1))
    b = handle.bind(model)
    data.qpos[:3] = [0.2, -0.1, 0.05]
    data.ctrl[:3] = data.qpos[:3]
    mujoco.mj_kinematics(model, data)
    b.set_hanging(model, data)
    x = b.centreline(model, data)
    p = handle.params
    tip = np.array([0.2, -0.1, 1.55])
    assert x[0] == pytest.approx(tip - [0, 0, p.clearance], abs=1e-9)
    assert np.abs(x[:, :2] - tip[:2]).max() < 1e-12  # straight down
    assert np.all(data.qvel[b.vert_dof] == 0) and np.all(data.qvel[b.twist_dof] == 0)
    mujoco.mj_step(model, data, nstep=int(0.3 / model.opt.timestep))
    x = b.centreline(model, data)
    hang = np.linalg.norm(x[-1] - x[0])
    assert hang == pytest.approx(p.length, rel=0.005)
    assert b.length(model, data) == pytest.approx(p.length, rel=0.005)
    assert np.abs(x[:, :2] - tip[:2]).max() < 1e-3
    assert not b.self_contact(model, data)


def test_set_hanging_sway_tilts_the_rope():
    _, handle, model, data = hand_scene(get_rope(4))
    mujoco.mj_kinematics(model, data)
    handle.set_hanging(model, data, sway_angle=0.1, sway_azimuth=math.pi / 2)
    x = handle.centreline(model, data)
    d = (x[-1] - x[1]) / np.linalg.norm(x[-1] - x[1])
    assert d == pytest.approx([0, math.sin(0.1), -math.cos(0.1)], abs=1e-12)
    with pytest.raises(ConfigError) as e:
        handle.set_hanging(model, data, sway_angle=2.0)
    assert str(e.value) == "sway_angle: must lie in [0, pi/2) rad, got 2.0"


def test_self_contact_true_for_a_rope_pressed_on_itself():
    _, handle, model, data = hand_scene(get_rope(1))
    b = handle.bind(model)
    p = handle.params
    # a helix of 3 turns with a pitch of 0.6 diameters: turn k lies on turn k + 1
    t = np.linspace(0, 6 * math.pi, 6000)
    r = 0.07
    helix = np.column_stack(
        [r * np.cos(t), r * np.sin(t), 1.0 - 0.6 * p.diameter * t / (2 * math.pi)]
    )
    x = crossings.resample_equal_chords(helix, p.segment_length, p.segments)
    b.set_vertices(model, data, x)
    assert b.self_contact(model, data)
    with pytest.raises(ConfigError) as e:
        b.set_vertices(model, data, x[:-1])
    assert str(e.value) == "x: must be finite with shape (31, 3), got shape (30, 3)"


def test_stretch_below_two_percent_in_a_fast_motion():
    """The reference hand motion (peak 3.9 m/s, wrist turns of 180+ degrees), no settling."""
    out = measures.measure_fast_motion(measures.Config(rope=1), settle_s=0.0, judge_knot=False)
    assert not out["diverged"]
    assert out["max_stretch"] < 0.02
    assert out["max_edge_strain"] < 0.05
    assert out["crossings"] == 0


def test_knot_pull_without_contact_shows_crossings():
    """With contacts off, pulling the loose knot passes the rope through itself: the crossing
    check sees it (and the knot is lost)."""
    out = measures.measure_knot_pull(measures.Config(rope=6), self_collide=False)
    assert out["knot_before"] == "trefoil"
    assert out["crossings"] >= 1
    assert out["knot_after"] != "trefoil"


# ------------------------------------------------------------------------------------------
# pure kernels
# ------------------------------------------------------------------------------------------
@given(st.tuples(finite, finite, finite).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_quat_from_x_to_rotates_ex_onto_axis(v):
    q = quat_from_x_to(np.array(v))
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.array([1.0, 0, 0]), q)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    assert out == pytest.approx(np.array(v) / np.linalg.norm(v), abs=1e-9)


@given(st.floats(0, 1.5), st.floats(-10, 10))
def test_sway_direction_angle(a, phi):
    d = sway_direction(a, phi)
    assert np.linalg.norm(d) == pytest.approx(1.0)
    assert math.acos(np.clip(-d[2], -1, 1)) == pytest.approx(a, abs=1e-7)


def test_hanging_vertices_spacing():
    x = hanging_vertices([0, 0, 1], [0, 0.03, 1], [0, 0, -1], 5)
    assert x.shape == (6, 3)
    assert np.linalg.norm(np.diff(x, axis=0), axis=1) == pytest.approx(np.full(5, 0.03))
    assert x[-1] == pytest.approx([0, 0.03, 1 - 4 * 0.03])


@given(
    st.lists(st.tuples(finite, finite, finite), min_size=2, max_size=8),
    st.floats(0.01, 0.5),
)
@settings(max_examples=50)
def test_points_at_arclength_on_a_polyline(dirs, seg):
    dirs = np.array(dirs)
    norms = np.linalg.norm(dirs, axis=1)
    dirs = np.where(norms[:, None] > 1e-6, dirs / np.maximum(norms, 1e-12)[:, None], [1, 0, 0])
    x = np.vstack([np.zeros(3), np.cumsum(seg * dirs, axis=0)])
    n = len(dirs)
    assert polyline_length(x) == pytest.approx(n * seg)
    s = np.linspace(0, n * seg, 7)
    pts = points_at_arclength(x, seg, s)
    k = np.minimum((s / seg).astype(int), n - 1)
    assert np.linalg.norm(pts - x[k], axis=1) == pytest.approx(s - k * seg, abs=1e-9)
    batched = points_at_arclength(np.stack([x, x + 1.0]), seg, s)
    assert batched[1] == pytest.approx(pts + 1.0)
    with pytest.raises(ConfigError):
        points_at_arclength(x, seg, np.array([n * seg * 1.01]))


@given(st.floats(-7, 7), st.floats(-7, 7))
def test_hand_angles_recover_ry_rx(a, b):
    q_b = np.array([math.cos(b / 2), 0, math.sin(b / 2), 0])
    q_a = np.array([math.cos(a / 2), math.sin(a / 2), 0, 0])
    q = np.zeros(4)
    mujoco.mju_mulQuat(q, q_b, q_a)  # R = Ry(b) Rx(a)
    a2, b2 = harness.hand_angles(q[None])
    r1, r2 = np.zeros(9), np.zeros(9)
    mujoco.mju_quat2Mat(r1, q)
    qa2 = np.array([math.cos(a2[0] / 2), math.sin(a2[0] / 2), 0, 0])
    qb2 = np.array([math.cos(b2[0] / 2), 0, math.sin(b2[0] / 2), 0])
    q2 = np.zeros(4)
    mujoco.mju_mulQuat(q2, qb2, qa2)
    mujoco.mju_quat2Mat(r2, q2)
    assert r2 == pytest.approx(r1, abs=1e-9)


def test_hand_angles_fit_the_reference_motion():
    """The reference motion is a pure Ry(b) Rx(a) rotation and the angles are continuous."""
    m = harness.HandMotion.load()
    a, b = harness.hand_angles(m.quat)
    assert np.abs(np.diff(a)).max() < 0.5 and np.abs(np.diff(b)).max() < 0.5
    q = np.zeros(4)
    for ai, bi, qi in zip(a, b, m.quat, strict=True):
        mujoco.mju_mulQuat(
            q,
            [math.cos(bi / 2), 0, math.sin(bi / 2), 0],
            [math.cos(ai / 2), math.sin(ai / 2), 0, 0],
        )
        assert abs(abs(q @ qi) / np.linalg.norm(qi) - 1) < 1e-8  # file has 5 decimals


pts = st.tuples(finite, finite, finite).map(np.array)


@given(pts, pts, pts, pts, pts, pts, pts, pts, st.floats(0, 1))
@settings(max_examples=60)
def test_coplanarity_cubic_matches_determinant(a, b, c, d, da, db, dc, dd, t):
    coef = crossings.coplanarity_cubic(a, b, c, d, da, db, dc, dd)
    at = [p + t * dp for p, dp in ((a, da), (b, db), (c, dc), (d, dd))]
    direct = np.linalg.det(np.array([at[1] - at[0], at[2] - at[0], at[3] - at[0]]))
    poly = coef[0] + coef[1] * t + coef[2] * t**2 + coef[3] * t**3
    assert poly == pytest.approx(direct, abs=1e-9 * (1 + np.abs(coef).sum()))


@given(st.lists(st.floats(0.02, 0.98), min_size=1, max_size=3, unique=True), st.floats(0.5, 3))
def test_cubic_roots_unit_finds_planted_roots(roots, scale):
    roots = sorted(roots)
    if len(roots) > 1 and min(np.diff(roots)) < 0.02:
        return
    p = np.poly1d(np.poly(roots)) * scale
    if len(roots) < 3:  # pad with roots outside [0, 1]
        p = p * np.poly1d(np.poly([1.7, -2.3][: 3 - len(roots)]))
    coef = p.coefficients[::-1][None, :4]
    found = crossings.cubic_roots_unit(coef)[0]
    found = np.sort(found[~np.isnan(found)])
    assert found == pytest.approx(np.array(roots), abs=1e-9)


@given(pts, pts, pts, pts)
@settings(max_examples=60)
def test_segment_distance_matches_sampling(p1, q1, p2, q2):
    s = np.linspace(0, 1, 201)
    a = p1 + s[:, None] * (q1 - p1)
    b = p2 + s[:, None] * (q2 - p2)
    brute = np.linalg.norm(a[:, None] - b[None], axis=2).min()
    dist = crossings.segment_distance(p1, q1, p2, q2)
    assert dist <= brute + 1e-9
    step = max(np.linalg.norm(q1 - p1), np.linalg.norm(q2 - p2)) / 200
    assert dist >= brute - step - 1e-9


def test_count_crossings_synthetic():
    # segment 0 lies on the x axis; segment 2 (along y at x = 0) sweeps down through it
    x0 = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 1], [0, 1, 1]], dtype=float)
    x1 = x0.copy()
    x1[2:, 2] = -1
    assert crossings.count_crossings(x0, x1) == 1
    assert crossings.count_crossings(x0, x1, min_gap=3) == 0  # pair (0, 2) not tested
    x1[2:, 0] = 3  # sweeps down beside segment 0 (x = 1.5 at z = 0), not through it
    assert crossings.count_crossings(x0, x1) == 0
    assert crossings.count_crossings(x0, x0) == 0
    assert crossings.count_run_crossings(np.stack([x0, x0, x0])) == 0


def test_resample_equal_chords_and_loose_knot():
    from flyknot.knot import classify_centreline

    for rid in (1, 5):
        p = get_rope(rid)
        x = crossings.overhand_knot_vertices(p)
        e = np.linalg.norm(np.diff(x, axis=0), axis=1)
        assert e == pytest.approx(np.full(p.segments, p.segment_length), rel=1e-9)
        assert classify_centreline(x) == "trefoil"
        n = p.segments
        gaps = [
            crossings.segment_distance(x[i], x[i + 1], x[j], x[j + 1])
            for i in range(n)
            for j in range(i + 2, n)
        ]
        assert min(gaps) > p.diameter  # loose: nothing touches at the start
    with pytest.raises(ConfigError):
        crossings.resample_equal_chords(np.array([[0, 0, 0], [0, 0, 0.1]]), 0.05, 3)


def test_twist_hinges_do_not_change_bending():
    """``twist=True`` (flexcomp, per-edge twist hinges) bends exactly like the default."""
    out = []
    for twist in (False, True):
        spec = mujoco.MjSpec()
        hand = spec.worldbody.add_body(name="hand", pos=[0, 0, 1.5])
        hand.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01, 0, 0], mass=0.1)
        p = get_rope(1)
        handle = add_rope(spec, p, anchor_body="hand", axis=(1, 0, 0), twist=twist)
        configure_options(spec, [p])
        model = spec.compile()
        data = mujoco.MjData(model)
        assert len(handle.twist_joints) == (p.segments if twist else 0)
        mujoco.mj_forward(model, data)
        mujoco.mj_step(model, data, nstep=200)  # a horizontal cantilever sagging for 0.2 s
        out.append(handle.centreline(model, data))
    assert out[0][-1, 2] < 1.5 - 0.1  # it does sag
    assert np.abs(out[0] - out[1]).max() < 1e-4  # [m]; measured 6e-6 (solver coupling only)


@pytest.mark.parametrize(
    ("table", "rope", "cone", "depth"),
    [("ropes_elastic.toml", 1, None, 0.02), ("ropes_elastic.toml", 4, None, 0.02),
     ("ropes.toml", 1, None, 0.005), ("ropes.toml", 4, None, 0.005),
     ("ropes.toml", 1, "pyramidal", 0.005)],
)  # fmt: skip
def test_a_lowered_rope_lands_on_the_floor(table, rope, cone, depth):
    """The hand lowers 1 m in 1 s, piling the rope on the floor: it stays on it.

    The rope starts 1 mrad off the vertical (1 mm at its end). Started exactly vertical, its
    segments stay in one line (nothing in the simulation breaks the symmetry), the column
    does not buckle, and with the elliptic cone the hand drives it 0.4-0.5 m into the floor
    (``docs/rope-model.md``); a real rope is never that straight.
    """
    path = ASSETS_DIR / table
    params, settings = load_rope_table(path)[rope], load_sim_settings(path)
    if cone is not None:
        settings = replace(settings, cone=cone)
    _, handle, model, data = hand_scene(params, settings=settings)
    mujoco.mj_kinematics(model, data)
    handle.set_hanging(model, data, sway_angle=1e-3)
    dt = model.opt.timestep
    lowest = np.inf
    for k in range(round(2.0 / dt)):
        data.ctrl[2] = -min(1.0, k * dt)
        mujoco.mj_step(model, data)
        lowest = min(lowest, handle.centreline(model, data)[:, 2].min())
    assert data.qpos[2] == pytest.approx(-1.0, abs=0.01)  # the hand got down
    assert lowest > -depth  # measured: elastic table 0-16 mm into the floor, the lab's < 1 mm

"""The rest-after-motion case of the rope validation suite: its measures on synthetic shapes
(exact values), its throw, its place in the suite, and one short run of it."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from flyknot.constants import ROPE_TABLE
from flyknot.errors import ConfigError
from flyknot.geometry import turning_angles
from flyknot_sim.rope_table import get_rope
from flyknot_tools.cli import main as tools_main
from flyknot_tools.rope_validate.cases import CASES
from flyknot_tools.rope_validate.common import G
from flyknot_tools.rope_validate.rest_after_motion import (
    KINK_DEG,
    Throw,
    couple_hold_angles,
    hanging_tensions,
    kinks,
    rest_after_motion,
    shape_offset,
    turned_to_swing,
)
from flyknot_tools.rope_validate.suite import CASE_NAMES, SUITES, model_with, picture_path

L = 0.05
"""Segment length of the synthetic shapes [m]."""
N = 21
"""Segments of the synthetic shapes: 20 free ones below the held one (an even number, so a
zig-zag's free end lies on the vertical through vertex 1)."""


def straight(n: int = N) -> np.ndarray:
    """A rope hanging straight down from the origin, n segments of length L."""
    return np.array([[0.0, 0.0, -L * k] for k in range(n + 1)])


def zigzag(half_angle: float, n: int = N) -> np.ndarray:
    """The held segment straight down, then segments alternately half_angle [rad] to +x and
    to -x of the vertical: each free joint turns by 2 half_angle, vertex 1 by half_angle."""
    x = [np.zeros(3), np.array([0.0, 0.0, -L])]
    for j in range(n - 1):
        side = 1.0 if j % 2 == 0 else -1.0
        x.append(x[-1] + L * np.array([side * math.sin(half_angle), 0.0, -math.cos(half_angle)]))
    return np.array(x)


def test_turning_angles_of_a_straight_and_a_zigzag_rope():
    assert np.array_equal(turning_angles(straight()), np.zeros(N - 1))
    a = math.radians(10.0)
    turn = turning_angles(zigzag(a))
    assert turn[0] == pytest.approx(a, abs=1e-12)  # the joint at the held segment
    assert turn[1:] == pytest.approx(np.full(N - 2, 2 * a), abs=1e-12)
    hook = np.array([[0.0, 0, 0], [0, 0, -L], [L, 0, -L], [L, 0, 0]])  # two right angles
    assert turning_angles(hook) == pytest.approx([math.pi / 2, math.pi / 2], abs=1e-12)


def test_kinks_of_a_straight_and_a_zigzag_rope():
    none = np.zeros(N - 1)
    flat = kinks(straight(), straight(), none)
    assert (flat.median_excess_deg, flat.max_excess_deg, flat.over_30) == (0.0, 0.0, 0)
    zz = kinks(zigzag(math.radians(20.0)), straight(), none)  # 40 deg at every free joint
    assert zz.median_turn_deg == pytest.approx(40.0, abs=1e-9)
    assert zz.max_turn_deg == pytest.approx(40.0, abs=1e-9)
    assert zz.median_excess_deg == pytest.approx(40.0, abs=1e-9)
    assert zz.over_30 == N - 2
    held = kinks(zigzag(math.radians(20.0)), straight(), np.full(N - 1, math.radians(36.0)))
    assert (
        held.median_excess_deg == pytest.approx(4.0, abs=1e-9) and held.median_excess_deg < KINK_DEG
    )
    # against a reference bent the same way, a zig-zag has no excess
    same = kinks(zigzag(math.radians(20.0)), zigzag(math.radians(20.0)), none)
    assert same.median_excess_deg == pytest.approx(0.0, abs=1e-9) and same.over_30 == N - 2


def test_shape_offset_turns_out_the_swing_but_not_a_zigzag():
    ref = straight()
    swing = np.radians(25.0)
    rot = np.array(
        [[math.cos(swing), 0, math.sin(swing)], [0, 1, 0], [-math.sin(swing), 0, math.cos(swing)]]
    )
    swung = ref.copy()
    swung[2:] = (ref[2:] - ref[1]) @ rot.T + ref[1]  # swung rigidly about vertex 1
    assert shape_offset(swung, ref) == pytest.approx(0.0, abs=1e-12)
    assert turned_to_swing(swung, ref) == pytest.approx(swung, abs=1e-12)
    assert np.linalg.norm(swung[-1] - ref[-1]) > 0.3  # the free end is far off
    a = math.radians(15.0)
    m = N - 1  # free segments; even: the zig-zag's chord is vertical, nothing is turned
    expected = max(
        m * L * (1 - math.cos(a)),  # the free end, lifted
        math.hypot(L * math.sin(a), (m - 1) * L * (1 - math.cos(a))),  # the vertex above it
    )
    assert shape_offset(zigzag(a), ref) == pytest.approx(expected, abs=1e-12)


def test_hanging_tensions_carry_the_weight_below():
    p = get_rope(1)
    t = hanging_tensions(p)
    assert t[-1] == pytest.approx(G * (p.end_mass + p.density * p.segment_length / 2))
    assert np.diff(t) == pytest.approx(np.full(p.segments - 2, -G * p.density * p.segment_length))


def test_the_couple_holds_a_zigzag_in_cords_and_the_chain():
    assert np.array_equal(couple_hold_angles(get_rope(7)), np.zeros(29))  # latex: no couple
    bare = replace(get_rope(6), link_friction_radius=0.0)  # a chain without its links' friction
    assert np.array_equal(couple_hold_angles(bare), np.zeros(29))
    p = get_rope(1)
    hold = couple_hold_angles(p)
    seg, m0, b = p.segment_length, p.frictional_couple, p.bending_stiffness
    t = hanging_tensions(p)
    assert hold == pytest.approx(4 * m0 / (t * seg + 4 * b / seg), rel=1e-12)
    # at the held end's tension the couple holds 12 deg, at the end weight's 30 deg
    assert math.degrees(hold[1]) == pytest.approx(11.9, abs=0.1)
    assert math.degrees(hold[-1]) == pytest.approx(30.3, abs=0.1)
    assert np.all(np.diff(hold) > 0)


def test_the_links_friction_holds_a_zigzag_in_the_chain():
    """With the links' friction the chain's joints hold M_0,k = mu r T_k (the joint's tension
    at rest): a zig-zag of about 4 mu r / l at every joint (9-10 deg at r = 2.5 mm)."""
    p = get_rope(6)
    assert p.link_friction_radius == 0.0025
    hold = couple_hold_angles(p)
    t = hanging_tensions(p)
    joint = np.r_[t[0], (t[:-1] + t[1:]) / 2]  # joint 1 reads the edge below
    arm, seg = p.friction * 0.0025, p.segment_length
    assert hold == pytest.approx(4 * arm * joint / (t * seg), rel=1e-12)
    assert math.degrees(hold[1:].min()) == pytest.approx(9.05, abs=0.05)
    assert math.degrees(hold.max()) == pytest.approx(10.3, abs=0.05)


def test_the_throw_is_the_flying_knot_motion_then_still():
    throw = Throw()
    assert throw.duration == pytest.approx(0.76) and throw.peak_speed == pytest.approx(
        3.87, abs=0.01
    )
    fast = Throw(speed=1.2)
    assert fast.duration == pytest.approx(0.76 / 1.2)
    assert fast.peak_speed == pytest.approx(1.2 * throw.peak_speed, rel=1e-9)
    path = throw.path(0.001)
    q0, _ = path(0.0)
    assert np.array_equal(q0, np.zeros(6))  # from where the holder is
    q_end, qd_end = path(5.0)
    assert np.array_equal(q_end, path(throw.duration)[0]) and not qd_end.any()
    assert q_end[:3] == pytest.approx([0.37401, 0.15953, -0.09431], abs=1e-9)
    assert abs(q_end[3]) > 1.0  # the hand turned over
    assert not Throw(turn=False).path(0.001)(5.0)[0][3:].any()
    assert "3.9 m/s" in throw.label()
    with pytest.raises(ConfigError):
        Throw(speed=0.0)


def test_the_case_is_in_the_suite(tmp_path):
    assert "rest_after_motion" in CASE_NAMES and CASES["rest_after_motion"] is rest_after_motion
    m = model_with(get_rope(6), {})
    for suite in ("full", "quick"):
        assert [name for name, _ in SUITES[suite](m)].count("rest_after_motion") == 1
    assert picture_path(None, "rest_after_motion", m) is None
    assert picture_path(tmp_path, "rest_after_motion", m) == (
        tmp_path / "rest_after_motion_rope6_default.png"
    )
    odd = model_with(get_rope(6), {"cd": "2.3"})
    assert picture_path(tmp_path, "rest_after_motion", odd).name == (
        "rest_after_motion_rope6_cd_2.3.png"
    )


FIELDS = {
    "throw",
    "wait_s",
    "median_excess_deg",
    "max_excess_deg",
    "median_turn_deg",
    "max_turn_deg",
    "joints_over_30_deg",
    "lowered_median_turn_deg",
    "couple_holds_deg",
    "shape_offset_m",
    "end_offset_m",
    "end_speed_m_s",
    "rest_speed_m_s",
    "final",
    "picture",
}


def test_a_short_run_reports_its_numbers_and_draws(tmp_path):
    """The chain (the fastest rope to simulate) thrown, 2 s of wait: every number is there,
    the verdict is the median's, and the picture is written (matplotlib: no OpenGL)."""
    picture = tmp_path / "rest.png"
    r = rest_after_motion(model_with(get_rope(6), {}), wait_s=2.0, reference_s=0.5, picture=picture)
    assert r.case == "rest_after_motion" and r.rope == 6 and r.variant == "default"
    assert set(r.measured) == FIELDS
    assert r.passed == (r.measured["median_excess_deg"] <= KINK_DEG)
    assert r.measured["couple_holds_deg"] == pytest.approx([9.05, 10.3], abs=0.1)
    assert r.measured["lowered_median_turn_deg"] == pytest.approx(0.0, abs=0.5)
    assert r.applies == (r.measured["final"] == "unknot")
    assert picture.stat().st_size > 10_000 and picture.read_bytes()[:4] == b"\x89PNG"
    assert "s after the throw: median turning" in r.detail
    json.dumps(r.to_json())


def test_cli_writes_the_pictures(tmp_path, capsys):
    args = ["rope-validate", "--ropes", "6", "--quick", "--json", "--table", str(ROPE_TABLE)]
    code = tools_main([*args, "--cases", "rest_after_motion", "--pictures", str(tmp_path)])
    (row,) = json.loads(capsys.readouterr().out)
    assert row["case"] == "rest_after_motion" and set(row["measured"]) == FIELDS
    assert (tmp_path / "rest_after_motion_rope6_default.png").is_file()
    assert code == (0 if row["passed"] or not row["applies"] else 1)

"""The knot verdict: constructed ropes, recorded trials of each class, invariances, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError, RecordError
from flyknot.geometry import so3_exp
from flyknot.knot import closure_votes
from flyknot.verdict import (
    CLASSES,
    JudgeParams,
    Verdict,
    judge_centreline,
    knot_core,
    operator_verdict,
    tube_knot,
    with_tube,
)
from tests.knot_curves import (
    TUBE_AXIS,
    end_in_its_loop,
    figure_eight,
    loop_round_held_end,
    overhand,
    straight,
    transformed,
)

DATA = Path(__file__).parent / "data" / "verdicts"

CASES = {
    # name: (curve, expected class)
    "tight knot 20 cm above the free end": (overhand(above=0.6, tail=0.2), "knot"),
    "the same knot 5 cm below the grip": (overhand(above=0.05, tail=0.6), "knot"),
    "the same knot at the tube's tip": (overhand(above=0.0, tail=0.6), "wrapped_at_grip"),
    "a loose knot": (overhand(above=0.3, tail=0.2, scale=0.03), "knot"),
    "a figure-eight": (figure_eight(), "other_knot"),
    "one loop round the held end, tail hanging": (loop_round_held_end(), "wrapped_at_grip"),
    "a straight rope": (straight(), "unknot"),
    "the free end half way through its loop": (end_in_its_loop(), "ambiguous"),
}
DECISIVE = sorted(name for name, (_, klass) in CASES.items() if klass != "ambiguous")


def _mirror(points: np.ndarray) -> np.ndarray:
    return points * np.array([-1.0, 1.0, 1.0])


def _coarse(points: np.ndarray) -> np.ndarray:
    """Every other point, the ends kept."""
    idx = sorted(set(range(0, len(points), 2)) | {len(points) - 1})
    return points[idx]


def _noisy(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """1 mm of noise on every point but the held end's two (clamped in the tube)."""
    out = points + np.random.default_rng(seed).normal(0.0, 0.001, points.shape)
    out[:2] = points[:2]
    return out


@pytest.mark.parametrize("name", list(CASES))
def test_constructed_ropes(name):
    curve, klass = CASES[name]
    v = judge_centreline(curve, TUBE_AXIS)
    assert v.klass == klass, v.describe()
    assert v.success == (klass == "knot")


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("variant", ["coarse", "noisy", "rotated", "mirrored", "reversed knot"])
def test_constructed_ropes_under_changes(name, variant):
    curve, klass = CASES[name]
    axis = TUBE_AXIS
    if variant == "coarse":
        curve = _coarse(curve)
    elif variant == "noisy":
        curve = _noisy(curve)
    elif variant == "rotated":
        r = so3_exp(np.array([0.4, -1.1, 0.7]))
        curve, axis = transformed(curve, r, np.array([0.3, -0.2, 1.5]), 1.0), r @ TUBE_AXIS
    elif variant == "mirrored":  # the other handedness
        curve = _mirror(curve)
    else:  # the knot part traversed the other way: a mirror image rotated back about z
        curve = _mirror(curve) * np.array([1.0, -1.0, 1.0])
    assert judge_centreline(curve, axis).klass == klass


@pytest.mark.parametrize(
    ("stem", "klass"),
    [
        ("knot_hand_swipe", "knot"),
        ("knot_rope1_repeat", "knot"),
        ("knot_low_rope3_repeat", "knot"),
        ("unknot_rope1_trial1", "unknot"),
        ("wrapped_rope1_main_job_trial4", "wrapped_at_grip"),
        ("wrapped_rope6_trial6", "wrapped_at_grip"),
    ],
)
def test_recorded_trials(stem, klass):
    points = np.load(DATA / f"{stem}.npy")
    v = judge_centreline(points)
    assert v.klass == klass, v.describe()
    if klass == "knot":
        assert v.core_from_held_m >= JudgeParams().clearance_m
        assert v.share >= JudgeParams().supermajority


def test_the_main_jobs_wrap_is_a_coin_flip_with_free_closures_and_decided_with_the_tube():
    points = np.load(DATA / "wrapped_rope1_main_job_trial4.npy")
    free = closure_votes(points)
    assert {free["unknot"], free["trefoil"]} == {15, 16}
    v = judge_centreline(points)
    assert v.votes == {"trefoil": 31} and v.core_from_held_m == 0.0 and not v.success


def test_knot_core_lies_round_the_knot():
    curve = overhand(above=0.6, tail=0.2)
    i, j = knot_core(with_tube(curve, TUBE_AXIS, 1.0), "trefoil", 15)
    # The knot's arc (points 20-79) starts after 0.6 m of straight rope (20 points 0.03 m
    # apart); its opened ends (where the tails join) are not part of the knotted core.
    assert 20 < i - 1 < 40 and 60 < j - 1 < 80
    v = judge_centreline(curve, TUBE_AXIS)
    assert v.core == (i - 1, j - 1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    assert v.core_from_held_m == pytest.approx(arc[i - 1])
    near = judge_centreline(overhand(above=0.05, tail=0.6), TUBE_AXIS)
    assert near.core_from_held_m == pytest.approx(v.core_from_held_m - 0.55, abs=0.02)


@settings(max_examples=15, deadline=None)
@given(
    rot=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    shift=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
    scale=st.floats(0.5, 2.0),
    name=st.sampled_from(DECISIVE),
)
def test_rigid_motions_leave_the_knot_and_its_vote_alone(rot, shift, scale, name):
    # Only without a floor: a rigid motion can lower a knot onto the floor.
    curve, free = CASES[name][0], JudgeParams(floor_z_m=None)
    r = so3_exp(np.array(rot))
    moved = transformed(curve, r, np.array(shift), 1.0)
    v0 = judge_centreline(curve, TUBE_AXIS, free)
    v1 = judge_centreline(moved, r @ TUBE_AXIS, free)
    assert v0.klass == CASES[name][1]
    assert (v1.klass, v1.knot) == (v0.klass, v0.knot)
    if v0.core is not None:  # the closure directions are fixed in space: a vertex or two
        assert np.abs(np.subtract(v1.core, v0.core)).max() <= 2
    # Scaling keeps the knot type; distances scale with it, so only the topology is compared.
    scaled = transformed(curve, np.eye(3), np.zeros(3), scale)
    assert tube_knot(scaled, TUBE_AXIS) == tube_knot(curve, TUBE_AXIS)


def test_verdict_round_trips_through_json():
    v = judge_centreline(overhand(above=0.6, tail=0.2), TUBE_AXIS)
    assert Verdict.from_json(v.to_json()) == v
    assert v.describe().startswith("knot (trefoil 31/31, 0.")


def test_bad_input_names_the_field():
    with pytest.raises(ConfigError, match=r"^klass: unknown value 'tied' \(valid choices: "):
        Verdict("tied", "trefoil")
    with pytest.raises(ConfigError, match=r"^supermajority: must be in \(0.5, 1\], got 0.4$"):
        JudgeParams(supermajority=0.4)
    with pytest.raises(RecordError, match=r"^verdict: expected keys "):
        Verdict.from_json({"klass": "knot"})
    with pytest.raises(RecordError, match=r"^tube_axis: must be a finite, non-zero vector$"):
        judge_centreline(straight(), np.zeros(3))
    with pytest.raises(RecordError, match=r"^points: need at least 4 points, got 2$"):
        judge_centreline(straight()[:2])
    with pytest.raises(
        ConfigError, match=r"^floor_clearance_m: must be a finite number > 0, got 0.0$"
    ):
        JudgeParams(floor_clearance_m=0.0)
    with pytest.raises(ConfigError, match=r"^floor_z_m: must be a finite height or None, got nan$"):
        JudgeParams(floor_z_m=float("nan"))
    assert set(CLASSES) == {
        "knot",
        "wrapped_at_grip",
        "ambiguous",
        "on_floor",
        "other_knot",
        "unknot",
    }
    assert operator_verdict("wrapped").klass == "wrapped_at_grip"
    assert operator_verdict("floor").klass == "on_floor"
    assert not operator_verdict("floor").success


@pytest.mark.parametrize(
    ("core_lowest", "klass"),
    [(0.0041, "on_floor"), (0.018, "on_floor"), (0.019, "knot"), (0.05, "knot")],
)
def test_a_knot_lying_on_the_floor_is_not_a_knot_in_the_hanging_rope(core_lowest, klass):
    """The same tight knot in a 9 mm rope lowered until its core's lowest centreline point is
    ``core_lowest`` above the floor, its tail (0.3 m) lying on the floor: within 3 radii and
    5 mm (18.5 mm: on the floor or on its own tail there) the knot lies on the floor."""
    rope = overhand(above=0.6, tail=0.0)
    rope = rope - np.array([0.0, 0.0, rope[:, 2].min() - core_lowest])
    tail = rope[-1] + np.outer(np.linspace(0.03, 0.3, 10), [1.0, 0.0, 0.0])
    tail[:, 2] = min(core_lowest, 0.0045)  # lying on the floor
    line = np.vstack([rope, tail])
    nine_mm = JudgeParams(rope_radius_m=0.0045)
    v = judge_centreline(line, TUBE_AXIS, nine_mm)
    assert (v.klass, v.knot) == (klass, "trefoil")
    assert v.success is (klass == "knot")
    assert line[v.core[0] : v.core[1] + 1, 2].min() == pytest.approx(core_lowest, abs=1e-3)
    # A rope twice as thick lies on the floor from twice as high; no floor: a knot.
    thick = judge_centreline(line, TUBE_AXIS, JudgeParams(rope_radius_m=0.009))
    assert thick.klass == ("on_floor" if core_lowest < 0.032 else "knot")
    assert judge_centreline(line, TUBE_AXIS, JudgeParams(floor_z_m=None)).success
    # The same knot with its tail lifted off the floor hangs, however low.
    lifted = line.copy()
    lifted[len(rope) :, 2] = 0.011
    if core_lowest > 0.011:
        assert judge_centreline(lifted, TUBE_AXIS, nine_mm).success

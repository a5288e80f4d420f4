"""Tests of the hand lab, the flying-knot motion family and its replay, the demonstration
search (score, variants, search, synthesis) and the ``flyknot demo replay`` and
``flyknot-tools demo synthesize`` commands (flyknot_sim.hand*, flyknot_tools.hand_demos,
flyknot_app.demo_cli, flyknot_tools.cli)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError
from flyknot_app import demo_cli
from flyknot_sim.hand import HandLab, judged_frames, trial_demonstration
from flyknot_sim.hand_motion import BLEND, N_PARAMS, KnotMotion, bernstein, windup_warp
from flyknot_sim.hand_params import HandParams, HandVariation, hand_rotation
from flyknot_sim.hand_replay import (
    REPLAY_GENERATOR,
    hand_from_demo,
    motion_from_demo,
    replay,
)
from flyknot_sim.mocap import MocapParams
from flyknot_sim.rope_table import get_rope, load_sim_settings
from flyknot_tools import cli as tools_cli
from flyknot_tools.hand_demos.reference import (
    REFERENCE_MOTION,
    angles_from_quat,
    fit_motion,
    load_reference_motion,
)
from flyknot_tools.hand_demos.score import (
    EXCURSION_LIMIT,
    SPEED_LIMIT,
    ScoreWeights,
    TrialSummary,
    score,
    writhe,
)
from flyknot_tools.hand_demos.search import (
    SearchConfig,
    evaluate,
    motion_summary,
    search,
    within_limits,
)
from flyknot_tools.hand_demos.synthesis import (
    GENERATOR,
    GENERATOR_VERSION,
    LEGACY_GENERATORS,
    pace_metadata,
    rope_metadata,
)
from flyknot_tools.hand_demos.variants import (
    ANGLE_BOUND,
    PACE_WEIGHT,
    VARIANTS,
    VIA_BOUND,
    Variant,
    get_variant,
    param_bounds,
)
from tests.recorded_on import assert_recorded_again

SHIPPED = ("fast", "slow", "swipe", "inverse")
FAST = VARIANTS["fast"]


def _motion_from_unit(u: np.ndarray, variant: Variant = FAST) -> KnotMotion:
    lo, hi = param_bounds(variant)
    return KnotMotion(lo + (hi - lo) * np.asarray(u))


unit_params = st.lists(st.floats(0.0, 1.0, allow_nan=False), min_size=N_PARAMS, max_size=N_PARAMS)


# ----------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------
def test_bernstein_partition_of_unity_and_derivatives_match_finite_differences():
    s = np.linspace(0.05, 0.95, 13)
    h = 1e-6
    b0 = bernstein(s)
    np.testing.assert_allclose(b0.sum(axis=1), 1.0, atol=1e-12)
    for order in (1, 2):
        fd = (bernstein(s + h, order=order - 1) - bernstein(s - h, order=order - 1)) / (2 * h)
        np.testing.assert_allclose(bernstein(s, order=order), fd, atol=1e-5 * 8**order)
    with pytest.raises(ConfigError, match=r"^order: must lie in 0\.\.8, got 9$"):
        bernstein(s, order=9)


@pytest.mark.parametrize("p, r", [(0.0, 1.0), (0.3, 0.3), (0.05, 0.2), (0.5, 0.1), (0.45, 1.0)])
def test_windup_warp_is_monotone_with_exact_ends_and_derivatives(p, r):
    u = np.linspace(0.0, 1.0, 2001)
    s0, s1, s2 = (windup_warp(u, p, r, k) for k in range(3))
    assert s0[0] == 0.0 and s0[-1] == pytest.approx(1.0, abs=1e-12)
    assert np.all(np.diff(s0) > 0) and s1.min() > 0
    assert s2[0] == 0.0 and s2[-1] == 0.0
    h = 1e-6
    # away from the kinks of s'' (the ends of the speed change) central differences are exact
    # to O(h^2)
    d = min(BLEND, p, 1 - p)
    uu = u[(np.abs(u - (p - d)) > 1e-3) & (np.abs(u - (p + d)) > 1e-3) & (u > h) & (u < 1 - h)]
    fd1 = (windup_warp(uu + h, p, r) - windup_warp(uu - h, p, r)) / (2 * h)
    fd2 = (windup_warp(uu + h, p, r, 1) - windup_warp(uu - h, p, r, 1)) / (2 * h)
    np.testing.assert_allclose(windup_warp(uu, p, r, 1), fd1, atol=1e-6)
    np.testing.assert_allclose(windup_warp(uu, p, r, 2), fd2, atol=1e-5)
    if p == 0.0 or r == 1.0:
        np.testing.assert_allclose(s0, u, atol=1e-15)


@pytest.mark.parametrize("p", [1e-310, 1e-12, 1.0 - 1e-12])
def test_windup_warp_of_a_vanishing_blend_is_the_identity_without_overflow(p):
    u = np.linspace(0.0, 1.0, 101)
    with np.errstate(all="raise"):  # a blend of 1e-310 overflowed pi / (2 d)
        for order, want in enumerate((u, np.ones_like(u), np.zeros_like(u))):
            np.testing.assert_array_equal(windup_warp(u, p, 0.2, order), want)


def test_motion_curve_derivatives_match_finite_differences():
    m = load_reference_motion().with_windup(0.95, 0.2)
    t = np.linspace(0.01, m.duration - 0.01, 157)
    h = 1e-6
    for order in (1, 2):
        fd = (m.curves(t + h, order - 1) - m.curves(t - h, order - 1)) / (2 * h)
        scale = np.abs(m.curves(t, order)).max()
        np.testing.assert_allclose(m.curves(t, order), fd, atol=1e-6 * scale)


@settings(max_examples=40, deadline=None)
@given(unit_params)
def test_every_motion_starts_and_ends_at_rest_and_keeps_its_bounds(u):
    m = _motion_from_unit(np.array(u))
    ends = np.array([0.0, m.duration])
    q, qd, qdd = m.joint_targets(ends)
    np.testing.assert_allclose(q[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(qd, 0.0, atol=1e-9)
    np.testing.assert_allclose(qdd, 0.0, atol=1e-6)
    # held before and after the motion
    q_out, qd_out, _ = m.joint_targets(np.array([-0.3, m.duration + 0.5]))
    np.testing.assert_allclose(q_out, q, atol=1e-12)
    np.testing.assert_array_equal(qd_out, 0.0)
    # Bezier curves stay in the convex hull of their control points
    y = m.curves(np.linspace(0.0, m.duration, 301))
    assert np.abs(y[:, 3:]).max() <= ANGLE_BOUND + 1e-12
    assert np.abs(y[:, :3]).max() <= VIA_BOUND + 1e-12
    assert q[1, 5] == 0.0  # no turn about z


def test_motion_validation_messages():
    x = load_reference_motion().x.copy()
    with pytest.raises(ConfigError, match=r"^KnotMotion\.x: must hold 23 numbers, got 22$"):
        KnotMotion(x[:-1])
    bad = x.copy()
    bad[0] = 0.05
    with pytest.raises(ConfigError, match=r"^KnotMotion\.T: must lie in \[0\.1, 5\] s"):
        KnotMotion(bad)
    bad = x.copy()
    bad[1] = 0.7
    with pytest.raises(ConfigError, match=r"^KnotMotion\.p: must lie in \[0, 0\.6\], got 0\.7$"):
        KnotMotion(bad)
    with pytest.raises(RecordError, match=r"^motion parameters lack T, p$"):
        KnotMotion.from_dict(
            {k: v for k, v in load_reference_motion().to_dict().items() if k not in ("T", "p")}
        )


def test_to_dict_round_trip_and_mirror_image():
    m = load_reference_motion()
    back = KnotMotion.from_dict(json.loads(json.dumps(m.to_dict())))
    np.testing.assert_array_equal(back.x, m.x)
    mm = m.mirrored()
    np.testing.assert_array_equal(mm.mirrored().x, m.x)
    t = np.linspace(0, m.duration, 50)
    y, ym = m.curves(t), mm.curves(t)
    s = np.diag([1.0, -1.0, 1.0])
    np.testing.assert_allclose(ym[:, :3], y[:, :3] @ s, atol=1e-12)
    r = hand_rotation(y[:, 4], y[:, 3])
    rm = hand_rotation(ym[:, 4], ym[:, 3])
    np.testing.assert_allclose(rm, s @ r @ s, atol=1e-12)


def test_fit_recovers_a_family_member_and_the_reference_fits_closely():
    m = load_reference_motion()
    t = np.arange(0, 1.0, 0.005)
    y = m.curves(t - 0.05)
    from scipy.spatial.transform import Rotation

    quat = Rotation.from_matrix(hand_rotation(y[:, 4], y[:, 3])).as_quat(scalar_first=True)
    fit, t0, err = fit_motion(t, y[:, :3], quat, durations=[m.duration], starts=[0.05])
    assert t0 == 0.05 and err < 1e-9
    np.testing.assert_allclose(fit.x, m.x, atol=1e-7)
    a = np.loadtxt(REFERENCE_MOTION, delimiter=",", comments="#", skiprows=2)
    _, _, err_ref = fit_motion(a[:, 0], a[:, 1:4], a[:, 4:8], durations=[m.duration])
    assert err_ref < 0.005  # the study's motion is a member up to rounding (0.4 mm, 0.2 deg)


@settings(max_examples=30, deadline=None)
@given(st.floats(-8, 8), st.floats(-8, 8))
def test_angles_from_quat_inverts_the_hinge_chain(a, b):
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(hand_rotation(np.array([b]), np.array([a]))).as_quat(scalar_first=True)
    a2, b2, res = angles_from_quat(q)
    np.testing.assert_allclose(
        hand_rotation(b2, a2), hand_rotation(np.array([b]), np.array([a])), atol=1e-12
    )
    assert res[0] < 1e-12


# ----------------------------------------------------------------------------------------
# writhe and score
# ----------------------------------------------------------------------------------------
def _helix(turns: float = 2.0, n: int = 60) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi * turns, n)
    return np.column_stack([np.cos(t), np.sin(t), 0.3 * t])


def test_writhe_is_zero_for_planar_curves_and_odd_under_reflection():
    t = np.linspace(0, 3 * np.pi, 50)
    planar = np.column_stack([np.cos(t) * t, np.sin(t) * t, np.zeros_like(t)])
    assert writhe(planar) == pytest.approx(0.0, abs=1e-12)
    h = _helix()
    w = writhe(h)
    assert abs(w) > 0.1
    assert writhe(h * np.array([1.0, -1.0, 1.0])) == pytest.approx(-w, rel=1e-12)
    with pytest.raises(
        RecordError, match=r"^points must have shape \(n, 3\) with n >= 2, got \(5,\)$"
    ):
        writhe(np.zeros(5))


@settings(max_examples=25, deadline=None)
@given(
    st.floats(0.1, 10.0),
    st.lists(st.floats(-1, 1), min_size=4, max_size=4),
    st.lists(st.floats(-2, 2), min_size=3, max_size=3),
)
def test_writhe_is_invariant_under_rigid_motion_and_scaling(scale, q, shift):
    from scipy.spatial.transform import Rotation

    if np.linalg.norm(q) < 1e-3:
        q = [1.0, 0.0, 0.0, 0.0]
    r = Rotation.from_quat(q).as_matrix()
    h = _helix(1.5, 40)
    moved = scale * h @ r.T + np.array(shift)
    # asin of dot products near +-1 loses half the digits: agreement to ~sqrt(eps)
    assert writhe(moved) == pytest.approx(writhe(h), abs=1e-6)


def test_score_orders_outcomes_and_penalises_limits():
    w = ScoreWeights()
    knotted = TrialSummary(tied=True, settle_fraction=1.0, knot_any=True, contact=True, writhe=3.2)
    slid_off = TrialSummary(
        tied=False, settle_fraction=0.4, knot_any=True, contact=True, writhe=3.2
    )
    touched = TrialSummary(contact=True, writhe=1.0)
    nothing = TrialSummary()
    scores = [score(s, w) for s in (knotted, slid_off, touched, nothing)]
    assert scores == sorted(scores, reverse=True)
    assert scores[0] == pytest.approx(100 + 30 + 10 + 5 + 5)
    assert scores[1] == pytest.approx(0.4 * 30 + 10 + 5 + 5)
    assert scores[3] == 0.0
    # a knotted settle beats any unknotted one, whatever the shaping terms
    best_unknotted = TrialSummary(
        tied=False, settle_fraction=1.0, knot_any=True, contact=True, writhe=99.0
    )
    assert score(knotted, w) > score(best_unknotted, w)
    fast = replace(knotted, peak_speed=9.0, excursion=0.8)
    assert score(fast, w) == pytest.approx(scores[0] - 20 * 1.0 - 100 * 0.1)
    rejected = replace(nothing, simulated=False, peak_speed=8.5)
    assert score(rejected, w) == pytest.approx(-10 - 20 * 0.5)
    assert score(rejected, w) < score(nothing, w)


def test_summary_and_weights_validation_messages():
    with pytest.raises(
        ConfigError, match=r"^TrialSummary\.settle_fraction: must lie in \[0, 1\], got 1\.5$"
    ):
        TrialSummary(settle_fraction=1.5)
    with pytest.raises(
        ConfigError, match=r"^TrialSummary\.writhe: must be a finite number >= 0, got -1\.0$"
    ):
        TrialSummary(writhe=-1.0)
    with pytest.raises(ConfigError, match=r"^ScoreWeights\.tied: must be a finite number >= 0"):
        ScoreWeights(tied=-1.0)


def test_variants_limits_and_stages():
    with pytest.raises(ConfigError) as e:
        get_variant("loop")
    assert str(e.value) == (
        "variant: unknown value 'loop' (valid choices: fast, slow, swipe, inverse)"
    )
    kinds = {name: [k for k, _ in v.stages()] for name, v in VARIANTS.items()}
    assert kinds["fast"] == ["throw"]
    assert kinds["slow"] == ["throw", "windup"]
    assert kinds["inverse"] == ["throw", "windup"]
    assert kinds["swipe"] == ["throw", "windup"]
    assert VARIANTS["inverse"].seed_motion().x[1 + 2 + 4] == pytest.approx(
        -load_reference_motion().x[1 + 2 + 4]
    )  # y3 mirrored
    ref = load_reference_motion()
    dz, dh = VARIANTS["swipe"].strike(ref)
    assert dz > dh > 0  # the reference strikes mostly downwards...
    assert VARIANTS["swipe"].violation(ref) == pytest.approx(dz - dh)  # ...so it violates
    assert VARIANTS["fast"].violation(ref) == 0.0
    speed, excursion = ref.hand_limits()
    assert 3.0 < speed < SPEED_LIMIT and 0.4 < excursion < EXCURSION_LIMIT
    slow = ref.with_windup(1.04, 0.2)
    assert slow.duration == 1.04 and slow.core_duration == pytest.approx(ref.duration)
    assert slow.hand_limits()[0] == pytest.approx(speed, rel=1e-3)


def test_pace_matches_finite_differences_of_the_exit_axis():
    ref = load_reference_motion()
    speed, rate, accel = FAST.pace(ref, dt=1e-4)
    t = np.arange(0.0, ref.duration, 1e-4)
    y = ref.curves(t)
    axis = -hand_rotation(y[:, 4], y[:, 3])[:, :, 2]  # the rope leaves along the hand's -z
    fd_rate = np.linalg.norm(np.gradient(axis, t, axis=0), axis=1).max()
    vel = np.gradient(y[:, :3], t, axis=0)
    fd_speed = np.linalg.norm(vel, axis=1).max()
    fd_accel = np.linalg.norm(np.gradient(vel, t, axis=0)[1:-1], axis=1).max()
    assert rate == pytest.approx(fd_rate, rel=1e-3)
    assert speed == pytest.approx(fd_speed, rel=1e-3)
    assert accel == pytest.approx(fd_accel, rel=1e-3)
    assert rate > 20.0  # the hand-paced reference flicks its wrist


def test_pace_limits_count_in_the_violation():
    ref = load_reference_motion()
    speed, rate, accel = FAST.pace(ref)
    paced = replace(FAST, axis_rate_limit=rate / 2, speed_limit=speed * 2)
    assert paced.violation(ref) == pytest.approx(PACE_WEIGHT * 1.0)
    both = replace(FAST, axis_rate_limit=rate / 2, speed_limit=speed / 4)
    assert both.violation(ref) == pytest.approx(PACE_WEIGHT * 4.0)
    three = replace(both, accel_limit=accel / 2)
    assert three.violation(ref) == pytest.approx(PACE_WEIGHT * 5.0)
    assert replace(FAST, axis_rate_limit=2 * rate, accel_limit=2 * accel).violation(ref) == 0.0
    assert not within_limits(motion_summary(ref, paced))
    assert pace_metadata(paced) == {"pace": {"speed_limit": speed * 2, "axis_rate_limit": rate / 2}}
    assert pace_metadata(FAST) == {}
    with pytest.raises(ConfigError) as e:
        replace(FAST, axis_rate_limit=0.0)
    assert str(e.value) == "Variant.axis_rate_limit: must be a number > 0 (inf: none), got 0.0"


# ----------------------------------------------------------------------------------------
# hand lab
# ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def lab() -> HandLab:
    return HandLab(HandParams(rope=1, settle_s=0.3, variation=HandVariation.none()))


@pytest.fixture(scope="module")
def ref_trial(lab):
    return lab.run(load_reference_motion())


def test_hand_follows_its_target_closely(ref_trial):
    pos_err, ang_err = ref_trial.tracking_error()
    assert pos_err < 2e-3  # [m] at 3.9 m/s peak speed
    assert ang_err < math.radians(2.0)
    # the recorded fingertip pose is the hand's: z axis along the rope's exit (down at rest)
    from scipy.spatial.transform import Rotation

    r0 = Rotation.from_quat(ref_trial.hand_quat[0], scalar_first=True).as_matrix()
    np.testing.assert_allclose(r0[:, 2], [0, 0, -1], atol=1e-9)
    np.testing.assert_allclose(ref_trial.hand_pos[0], [0, 0, 1.5], atol=1e-9)


def _min_gap(vertices: np.ndarray, radius: float, end_radius: float) -> float:
    """Smallest surface gap between non-adjacent capsules and between the end sphere and
    capsules 0..n-2 [m] (sampled segment distance, 21 points per segment)."""
    s = np.linspace(0, 1, 21)[:, None]
    n = len(vertices) - 1
    pts = np.stack([vertices[k] + s * (vertices[k + 1] - vertices[k]) for k in range(n)])
    gap = np.inf
    for i in range(n):
        for j in range(i + 2, n):
            d = np.linalg.norm(pts[i][:, None] - pts[j][None], axis=-1).min()
            gap = min(gap, d - 2 * radius)
    for j in range(n - 1):
        d = np.linalg.norm(pts[j] - vertices[-1], axis=-1).min()
        gap = min(gap, d - radius - end_radius)
    return float(gap)


def test_t_c_is_the_first_self_contact(lab, ref_trial):
    assert ref_trial.first_contact is not None
    k = round(ref_trial.first_contact / (ref_trial.t[1] - ref_trial.t[0]))
    p = get_rope(1)
    assert _min_gap(ref_trial.vertices[k], p.radius, p.end_radius) < 1e-3
    # well before it the rope is nowhere near itself
    assert _min_gap(ref_trial.vertices[k - 40], p.radius, p.end_radius) > 1e-3
    demo = trial_demonstration(
        ref_trial, lab.rope, MocapParams(), np.random.default_rng(0), rope_id=1
    )
    assert demo.t_c == ref_trial.first_contact
    lost = np.isnan(demo.markers).all(axis=(1, 2))
    assert not lost[demo.t < demo.t_c + 0.02 - 1e-9].any()
    assert lost[demo.t >= demo.t_c + 0.02 + 1e-9].all()
    assert demo.rate_hz == pytest.approx(200.0)


def test_judged_frames_and_variation(lab):
    t = 0.001 * np.arange(1001)
    idx = judged_frames(t, 0.05, 10.0)
    assert idx[0] == 50 and idx[-1] == 1000 and np.all(np.diff(idx)[:-1] == 100)
    v = HandLab(HandParams(settle_s=0.0)).draw_variation(np.random.default_rng(3))
    assert set(v) == {"kp_factor", "kv_factor", "sway", "azimuth", "sway_rate", "delay", "tempo"}
    assert 0.0 <= v["delay"] < 0.004 and len(v["kp_factor"]) == 6
    with pytest.raises(ConfigError, match=r"^rng: must be a numpy.random.Generator, got int$"):
        lab.draw_variation(3)
    with pytest.raises(
        ConfigError, match=r"^rope: unknown rope id 9 \(valid choices: 1, 2, 3, 4, 5, 6, 7\)$"
    ):
        HandParams(rope=9)
    with pytest.raises(ConfigError, match=r"^tempo_rel: must be < 0\.2, got 0\.3$"):
        HandVariation(tempo_rel=0.3)


# ----------------------------------------------------------------------------------------
# shipped demonstrations
# ----------------------------------------------------------------------------------------
def _shipped(name: str) -> Demonstration:
    return Demonstration.load(DEMOS_DIR / f"{name}.npz")


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_demo_is_current_and_described(name):
    demo = _shipped(name)
    m = demo.metadata
    # the shipped demos name the search's module as it was named when they were made
    assert m["generator"] in (GENERATOR, *LEGACY_GENERATORS)
    assert m["generator_version"] == GENERATOR_VERSION
    assert m["variant"] == name and demo.rope == 1
    # stale if the rope table changed since: regenerate with the command in the README
    assert m["rope"] == rope_metadata(1)["rope"], "rope 1 changed: regenerate assets/demos"
    assert m["simulation"] == rope_metadata(1)["simulation"]
    lo, hi = VARIANTS[name].duration
    assert lo <= m["motion_duration"] <= hi
    assert m["settle_outcome"] == "trefoil"
    assert m["check"]["repeats"] >= 20
    assert demo.rate_hz == pytest.approx(200.0)
    assert VARIANTS[name].violation(motion_from_demo(demo)) == 0.0
    readme = (DEMOS_DIR / "README.md").read_text()
    assert f"--variant {name} --seed {m['seed']}" in readme


def test_replaying_stored_parameters_reproduces_the_demo_exactly():
    # The shipped demos were made in the hand lab's defaults (air drag, the settle until
    # rest): replayed there without variation, the replay is the demonstration, bit for bit
    # on the machine class it was made on (tests/recorded_on.py).
    demo = _shipped("fast")
    lab = HandLab(hand_from_demo(demo, 1, vary=False))
    trial = lab.run(motion_from_demo(demo))
    assert trial.knot == "trefoil"
    again = trial_demonstration(
        trial,
        lab.rope,
        MocapParams(**demo.metadata["mocap"]),
        np.random.default_rng([demo.metadata["seed"], 3]),
        rope_id=1,
    )
    assert_recorded_again(again, demo)


def test_a_shipped_demo_ties_under_variation_with_a_short_settle():
    demo = _shipped("fast")
    res = replay(demo, repeats=2, seed=11, settle_s=0.8)
    assert res.knots >= 1
    assert all(t is not None and t < 1.5 for t in res.t_c)


def test_replay_on_another_rope_runs():
    demo = _shipped("fast")
    res = replay(demo, rope=4, repeats=1, settle_s=0.2)
    assert res.rope == 4 and res.outcomes[0] is not None


def test_replay_refuses_a_demo_without_motion(tmp_path):
    demo = _shipped("fast")
    bare = replace(demo, metadata={})
    with pytest.raises(RecordError, match=r"^demonstration: no motion parameters"):
        replay(bare)


# ----------------------------------------------------------------------------------------
# search (tiny budgets: checks the machinery, not the hit rate)
# ----------------------------------------------------------------------------------------
def test_search_runs_reproducibly_within_its_budget():
    cfg = SearchConfig(
        budget=6, popsize=3, confirm_trials=2, hand=HandParams(settle_s=0.1, judge_rate_hz=5.0)
    )
    a = search("fast", 5, cfg)
    b = search("fast", 5, cfg)
    assert 6 <= a.trials <= 6 + cfg.confirm_trials
    np.testing.assert_array_equal(a.history, b.history)
    assert a.history.shape[1] == 3 and a.stopped in ("budget", "target")
    with pytest.raises(
        ConfigError, match=r"^SearchConfig\.budget: must be an integer >= 1, got 0$"
    ):
        SearchConfig(budget=0)


# ----------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------
def test_cli_unknown_variant_lists_choices(tmp_path, capsys):
    code = tools_cli.main(
        ["demo", "synthesize", "--variant", "loop", "--out", str(tmp_path / "x.npz")]
    )
    assert code == 2
    assert capsys.readouterr().err == (
        "flyknot-tools: error: variant: unknown value 'loop' "
        "(valid choices: fast, slow, swipe, inverse)\n"
    )


def test_cli_bad_pace_limit(tmp_path, capsys):
    out = str(tmp_path / "x.npz")
    args = ["demo", "synthesize", "--variant", "fast", "--out", out, "--max-axis-rate", "-1"]
    assert tools_cli.main(args) == 2
    assert capsys.readouterr().err == (
        "flyknot-tools: error: --max-axis-rate: must be > 0, got -1.0\n"
    )


def test_cli_missing_file(tmp_path, capsys):
    missing = tmp_path / "nope.npz"
    code = demo_cli.main(["demo", "replay", str(missing)])
    assert code == 2
    assert capsys.readouterr().err == (
        f"flyknot: error: demonstration file {str(missing)!r} does not exist\n"
    )


def test_cli_bad_repeats(capsys):
    code = demo_cli.main(["demo", "replay", str(DEMOS_DIR / "fast.npz"), "--repeats", "0"])
    assert code == 2
    assert capsys.readouterr().err == "flyknot: error: --repeats: must be an integer >= 1, got 0\n"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            ["--variation", "rest_scale=2"],
            "--variation.rest_scale: must be a number in [0, 1], got 2",
        ),
        (
            ["--variation", "gain=1"],
            "--variation.gain: not a field of the variation (valid choices: sway_deg, "
            "servo_gain_rel, start_delay_max_s, rest_start, rest_scale, tempo_rel)",
        ),
        (
            ["--nominal", "--variation", "rest_scale=0.5"],
            "--variation: a --nominal replay has no variation to change",
        ),
    ],
)
def test_cli_bad_variation(capsys, extra, message):
    code = demo_cli.main(["demo", "replay", str(DEMOS_DIR / "fast.npz"), *extra])
    assert code == 2
    assert capsys.readouterr().err == f"flyknot: error: {message}\n"


def test_a_replays_variation_can_be_changed(monkeypatch):
    """``--variation`` reaches the hand lab: the same replay with the rope's start scaled."""
    from flyknot_sim import hand_replay

    seen = []
    monkeypatch.setattr(hand_replay, "HandLab", lambda hand: seen.append(hand) or _Stop())
    with pytest.raises(_StopError):
        demo_cli.main(
            ["demo", "replay", str(DEMOS_DIR / "fast.npz"), "--variation", "rest_scale=0.25"]
        )
    assert seen[0].variation == HandVariation(rest_scale=0.25)


def test_the_hand_labs_rest_scale_scales_the_same_start():
    full = HandLab(HandParams(rope=1, variation=HandVariation()))
    quarter = HandLab(HandParams(rope=1, variation=HandVariation(rest_scale=0.25)))
    for seed in range(3):
        a = full.draw_variation(np.random.default_rng(seed))
        b = quarter.draw_variation(np.random.default_rng(seed))
        assert b["sway"] == pytest.approx(0.25 * a["sway"], abs=1e-15)
        assert b["sway_rate"] == pytest.approx(0.25 * a["sway_rate"], abs=1e-15)
        assert (b["delay"], b["tempo"], b["kp_factor"]) == (a["delay"], a["tempo"], a["kp_factor"])


class _StopError(Exception):
    pass


class _Stop:
    def run(self, *args, **kwargs):
        raise _StopError


def test_cli_replay_json_and_saved_replays(tmp_path, capsys):
    out = tmp_path / "replays"
    code = demo_cli.main(
        [
            "demo",
            "replay",
            str(DEMOS_DIR / "fast.npz"),
            "--rope",
            "1",
            "--nominal",
            "--settle",
            "0.2",
            "--out",
            str(out),
            "--json",
        ]
    )
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["repeats"] == 1 and len(result["outcomes"]) == 1
    # Air drag moves the nominal replay's first contact by a few ms.
    assert result["t_c"][0] == pytest.approx(_shipped("fast").t_c, abs=0.01)
    saved = Demonstration.load(out / "replay_000.npz")
    assert saved.t_c == result["t_c"][0]
    with np.load(out / "replay_000.npz") as z:
        assert z["centreline"].shape[1:] == (get_rope(1).segments + 1, 3)
        meta = json.loads(str(z["meta"]))
    assert meta["metadata"]["generator"] == REPLAY_GENERATOR
    assert meta["metadata"]["kind"] == "replay"


def test_cli_is_wired_into_flyknot(capsys):
    from flyknot_app import cli

    assert cli.build_parser().parse_args(["demo", "replay", "x.npz"]).file == "x.npz"
    # making demonstrations is the offline tools' work, not the application's
    with pytest.raises(SystemExit) as e:
        cli.main(["demo", "synthesize", "--variant", "fast", "--out", "x.npz"])
    assert e.value.code == 2
    assert "invalid choice: 'synthesize'" in capsys.readouterr().err
    code = tools_cli.main(["demo", "synthesize", "--variant", "loop", "--out", "x.npz"])
    assert code == 2
    assert "valid choices: fast, slow, swipe, inverse" in capsys.readouterr().err


def _help(main, argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    return capsys.readouterr().out


def _actions(help_text: str) -> set[str]:
    """The sub-command names a help text lists (first word of each line indented by 4; the
    wrapped help is indented deeper)."""
    lines = help_text.split("positional arguments:")[1].split("options:")[0].splitlines()
    return {ln.split()[0] for ln in lines if ln.startswith("    ") and ln[4] != " "}


def test_demo_commands_are_split_between_flyknot_and_flyknot_tools(capsys):
    from flyknot_app import cli

    assert _actions(_help(tools_cli.main, ["demo", "--help"], capsys)) == {
        "synthesize",
        "robot",
        "robot-rate",
        "record",
        "rerecord",
    }
    assert _actions(_help(cli.main, ["demo", "--help"], capsys)) == {"replay", "critical"}
    assert _actions(_help(demo_cli.main, ["demo", "--help"], capsys)) == {"replay", "critical"}
    assert _actions(_help(tools_cli.main, ["--help"], capsys)) == {
        "demo",
        "rope-study",
        "rope-validate",
        "lab-study",
        "closure-study",
        "settle-compare",
    }


def test_rope_study_takes_its_own_options(capsys):
    out = _help(tools_cli.main, ["rope-study", "--help"], capsys)
    assert "--variants" in out and "--shape" in out


def test_sim_settings_are_recorded():
    assert rope_metadata(1)["simulation"]["integrator"] == load_sim_settings().integrator
    assert isinstance(Path(REFERENCE_MOTION), Path) and REFERENCE_MOTION.is_file()


def test_the_search_seed_is_found_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert REFERENCE_MOTION.is_absolute() and REFERENCE_MOTION.is_file()
    assert load_reference_motion().duration == pytest.approx(0.70, abs=0.01)


def test_confirmation_stops_once_the_target_is_out_of_reach():
    assert SearchConfig(target_rate=0.95, confirm_abort=True).confirm_failures == 1
    assert SearchConfig(target_rate=0.8, confirm_abort=True).confirm_failures == 4
    assert SearchConfig(target_rate=1.0, confirm_abort=True).confirm_failures == 0
    assert SearchConfig(target_rate=0.95).confirm_failures is None
    with pytest.raises(ConfigError) as e:
        SearchConfig(confirm_abort=1)
    assert str(e.value) == "SearchConfig.confirm_abort: must be true or false, got 1"
    outcomes = iter([True, False, True, False, True, True])
    played = []

    def run(motion, variation):
        played.append(variation)
        tied = next(outcomes)
        return SimpleNamespace(
            diverged=False,
            vertices=np.zeros((1, 4, 3)),
            judged=[0],
            tied=tied,
            settle_fraction=float(tied),
            knot_any=tied,
            first_contact=0.5,
        )

    lab = SimpleNamespace(run=run)
    ref = load_reference_motion()
    ev = evaluate(lab, ref, FAST, [{}] * 6, max_failures=1)
    assert len(played) == 4 and ev.ties == 2  # the second failure ends it
    played.clear()
    outcomes = iter([True] * 6)
    assert evaluate(lab, ref, FAST, [{}] * 6, max_failures=1).ties == 6


def test_the_last_stage_alone_is_a_local_search_from_the_start(monkeypatch):
    """``last_stage``: only the variant's last stage runs, from the start motion as it is
    (no wind-up picked), with the later stages' step and budget."""
    from flyknot.errors import SolverError
    from flyknot_tools.hand_demos import synthesis

    calls = []

    def fake_search(stage, seed, cfg, *, start, stream, lab, bar):
        calls.append((stage.name, cfg.sigma0, cfg.budget, cfg.target_rate, start, stream))
        raise SolverError("demo search", "budget", "stopped by the test")

    monkeypatch.setattr(synthesis, "search", fake_search)
    monkeypatch.setattr(synthesis, "_pick_windup", lambda *a: pytest.fail("wind-up picked"))
    start = KnotMotion.from_dict(_shipped("inverse").metadata["motion"])
    config = synthesis.SynthConfig()
    with pytest.raises(SolverError):
        synthesis.synthesize_motion("inverse", 0, config, start=start, last_stage=True)
    ((name, sigma, budget, target, motion, stream),) = calls
    assert name == "inverse" and stream == 1  # the two-stage variant's wind-up stage
    assert (sigma, budget) == (config.stage_sigma, config.stage_budget)
    assert target == config.search.target_rate and motion is start
    calls.clear()
    with pytest.raises(SolverError):  # a one-stage variant: its only stage, locally
        synthesis.synthesize_motion("fast", 0, config, start=start, last_stage=True)
    assert [c[:3] for c in calls] == [("fast", config.stage_sigma, config.stage_budget)]
    with pytest.raises(ConfigError) as e:
        synthesis.synthesize_motion("fast", 0, config, last_stage=True)
    assert str(e.value) == "start: the last stage alone needs a start motion (--start)"


def test_the_first_stage_alone_is_the_throw(monkeypatch):
    """``first_stage``: only the variant's first stage runs, with its own step and budget and
    the search's target rate; no wind-up is picked. Not with ``last_stage``."""
    from flyknot.errors import SolverError
    from flyknot_tools.hand_demos import synthesis

    calls = []

    def fake_search(stage, seed, cfg, *, start, stream, lab, bar):
        calls.append((stage.name, cfg.sigma0, cfg.budget, cfg.target_rate, stream))
        raise SolverError("demo search", "budget", "stopped by the test")

    monkeypatch.setattr(synthesis, "search", fake_search)
    monkeypatch.setattr(synthesis, "_pick_windup", lambda *a: pytest.fail("wind-up picked"))
    config = synthesis.SynthConfig()
    with pytest.raises(SolverError):
        synthesis.synthesize_motion("swipe", 0, config, first_stage=True)
    swipe = synthesis.get_variant("swipe")
    s = config.search
    assert calls == [("swipe/throw", swipe.throw_sigma, s.budget, s.target_rate, 0)]
    with pytest.raises(ConfigError) as e:
        synthesis.synthesize_motion("swipe", 0, config, first_stage=True, last_stage=True)
    assert str(e.value) == ("first_stage: the first stage alone or the last stage alone, not both")


def test_a_failed_later_stage_keeps_the_earlier_stages_best(tmp_path, monkeypatch):
    """The wind-up stage ties nothing: the throw stage's best, whose nominal trial tied, is
    recorded at ``OUT.throw.npz`` under the stage's name before the search raises; a stage
    whose best did not tie, and the run's last stage, write nothing."""
    from flyknot.errors import SolverError
    from flyknot_tools.hand_demos import synthesis
    from flyknot_tools.hand_demos.search import Candidate, SearchResult

    motion = KnotMotion.from_dict(_shipped("fast").metadata["motion"])

    def result(name, tied):
        best = Candidate(motion, 5, 0.5, tied, 1.0)
        return SearchResult(name, 0, best, 9, 3, 1, 1, (best,), np.zeros((0, 3)), 0.1, "target")

    def fake_search(stage, seed, cfg, *, start, stream, lab, bar):
        return result(stage.name, tied=stream == 0)

    monkeypatch.setattr(synthesis, "search", fake_search)
    monkeypatch.setattr(synthesis, "_pick_windup", lambda lab, m, *a: (m, 0))
    out = tmp_path / "chain.npz"
    lines = []
    keep = synthesis.stage_keeper(0, HandParams(), out, lines.append)
    with pytest.raises(SolverError) as e:
        synthesis.synthesize_motion("swipe", 0, synthesis.SynthConfig(), on_stage=keep)
    assert "stage swipe found no motion" in str(e.value)
    kept = synthesis.stage_path(out, "throw")
    assert kept == tmp_path / "chain.throw.npz"
    demo = Demonstration.load(kept)
    assert demo.metadata["variant"] == "swipe/throw"
    assert demo.metadata["motion"] == motion.to_dict()
    assert lines == [f"stage swipe/throw: its best motion (nominal trial ties) saved to {kept}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chain.throw.npz"]
    kept.unlink()
    keep("throw", synthesis.get_variant("swipe"), result("swipe/throw", tied=False), False)
    keep("windup", synthesis.get_variant("swipe"), result("swipe", tied=True), True)
    assert list(tmp_path.iterdir()) == []


def test_cli_envelope_start_and_budgets_reach_the_search(tmp_path, capsys, monkeypatch):
    from flyknot.errors import SolverError
    from flyknot_tools.hand_demos import synthesis
    from flyknot_tools.hand_demos.envelope import arm_envelope, shared_envelope

    seen = {}

    def fake(
        variant, seed, config, *, check_repeats, progress, start, last_stage, first_stage, on_stage
    ):
        seen.update(variant=variant, config=config, start=start, last_stage=last_stage)
        seen.update(first_stage=first_stage, on_stage=on_stage)
        raise SolverError("demo search", "budget", "stopped by the test")

    monkeypatch.setattr(synthesis, "synthesize", fake)
    args = ["demo", "synthesize", "--variant", "swipe", "--out", str(tmp_path / "x.npz")]
    args += ["--envelope", "--max-speed", "2.0", "--start", str(DEMOS_DIR / "fast.npz")]
    args += ["--throw-budget", "7", "--target-rate", "0.95", "--confirm-abort", "--quiet"]
    assert tools_cli.main([*args, "--last-stage"]) == 2
    assert seen["last_stage"] is True and seen["first_stage"] is False
    assert tools_cli.main([*args, "--first-stage"]) == 2
    assert seen["first_stage"] is True
    assert callable(seen["on_stage"])  # the CLI keeps every intermediate stage's best
    assert tools_cli.main(args) == 2
    assert seen["last_stage"] is False
    assert "stopped by the test" in capsys.readouterr().err
    env = shared_envelope(arm_envelope().envelope)
    v = seen["variant"]
    assert (v.speed_limit, v.axis_rate_limit, v.accel_limit) == (2.0, env.axis_rate, env.accel)
    assert v.swipe_ratio == 1.0  # still the swipe
    cfg = seen["config"].search
    assert (cfg.budget, cfg.target_rate, cfg.confirm_abort) == (7, 0.95, True)
    shipped = _shipped("fast").metadata["motion"]
    np.testing.assert_array_equal(seen["start"].x, KnotMotion.from_dict(shipped).x)
    robot = str(DEMOS_DIR / "robot.npz")
    args = ["demo", "synthesize", "--variant", "fast", "--out", str(tmp_path / "x.npz")]
    assert tools_cli.main([*args, "--start", robot]) == 2
    assert capsys.readouterr().err == (
        f"flyknot-tools: error: --start: {robot!r} holds no hand motion (made by demo "
        "synthesize?)\n"
    )
    assert tools_cli.main([*args, "--target-rate", "1.5"]) == 2
    assert capsys.readouterr().err == (
        "flyknot-tools: error: --target-rate: must lie in (0, 1], got 1.5\n"
    )
    assert tools_cli.main([*args, "--mirror-start"]) == 2
    assert capsys.readouterr().err == (
        "flyknot-tools: error: --mirror-start: needs a start motion (--start)\n"
    )
    fast = str(DEMOS_DIR / "fast.npz")
    assert tools_cli.main([*args, "--start", fast, "--mirror-start", "--quiet"]) == 2
    mirrored = KnotMotion.from_dict(shipped).mirrored()
    np.testing.assert_array_equal(seen["start"].x, mirrored.x)
    assert not np.array_equal(mirrored.x, KnotMotion.from_dict(shipped).x)


PACED = {
    "fast-paced": ("fast", "--variant fast --seed 0 --max-axis-rate 15 --max-speed 5.5"),
    "slow-paced": (
        "slow",
        "--variant slow --seed 0 --start assets/demos/fast-paced.npz --max-axis-rate 15 "
        "--max-speed 5.5",
    ),
    "swipe-paced": ("swipe", "--variant swipe --seed 0 --max-axis-rate 15 --max-speed 5.5"),
    "inverse-paced": (
        "inverse",
        "--variant inverse --seed 0 --start assets/demos/fast-paced.npz --mirror-start "
        "--max-axis-rate 15 --max-speed 5.5",
    ),
}


@pytest.mark.parametrize("name", PACED)
def test_the_person_paced_demonstrations_are_described_and_within_their_pace(name):
    """The person-paced four: each its variant's search under a pace cap, its peaks within the
    caps it records, tying in its varied check, its command in the demonstrations' README."""
    from scipy.spatial.transform import Rotation

    variant, command = PACED[name]
    demo = Demonstration.load(DEMOS_DIR / f"{name}.npz")
    m = demo.metadata
    assert m["variant"] == variant and m["settle_outcome"] == "trefoil"
    assert m["pace"] == {"speed_limit": 5.5, "axis_rate_limit": 15.0}
    assert m["check"]["knots"] >= 16 and m["check"]["repeats"] == 20
    assert m["rope"] == rope_metadata(1)["rope"], "rope 1 changed: regenerate assets/demos"
    dt = np.diff(demo.t)
    speed = np.linalg.norm(np.diff(demo.hand_pos, axis=0), axis=1) / dt
    z = Rotation.from_quat(demo.hand_quat, scalar_first=True).as_matrix()[:, :, 2]
    rate = np.arccos(np.clip(np.sum(z[1:] * z[:-1], axis=1), -1.0, 1.0)) / dt
    assert speed.max() <= 5.5 and rate.max() <= 15.0
    lo, hi = get_variant(variant).duration
    assert lo <= m["motion_duration"] <= hi
    readme = (DEMOS_DIR / "README.md").read_text()
    assert command in " ".join(readme.split())

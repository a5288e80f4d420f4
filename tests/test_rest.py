"""The rest criterion, the settled start and the settle monitor (flyknot.rest)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot.geometry import quat_to_matrix
from flyknot.rest import (
    RestCriterion,
    SettleMonitor,
    SettleParams,
    free_end_at_rest,
    pendulum_omega,
    settled_start,
    shape_change,
)


def test_pendulum_omega_is_the_uniform_chains_first_mode():
    assert pendulum_omega(1.1) == pytest.approx(1.2024 * math.sqrt(9.81 / 1.1))


def test_default_displacement_is_swing_amplitude_at_speed_bound():
    c = RestCriterion()
    assert c.max_displacement(1.1) == pytest.approx(0.03 / (1.2024 * math.sqrt(9.81 / 1.1)))
    assert RestCriterion(displacement_m=0.004).max_displacement() == 0.004


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=50, deadline=None)
def test_settled_start_lies_within_the_criterion(seed):
    c = RestCriterion()
    tilt, rate, _ = settled_start(np.random.default_rng(seed), c, 1.1)
    assert abs(tilt) * 1.1 <= c.max_displacement(1.1) + 1e-12
    assert abs(rate) * 1.1 <= c.speed_m_s + 1e-12


def test_settled_start_fills_the_disc_uniformly():
    c = RestCriterion()
    rng = np.random.default_rng(0)
    d = np.array([settled_start(rng, c, 1.1) for _ in range(4000)])
    amp = c.max_displacement(1.1)
    w = pendulum_omega(1.1)
    r2 = (d[:, 0] * 1.1) ** 2 + (d[:, 1] * 1.1 / w) ** 2
    # Uniform over a disc of radius A: E[r^2] = A^2 / 2.
    assert np.mean(r2) == pytest.approx(amp**2 / 2, rel=0.05)
    assert np.max(r2) <= amp**2 * (1 + 1e-9)


@given(st.integers(0, 2**32 - 1), st.floats(0.0, 1.0))
@settings(max_examples=50, deadline=None)
def test_a_share_of_the_criterion_scales_the_same_start(seed, scale):
    c = RestCriterion()
    full = settled_start(np.random.default_rng(seed), c, 1.1)
    part = settled_start(np.random.default_rng(seed), c, 1.1, scale)
    assert part[0] == pytest.approx(scale * full[0], abs=1e-15)
    assert part[1] == pytest.approx(scale * full[1], abs=1e-15)
    assert part[2] == full[2]


@pytest.mark.parametrize("scale", [-0.1, 1.5, "half", True])
def test_a_share_outside_zero_to_one_is_refused(scale):
    with pytest.raises(ConfigError, match=rf"^scale: must be a number in \[0, 1\], got {scale!r}$"):
        settled_start(np.random.default_rng(0), RestCriterion(), 1.1, scale)


def test_free_end_at_rest():
    c = RestCriterion()
    assert free_end_at_rest([0.01, 0.02], [0.001, 0.002], c, 1.1)
    assert not free_end_at_rest([0.01, 0.04], [0.001, 0.002], c, 1.1)
    assert not free_end_at_rest([0.01], [0.05], c, 1.1)
    assert not free_end_at_rest([], [], c, 1.1)


def _run(monitor, t0, speed_fn, verdict_fn, contact_fn=lambda t: True, dt=0.004, region_fn=None):
    t = t0
    while not monitor.observe(
        t,
        speed_fn(t),
        lambda t=t: verdict_fn(t),
        contact_fn(t),
        None if region_fn is None else (lambda t=t: region_fn(t)),
    ):
        t += dt
        if t > t0 + 100:
            raise AssertionError("monitor never ended")
    return monitor.outcome


def test_monitor_stops_one_window_after_the_speed_falls_below_threshold():
    p = SettleParams()
    out = _run(SettleMonitor(p, 2.0), 2.0, lambda t: 0.5 if t < 6.0 else 0.01, lambda t: "trefoil")
    assert out.settled and not out.contact_free
    assert out.settle_s == pytest.approx(4.0 + p.rest.window_s, abs=0.005)
    assert out.verdict == "trefoil"
    assert out.free_end_speed_m_s == pytest.approx(0.01)


def test_monitor_waits_at_least_min_s():
    out = _run(SettleMonitor(SettleParams(min_s=1.5), 0.0), 0.0, lambda t: 0.0, lambda t: "unknot")
    assert out.settled
    assert out.settle_s == pytest.approx(1.5, abs=0.005)


def test_monitor_waits_for_a_stable_verdict():
    # At rest from the start, but the verdict flips at every sample until t = 5 s.
    calls = []

    def verdict(t):
        calls.append(t)
        return ("trefoil" if len(calls) % 2 else "unknot") if t < 5.0 else "trefoil"

    out = _run(SettleMonitor(SettleParams(), 0.0), 0.0, lambda t: 0.0, verdict)
    assert out.settled and out.verdict == "trefoil"
    assert out.settle_s >= 5.0 + 1.0 - 0.3
    window = [
        v for tv, v in zip(out.history_t, out.history, strict=True) if tv >= out.settle_s - 1.0
    ]
    assert set(window) == {"trefoil"}


def test_monitor_cap_marks_the_trial_unsettled():
    out = _run(SettleMonitor(SettleParams(max_s=3.0), 0.0), 0.0, lambda t: 1.0, lambda t: "trefoil")
    assert not out.settled and not out.contact_free
    assert out.settle_s == pytest.approx(3.0, abs=0.005)
    assert out.free_end_speed_m_s == 1.0


def test_monitor_contact_free_unknot_ends_early():
    out = _run(
        SettleMonitor(SettleParams(), 0.0),
        0.0,
        lambda t: 1.0,
        lambda t: "unknot",
        contact_fn=lambda t: t < 2.0,
    )
    assert out.contact_free and not out.settled
    assert out.settle_s == pytest.approx(3.0, abs=0.005)
    # A swinging trefoil without contact is not judged early.
    out = _run(
        SettleMonitor(SettleParams(max_s=4.0), 0.0),
        0.0,
        lambda t: 1.0,
        lambda t: "trefoil",
        contact_fn=lambda t: False,
    )
    assert not out.contact_free and out.settle_s == pytest.approx(4.0, abs=0.005)


def test_a_rope_unknotted_at_every_verdict_for_unknot_held_s_ends_early():
    # Touching itself and swinging: only the held-unknot end or the cap can end it.
    out = _run(SettleMonitor(SettleParams(), 0.0), 0.0, lambda t: 1.0, lambda t: "unknot")
    assert out.unknot_held and not (out.settled or out.contact_free or out.knot_set)
    # the first verdict sample at least 3 s after the first one (samples every 0.25 s of
    # ticks: 0, 0.252, ..., 3.024)
    assert out.settle_s == out.history_t[-1] == pytest.approx(3.024)
    meta = out.as_metadata(SettleParams())
    assert meta["unknot_held"] is True and meta["criterion"]["unknot_held_s"] == 3.0
    off = SettleParams(max_s=6.0, unknot_held_s=None)
    out = _run(SettleMonitor(off, 0.0), 0.0, lambda t: 1.0, lambda t: "unknot")
    assert not out.unknot_held and out.settle_s == pytest.approx(6.0, abs=0.005)


def test_a_knotted_verdict_restarts_the_held_unknot_clock():
    # Unknotted, then a knot from 1.0 s to 1.6 s, then unknotted again: the rope is judged
    # at the first verdict sample 3 s after the first unknotted sample that followed the knot.
    out = _run(
        SettleMonitor(SettleParams(max_s=10.0), 0.0),
        0.0,
        lambda t: 1.0,
        lambda t: "trefoil" if 0.99 <= t < 1.6 else "unknot",
    )
    assert out.unknot_held and out.verdict == "unknot"
    k = max(i for i, v in enumerate(out.history) if v == "trefoil") + 1
    assert out.history.count("trefoil") == 3  # the samples at 1.008, 1.26 and 1.512 s
    assert out.history_t[k] == pytest.approx(1.764)
    assert out.settle_s == out.history_t[-1] == pytest.approx(1.764 + 3.024)


def test_without_turns_the_named_early_ends_off():
    p = SettleParams(min_s=1.0)
    assert p.without() == p
    assert p.without("knot_set") == SettleParams(min_s=1.0, knot_set_s=None)
    both = p.without("knot_set", "unknot_held")
    assert (both.knot_set_s, both.unknot_held_s, both.min_s) == (None, None, 1.0)
    with pytest.raises(ConfigError) as e:
        p.without("rest")
    assert str(e.value) == "end: unknown early end 'rest' (valid choices: knot_set, unknot_held)"


def test_fixed_settle_judges_at_its_time():
    out = _run(SettleMonitor(SettleParams.fixed(0.5), 1.0), 1.0, lambda t: 2.0, lambda t: "unknot")
    assert out.settle_s == pytest.approx(0.5, abs=0.005)
    assert not out.settled


def test_outcome_before_the_end_is_an_error():
    m = SettleMonitor(SettleParams(), 0.0)
    with pytest.raises(ConfigError, match=r"^outcome: the settle has not ended yet"):
        _ = m.outcome


def test_metadata_round_trip_fields():
    p = SettleParams()
    out = _run(SettleMonitor(p, 0.0), 0.0, lambda t: 0.0, lambda t: "unknot")
    meta = out.as_metadata(p)
    assert meta["settled"] is True
    assert meta["criterion"]["speed_m_s"] == 0.03
    assert meta["knot_history"]["verdict"][-1] == "unknot"
    assert meta["verdict_stable_s"] >= 1.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"min_s": -1.0}, "min_s: must be a finite number >= 0, got -1.0"),
        ({"max_s": 1.0, "min_s": 2.0}, "max_s: must be >= min_s (2.0), got 1.0"),
        ({"verdict_interval_s": 0.0}, "verdict_interval_s: must be a finite number > 0, got 0.0"),
        ({"contact_free_unknot": 1}, "contact_free_unknot: must be true or false, got 1"),
        ({"rest": 0.03}, "rest: must be a RestCriterion, got float"),
        ({"unknot_held_s": 0.0}, "unknot_held_s: must be a finite number > 0, got 0.0"),
    ],
)
def test_settle_params_errors(kwargs, message):
    with pytest.raises(ConfigError) as e:
        SettleParams(**kwargs)
    assert str(e.value) == message


def test_rest_criterion_errors():
    with pytest.raises(ConfigError) as e:
        RestCriterion(speed_m_s=0.0)
    assert str(e.value) == "speed_m_s: must be a finite number > 0, got 0.0"


def test_start_with_sway_adds_tilts_as_vectors():
    from flyknot.rest import start_with_sway

    c = RestCriterion()
    tilt, rate, psi = settled_start(np.random.default_rng(5), c, 1.1)
    angle, direction, r = start_with_sway(np.random.default_rng(5), c, 1.1, 0.0, 0.0)
    assert angle == pytest.approx(abs(tilt))
    assert r * np.sign(tilt) == pytest.approx(rate)
    # With a sway: the two tilts add as plane vectors.
    angle, direction, _ = start_with_sway(np.random.default_rng(5), c, 1.1, 0.1, 1.0)
    expected = 0.1 * np.array([np.cos(1.0), np.sin(1.0)]) + tilt * np.array(
        [np.cos(psi), np.sin(psi)]
    )
    got = angle * np.array([np.cos(direction), np.sin(direction)])
    np.testing.assert_allclose(got, expected, atol=1e-12)


_KNOT = np.random.default_rng(7).normal(scale=0.02, size=(31, 3))


def _swinging(t):
    """A rope swinging as a rigid body about the grip: every shape change is zero."""
    c, s = math.cos(0.4 * math.sin(3.6 * t)), math.sin(0.4 * math.sin(3.6 * t))
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return (5, 12), _KNOT @ rot.T


@given(
    st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    st.lists(st.floats(-2, 2), min_size=3, max_size=3),
    st.integers(2, 12),
)
@settings(max_examples=50, deadline=None)
def test_shape_change_is_zero_for_rigid_motions(q, shift, k):
    pts = np.random.default_rng(k).normal(size=(k, 3))
    rot = quat_to_matrix(np.asarray(q) / np.linalg.norm(q))
    assert shape_change(pts, pts @ rot.T + np.asarray(shift)) < 1e-9


def test_shape_change_is_the_largest_change_of_a_distance():
    ref = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    now = ref.copy()
    now[1, 0] = 1.3  # |p1 - p0| 1 -> 1.3; |p1 - p2| sqrt(5) -> sqrt(1.69 + 4)
    assert shape_change(ref, now) == pytest.approx(0.3)
    with pytest.raises(ConfigError, match=r"^now: must have the reference's shape \(3, 3\)"):
        shape_change(ref, now[:2])


def test_a_set_knot_is_judged_before_rest():
    p = SettleParams()
    out = _run(
        SettleMonitor(p, 0.0, diameter=0.009), 0.0, lambda t: 1.0, lambda t: "trefoil",
        region_fn=_swinging,
    )  # fmt: skip
    # Knotted from the first sample (t = 0): set after knot_set_s, past min_s.
    assert out.knot_set and not out.settled and not out.contact_free
    assert out.settle_s == pytest.approx(p.knot_set_s, abs=0.005)
    assert out.as_metadata(p)["knot_set"] is True


def test_a_working_knot_is_not_set():
    def working(t):
        span, pts = _swinging(t)
        pts = pts.copy()
        pts[8] += [0.01 * math.sin(5.0 * t), 0, 0]  # one strand slides by up to 1 cm
        return span, pts

    out = _run(
        SettleMonitor(SettleParams(max_s=6.0), 0.0, diameter=0.009), 0.0, lambda t: 1.0,
        lambda t: "trefoil", region_fn=working,
    )  # fmt: skip
    assert not out.knot_set and out.settle_s == pytest.approx(6.0, abs=0.005)


def test_the_knot_must_keep_its_type_and_the_check_can_be_off():
    flicker = _run(
        SettleMonitor(SettleParams(max_s=6.0), 0.0, diameter=0.009), 0.0, lambda t: 1.0,
        lambda t: "trefoil" if int(t) % 2 else "figure-eight", region_fn=_swinging,
    )  # fmt: skip
    assert not flicker.knot_set and flicker.settle_s == pytest.approx(6.0, abs=0.005)
    for monitor in (
        SettleMonitor(SettleParams(max_s=5.0, knot_set_s=None), 0.0, diameter=0.009),
        SettleMonitor(SettleParams(max_s=5.0), 0.0),  # no diameter: no tolerance
    ):
        out = _run(monitor, 0.0, lambda t: 1.0, lambda t: "trefoil", region_fn=_swinging)
        assert not out.knot_set and out.settle_s == pytest.approx(5.0, abs=0.005)
    with pytest.raises(ConfigError, match=r"^knot_set_s: must be a finite number > 0"):
        SettleParams(knot_set_s=0.0)

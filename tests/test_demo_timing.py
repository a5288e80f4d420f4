"""Tests of the demonstration timing selection (learner.demo_timing)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError
from learner.demo_timing import DemoWindow, hand_speed, select_demo_window, trim_demonstration

# A smooth speed bump: v(t) = V sin^2(pi (t - TA) / D) on [TA, TA + D], 0 elsewhere.
RATE = 200.0
DT = 1.0 / RATE
TA, D, V = 0.5, 0.6, 4.0
T_END = 1.5
T_C = TA + 0.8 * D  # 0.98 s
T = np.arange(round(T_END * RATE) + 1) / RATE


def arc(t: np.ndarray | float) -> np.ndarray:
    """Path length s(t) = integral of v [m]."""
    u = np.clip(np.asarray(t, dtype=float) - TA, 0.0, D)
    return V * (u / 2.0 - D / (4.0 * np.pi) * np.sin(2.0 * np.pi * u / D))


def speed(t: np.ndarray | float) -> np.ndarray:
    """v(t) [m/s]."""
    u = np.asarray(t, dtype=float) - TA
    return np.where((u >= 0) & (u <= D), V * np.sin(np.pi * u / D) ** 2, 0.0)


def line_motion(t: np.ndarray) -> np.ndarray:
    """Straight line along a fixed unit direction, (k, 3) [m]."""
    e = np.array([2.0, -1.0, 2.0]) / 3.0
    return np.array([0.1, 0.2, 1.3]) + arc(t)[:, None] * e


def circle_motion(t: np.ndarray, r: float = 0.4) -> np.ndarray:
    """Along a circle of radius r at the same speed, (k, 3) [m]."""
    a = arc(t) / r
    return np.column_stack([r * np.cos(a), r * np.sin(a), 1.4 + 0.0 * a])


U_REST = D * np.arcsin(np.sqrt(0.03)) / np.pi
T_REST = TA + U_REST  # analytic 3 % crossing before the peak
T_PEAK = TA + D / 2.0
T_F = T_C + 0.035


def analytic_t0(t_rest: float) -> float:
    """t_0 with s(t_0) - s(t_rest) = 0.05 (s(t_f) - s(t_rest))."""
    target = arc(t_rest) + 0.05 * (arc(T_F) - arc(t_rest))
    return brentq(lambda x: arc(x) - target, t_rest, T_F, xtol=1e-14)


# --- speed ------------------------------------------------------------------------------


@pytest.mark.parametrize(("motion", "kappa"), [(line_motion, 0.0), (circle_motion, 1 / 0.4)])
def test_hand_speed_matches_analytic(motion, kappa: float) -> None:
    """Central differences: |error| <= h^2/6 |p^(3)| <= h^2/6 (max|v''| + kappa^2 V^3)."""
    v = hand_speed(T, motion(T))
    vpp_max = V * 2.0 * (np.pi / D) ** 2 + kappa**2 * V**3
    interior = slice(1, -1)
    err = np.abs(v[interior] - speed(T)[interior])
    assert err.max() <= DT**2 / 6.0 * vpp_max * 1.05 + 1e-12
    assert v.shape == T.shape


def test_hand_speed_smoothing_reduces_noise() -> None:
    rng = np.random.default_rng(0)
    p = line_motion(T) + rng.normal(0.0, 0.0005, (T.size, 3))
    raw = hand_speed(T, p)[T < 0.45]  # hand at rest: speed is pure noise
    smooth = hand_speed(T, p, smooth_s=0.025)[T < 0.45]
    assert smooth.mean() < 0.5 * raw.mean()


# --- window selection -------------------------------------------------------------------


@pytest.mark.parametrize("motion", [line_motion, circle_motion])
def test_window_matches_analytic(motion) -> None:
    w = select_demo_window(T, motion(T), T_C)
    assert abs(w.t_peak - T_PEAK) <= DT / 2
    # last sample at or before the analytic crossing (finite-difference error << 1 sample)
    assert T_REST - DT - 1e-3 * DT <= w.t_rest <= T_REST + 0.1 * DT
    assert w.tf == pytest.approx(T_F, abs=1e-12)
    # t_0: within 1 % of a sample of the analytic value from the selected t_rest, and
    # within one sample of the fully analytic one.
    assert abs(w.t0 - analytic_t0(w.t_rest)) <= 0.01 * DT
    assert abs(w.t0 - analytic_t0(T_REST)) <= DT
    assert w.t_rest <= w.t0 < T_PEAK < T_C < w.tf
    assert w.duration == pytest.approx(w.tf - w.t0)


def test_window_path_fraction_is_exact_on_a_line() -> None:
    w = select_demo_window(T, line_motion(T), T_C, path_frac=0.5)
    p = line_motion(np.array([w.t_rest, w.t0, w.tf]))
    d1, d2 = np.linalg.norm(p[1] - p[0]), np.linalg.norm(p[2] - p[0])
    assert d1 / d2 == pytest.approx(0.5, abs=2e-3)  # p(t0) itself is a chord: O(dt^2)
    assert select_demo_window(T, line_motion(T), T_C, path_frac=0.0).t0 == w.t_rest


def test_search_window_excludes_a_faster_pickup() -> None:
    """A faster motion outside the search window (the rope being picked up) is ignored."""
    p = line_motion(T)
    pick = T < 0.2
    p[pick, 0] += 0.3 * np.sin(np.pi * T[pick] / 0.2) ** 2  # peaks around 9 m/s
    assert select_demo_window(T, p, T_C).t_peak < 0.2
    w = select_demo_window(T, p, T_C, search_window=(0.3, 1.2))
    assert abs(w.t_peak - T_PEAK) <= DT / 2
    assert T_REST - 1.001 * DT <= w.t_rest <= T_REST + 0.1 * DT


def test_noisy_demo_with_smoothing_is_close() -> None:
    rng = np.random.default_rng(1)
    p = line_motion(T) + rng.normal(0.0, 0.0003, (T.size, 3))
    w = select_demo_window(T, p, T_C, smooth_s=0.025)
    assert abs(w.t_peak - T_PEAK) <= 3 * DT
    assert abs(w.t0 - analytic_t0(T_REST)) <= 3 * DT


@settings(max_examples=40, deadline=None)
@given(
    shift=st.floats(-50.0, 50.0),
    quat=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1
    ),
    offset=st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3),
    scale=st.floats(0.2, 5.0),
)
def test_window_invariances(shift: float, quat: list, offset: list, scale: float) -> None:
    """Time shift moves every time alike; rigid motion and scaling of positions change none."""
    base = select_demo_window(T, circle_motion(T), T_C, search_window=(0.1, 1.4))
    w, x, y, z = np.array(quat) / np.linalg.norm(quat)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    p = scale * circle_motion(T) @ R.T + np.array(offset)
    moved = select_demo_window(T + shift, p, T_C + shift, search_window=(0.1 + shift, 1.4 + shift))
    for name in ("t0", "tf", "t_peak", "t_rest"):
        assert getattr(moved, name) - shift == pytest.approx(getattr(base, name), abs=1e-9)


# --- errors -----------------------------------------------------------------------------


def _err(exc: type, match: str, **kw) -> None:
    args = {"t": T, "hand_pos": line_motion(T), "t_c": T_C} | kw
    t, p, tc = args.pop("t"), args.pop("hand_pos"), args.pop("t_c")
    with pytest.raises(exc) as e:
        select_demo_window(t, p, tc, **args)
    assert str(e.value) == match


def test_errors_exact_messages() -> None:
    _err(RecordError, "t_c = 2.0 lies outside the samples [0.0, 1.5] s", t_c=2.0)
    _err(RecordError, "t_f = t_c + 0.035 = 1.505 lies after the last sample 1.5 s", t_c=1.47)
    _err(
        RecordError,
        "search_window (1.6, 1.7) s holds no samples (samples span [0.0, 1.5] s)",
        search_window=(1.6, 1.7),
    )
    _err(
        ConfigError,
        "search_window: must be (t0~, tf~) with t0~ < tf~, got (1.0, 0.5)",
        search_window=(1.0, 0.5),
    )
    _err(
        RecordError,
        "hand speed never falls to 0.03 of its peak 3.999 m/s between the search window start "
        "0.6 s and t_peak 0.8 s",
        search_window=(0.6, 1.2),
    )
    _err(
        RecordError,
        "the hand does not move inside the search window (peak speed below 1e-06 m/s)",
        hand_pos=np.ones((T.size, 3)),
    )
    _err(RecordError, "t_c = 0.3 s is not after the hand starts moving (t_rest = 0.53 s)", t_c=0.3)
    _err(ConfigError, "near_zero_frac: must be < 1, got 1.5", near_zero_frac=1.5)
    _err(ConfigError, "path_frac: must be a finite number >= 0, got -0.1", path_frac=-0.1)
    _err(RecordError, "hand_pos must have shape (301, 3), got (301, 2)", hand_pos=np.ones((301, 2)))
    _err(RecordError, "t must be strictly increasing", t=T[::-1].copy())


def test_demo_window_validation() -> None:
    with pytest.raises(ConfigError) as e:
        DemoWindow(t0=1.0, tf=0.5, t_peak=0.8, t_rest=0.4)
    assert str(e.value) == "DemoWindow: needs t_rest <= t0 < tf, got t_rest=0.4, t0=1.0, tf=0.5"
    with pytest.raises(ConfigError, match=r"^DemoWindow.t0: must be a finite time, got nan$"):
        DemoWindow(t0=float("nan"), tf=0.5, t_peak=0.8, t_rest=0.4)


# --- trimming ---------------------------------------------------------------------------

OMEGA = 3.0  # [rad/s] hand rotation about z


def _demo() -> Demonstration:
    quat = np.column_stack(
        [np.cos(OMEGA * T / 2), np.zeros_like(T), np.zeros_like(T), np.sin(OMEGA * T / 2)]
    )
    markers = line_motion(T)[:, None, :] + np.linspace(0, -1.0, 11)[None, :, None] * [0, 0, 1]
    markers[T >= T_C + 0.02] = np.nan
    markers[T == 0.7, 4] = np.nan  # one lost marker in one frame
    return Demonstration(
        t=T,
        hand_pos=line_motion(T),
        hand_quat=quat,
        markers=markers,
        t_c=T_C,
        rope=3,
        metadata={"variant": "x"},
    )


def test_trim_demonstration() -> None:
    demo = _demo()
    w = select_demo_window(demo.t, demo.hand_pos, demo.t_c)
    cut = trim_demonstration(demo, w)
    length = w.tf - w.t0
    assert cut.t[0] == 0.0 and cut.t[-1] == pytest.approx(length, abs=1e-12)
    np.testing.assert_allclose(np.diff(cut.t), np.diff(cut.t)[0], rtol=1e-9)
    assert np.diff(cut.t)[0] <= DT
    assert len(cut.t) == int(np.ceil(length / DT)) + 1
    assert cut.t_c == pytest.approx(T_C - w.t0, abs=1e-12)
    assert (cut.rope, cut.metadata["variant"]) == (3, "x")
    assert cut.metadata["timing"]["t0"] == w.t0
    tq = w.t0 + cut.t
    # straight line: linear interpolation error <= dt^2/8 max|s''| = dt^2/8 V pi/D
    np.testing.assert_allclose(cut.hand_pos, line_motion(tq), rtol=0, atol=DT**2 * V * 3.2 / D)
    # constant-rate rotation: slerp is exact
    q = np.column_stack([np.cos(OMEGA * tq / 2), 0 * tq, 0 * tq, np.sin(OMEGA * tq / 2)])
    np.testing.assert_allclose(cut.hand_quat, q, rtol=0, atol=1e-12)
    # markers: lost after the loss onset, and around the one lost sample at 0.7 s
    lost_any = np.isnan(cut.markers).any(axis=(1, 2))
    np.testing.assert_array_equal(np.isnan(cut.markers).all(axis=(1, 2)), tq > T_C + 0.015)
    near = np.abs(tq - 0.7) < DT
    assert np.isnan(cut.markers[near, 4]).all()
    assert not np.isnan(cut.markers[near][:, [0, 1, 2, 3, 5]]).any()
    assert (
        lost_any[(tq > T_C + 0.015) | near].all()
        and not lost_any[~((tq > T_C + 0.015) | near)].any()
    )


def test_trim_keeps_samples_when_window_is_on_the_grid() -> None:
    demo = _demo()
    w = DemoWindow(t0=0.6, tf=0.9, t_peak=0.8, t_rest=0.55)
    cut = trim_demonstration(
        Demonstration(demo.t, demo.hand_pos, demo.hand_quat, demo.markers, t_c=0.85), w
    )
    i = (T >= 0.6 - 1e-9) & (T <= 0.9 + 1e-9)
    assert len(cut.t) == i.sum()
    np.testing.assert_allclose(cut.hand_pos, demo.hand_pos[i], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cut.markers, demo.markers[i], rtol=0, atol=1e-12)  # NaN alike


def test_trim_errors() -> None:
    demo = _demo()
    with pytest.raises(RecordError) as e:
        trim_demonstration(demo, DemoWindow(t0=0.6, tf=0.9, t_peak=0.8, t_rest=0.55))
    assert str(e.value) == "window [0.6, 0.9] s does not contain t_c = 0.98 s"
    with pytest.raises(RecordError) as e:
        trim_demonstration(demo, DemoWindow(t0=1.0, tf=1.6, t_peak=0.8, t_rest=0.55))
    assert str(e.value) == "window [1.0, 1.6] s is not inside the demonstration [0.0, 1.5] s"

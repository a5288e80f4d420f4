"""Tests of the motion-capture emulation (flyknot_sim.mocap)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from flyknot.errors import ConfigError, RecordError
from flyknot_sim.mocap import (
    MocapParams,
    add_noise,
    apply_tracking_loss,
    emulate,
    resample_markers,
    sample_times,
)

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)


def _sim_motion(k: int = 401, dt: float = 0.002, n: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """A smooth made-up motion of n markers sampled every dt [s]."""
    t = np.arange(k) * dt
    j = np.arange(n)
    x = np.sin(2.0 * t[:, None] + 0.1 * j[None, :])
    y = 0.1 * j[None, :] + 0.0 * t[:, None]
    z = 1.5 - 0.1 * j[None, :] + 0.2 * np.cos(3.0 * t[:, None])
    return t, np.stack([x, y, z], axis=-1)


# --- parameters -------------------------------------------------------------------------


def test_params_defaults_match_the_lab() -> None:
    p = MocapParams()
    assert (p.rate_hz, p.noise_std, p.loss_delay, p.loss_mode) == (200.0, 0.001, 0.02, "all")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rate_hz": 0.0}, "MocapParams.rate_hz: must be a finite number > 0, got 0.0"),
        ({"noise_std": -1e-3}, "MocapParams.noise_std: must be a finite number >= 0, got -0.001"),
        ({"loss_delay": float("nan")}, "MocapParams.loss_delay: must be a finite number >= 0"),
        (
            {"loss_mode": "some"},
            "MocapParams.loss_mode: unknown value 'some' (valid choices: all, random, none)",
        ),
        ({"loss_fraction": 1.5}, "MocapParams.loss_fraction: must lie in [0, 1], got 1.5"),
    ],
)
def test_params_reject_bad_values(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        MocapParams(**kwargs)
    assert str(e.value).startswith(message)
    assert e.value.field == message.split(":")[0]


def test_rng_must_be_a_generator() -> None:
    with pytest.raises(ConfigError, match=r"^rng: must be a numpy.random.Generator, got int$"):
        add_noise(np.zeros((2, 11, 3)), 0.001, 42)  # type: ignore[arg-type]


# --- sample times -----------------------------------------------------------------------


def test_sample_times_exact() -> None:
    t = sample_times(1.0, 200.0)
    assert t.shape == (201,)
    np.testing.assert_array_equal(t, np.arange(201) / 200.0)
    assert t[-1] == 1.0
    np.testing.assert_allclose(np.diff(t), 0.005, rtol=0, atol=1e-15)


def test_sample_times_end_between_frames_and_offset() -> None:
    assert sample_times(1.0049, 200.0).shape == (201,)
    assert sample_times(0.0, 200.0).tolist() == [0.0]
    t = sample_times(0.5, 100.0, t_start=0.25)
    np.testing.assert_allclose(t, 0.25 + np.arange(26) / 100.0, rtol=0, atol=1e-15)


def test_sample_times_errors() -> None:
    with pytest.raises(ConfigError, match=r"^t_end: must be >= t_start = 1.0, got 0.5$"):
        sample_times(0.5, 200.0, t_start=1.0)
    with pytest.raises(ConfigError, match=r"^rate_hz: must be a finite number > 0, got -5$"):
        sample_times(1.0, -5)


@given(st.floats(0.0, 20.0), st.sampled_from([100.0, 120.0, 200.0, 250.0, 360.0]))
def test_sample_times_property(t_end: float, rate: float) -> None:
    t = sample_times(t_end, rate)
    assert t[0] == 0.0
    assert t[-1] <= t_end + 1e-9
    assert t[-1] + 1.0 / rate > t_end - 1e-9
    np.testing.assert_allclose(np.diff(t), 1.0 / rate, rtol=1e-9, atol=1e-12)


# --- resampling -------------------------------------------------------------------------


def test_resample_hits_samples_exactly_and_shapes() -> None:
    t_sim, m_sim = _sim_motion()
    out = resample_markers(t_sim, m_sim, t_sim[::5])
    assert out.shape == (81, 11, 3)
    np.testing.assert_array_equal(out, m_sim[::5])


def test_resample_midpoints_are_averages() -> None:
    t_sim, m_sim = _sim_motion(k=11)
    mid = 0.5 * (t_sim[:-1] + t_sim[1:])
    np.testing.assert_allclose(
        resample_markers(t_sim, m_sim, mid), 0.5 * (m_sim[:-1] + m_sim[1:]), rtol=0, atol=1e-15
    )


@settings(max_examples=50, deadline=None)
@given(
    arrays(float, (5, 3), elements=finite),
    arrays(float, (5, 3), elements=finite),
    st.lists(st.floats(0.001, 0.05), min_size=2, max_size=40),
    st.lists(st.floats(0.0, 1.0), min_size=1, max_size=30),
)
def test_resample_linear_motion_is_exact(
    x0: np.ndarray, v: np.ndarray, steps: list[float], fractions: list[float]
) -> None:
    """x(t) = x0 + v t sampled at uneven times is reproduced exactly at any time between."""
    t_sim = np.concatenate([[0.0], np.cumsum(steps)])
    m_sim = x0[None] + v[None] * t_sim[:, None, None]
    t_out = np.array(fractions) * t_sim[-1]
    want = x0[None] + v[None] * t_out[:, None, None]
    np.testing.assert_allclose(resample_markers(t_sim, m_sim, t_out), want, rtol=0, atol=1e-9)


def test_resample_errors() -> None:
    t_sim, m_sim = _sim_motion(k=11)
    with pytest.raises(RecordError, match=r"^t_out spans \[0.0, 0.03\] s, outside the simulated"):
        resample_markers(t_sim, m_sim, np.array([0.0, 0.03]))
    with pytest.raises(RecordError, match=r"^markers_sim must have 11 frames to match its times"):
        resample_markers(t_sim, m_sim[:-1], t_sim)
    with pytest.raises(RecordError, match=r"^t_sim must be strictly increasing$"):
        resample_markers(t_sim[::-1], m_sim, t_sim)
    bad = m_sim.copy()
    bad[3, 2, 1] = np.nan
    with pytest.raises(RecordError, match=r"^markers_sim must be finite everywhere$"):
        resample_markers(t_sim, bad, t_sim)


# --- noise ------------------------------------------------------------------------------


def test_noise_statistics() -> None:
    rng = np.random.default_rng(0)
    clean = np.broadcast_to(np.linspace(0, 1, 11)[None, :, None], (20000, 11, 3)).copy()
    noisy = add_noise(clean, 0.001, rng)
    e = (noisy - clean).reshape(-1, 3)  # 220 000 samples per axis
    assert noisy.shape == clean.shape
    # std within 2 % (its sampling error is ~0.15 %), mean within 5 standard errors.
    np.testing.assert_allclose(e.std(axis=0), 0.001, rtol=0.02)
    assert np.all(np.abs(e.mean(axis=0)) < 5 * 0.001 / np.sqrt(e.shape[0]))
    # axes uncorrelated
    c = np.corrcoef(e.T)
    assert np.all(np.abs(c[np.triu_indices(3, 1)]) < 0.01)


def test_noise_zero_std_and_nan_and_seed() -> None:
    x = np.ones((4, 11, 3))
    x[2, 5] = np.nan
    assert np.array_equal(add_noise(x, 0.0, np.random.default_rng(1)), x, equal_nan=True)
    y = add_noise(x, 0.01, np.random.default_rng(1))
    assert np.isnan(y[2, 5]).all() and np.isfinite(np.delete(y.reshape(-1, 3), 27, 0)).all()
    np.testing.assert_array_equal(y, add_noise(x, 0.01, np.random.default_rng(1)))


# --- tracking loss ----------------------------------------------------------------------


def test_loss_all_exactly_from_contact_plus_delay() -> None:
    t = sample_times(1.0, 200.0)
    x = np.zeros((t.size, 11, 3))
    out = apply_tracking_loss(t, x, 0.5, MocapParams(), np.random.default_rng(0))
    lost = np.isnan(out).any(axis=(1, 2))
    # 0.5 + 0.02 = 0.52 s = frame 104 (a frame lands exactly on the onset: it is lost).
    assert not lost[:104].any()
    assert np.isnan(out[104:]).all()
    out2 = apply_tracking_loss(t, x, 0.5012, MocapParams(), np.random.default_rng(0))
    assert np.isnan(out2).any(axis=(1, 2)).argmax() == 105  # onset 0.5212 s


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 1.2), st.floats(0.0, 0.1))
def test_loss_onset_property(t_contact: float, delay: float) -> None:
    t = sample_times(1.0, 200.0)
    p = MocapParams(loss_delay=delay)
    out = apply_tracking_loss(t, np.zeros((t.size, 11, 3)), t_contact, p, np.random.default_rng(0))
    lost = np.isnan(out).all(axis=(1, 2))
    seen = np.isfinite(out).all(axis=(1, 2))
    assert np.all(lost | seen)
    onset = t_contact + delay
    assert np.all(seen[t < onset - 1e-9])
    assert np.all(lost[t >= onset])


def test_no_contact_no_loss_and_none_mode() -> None:
    t = sample_times(1.0, 200.0)
    x = np.ones((t.size, 11, 3))
    rng = np.random.default_rng(0)
    for mode in ("all", "random", "none"):
        out = apply_tracking_loss(t, x, None, MocapParams(loss_mode=mode), rng)
        np.testing.assert_array_equal(out, x)
    out = apply_tracking_loss(t, x, 0.1, MocapParams(loss_mode="none"), rng)
    np.testing.assert_array_equal(out, x)


def test_loss_random_fraction_and_per_marker_independence() -> None:
    t = sample_times(60.0, 200.0)  # 12 001 frames
    x = np.zeros((t.size, 11, 3))
    p = MocapParams(loss_mode="random", loss_fraction=0.3)
    out = apply_tracking_loss(t, x, 10.0, p, np.random.default_rng(3))
    lost = np.isnan(out).any(axis=2)  # (m, 11)
    # a lost marker loses all three coordinates
    assert np.array_equal(lost, np.isnan(out).all(axis=2))
    before = t < 10.02 - 1e-9
    assert not lost[before].any()
    after = lost[~before]
    # each marker: fraction within 5 standard errors of 0.3
    se = np.sqrt(0.3 * 0.7 / after.shape[0])
    assert np.all(np.abs(after.mean(axis=0) - 0.3) < 5 * se)
    # independence between markers: joint loss of two markers ~ 0.09
    assert abs((after[:, 0] & after[:, 1]).mean() - 0.09) < 0.02
    # with loss, some frames keep some markers (unlike "all")
    assert (after.any(axis=1) & ~after.all(axis=1)).mean() > 0.9


def test_loss_errors() -> None:
    t = sample_times(1.0, 200.0)
    with pytest.raises(RecordError, match=r"^markers must have 201 frames to match its times"):
        apply_tracking_loss(t, np.zeros((5, 11, 3)), 0.5, MocapParams(), np.random.default_rng())
    with pytest.raises(
        ConfigError, match=r"^first_contact_time: must be a finite time or None, got nan$"
    ):
        apply_tracking_loss(
            t, np.zeros((201, 11, 3)), float("nan"), MocapParams(), np.random.default_rng()
        )


# --- the chain --------------------------------------------------------------------------


def test_emulate_chain() -> None:
    t_sim, m_sim = _sim_motion(k=501, dt=0.002)  # 0 .. 1.0 s
    t = sample_times(t_sim[-1], 200.0)
    m = emulate(t_sim, m_sim, t, 0.4, MocapParams(noise_std=0.0), np.random.default_rng(0))
    assert m.shape == (201, 11, 3)
    ok = t < 0.42 - 1e-9
    np.testing.assert_allclose(m[ok], resample_markers(t_sim, m_sim, t[ok]), rtol=0, atol=1e-15)
    assert np.isnan(m[~ok]).all()


def test_emulate_noise_and_seed_reproducible() -> None:
    t_sim, m_sim = _sim_motion(k=501, dt=0.002)
    t = sample_times(t_sim[-1], 200.0)
    p = MocapParams(noise_std=0.001, loss_mode="random")
    a = emulate(t_sim, m_sim, t, 0.4, p, np.random.default_rng(7))
    b = emulate(t_sim, m_sim, t, 0.4, p, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
    err = a[t < 0.4] - resample_markers(t_sim, m_sim, t[t < 0.4])
    assert 0.0008 < err.std() < 0.0012
    assert np.isnan(a[t >= 0.42]).any() and np.isfinite(a[t >= 0.42]).any()


def test_emulate_offset_clock_and_errors() -> None:
    t_sim, m_sim = _sim_motion(k=101, dt=0.002)  # 0 .. 0.2 s
    t = sample_times(0.2, 200.0, t_start=0.0123)
    m = emulate(t_sim, m_sim, t, None, MocapParams(noise_std=0.0), np.random.default_rng(0))
    np.testing.assert_allclose(m, resample_markers(t_sim, m_sim, t), rtol=0, atol=0)
    assert np.isfinite(m).all()
    with pytest.raises(RecordError, match=r"^t_out spans \[0.0, 0.205\] s, outside the simulated"):
        emulate(t_sim, m_sim, np.array([0.0, 0.205]), None, MocapParams(), np.random.default_rng())
    with pytest.raises(ConfigError, match=r"^params: must be a MocapParams, got dict$"):
        emulate(t_sim, m_sim, t, None, {}, np.random.default_rng())  # type: ignore[arg-type]

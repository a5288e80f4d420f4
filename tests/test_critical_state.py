"""Critical-point state from noisy, partly lost markers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError, RecordError
from flyknot.geometry import quat_to_matrix
from learner.critical_state import (
    MarkerFitParams,
    local_polyfit_state,
    markers_state_at,
    to_demo_frame,
)


@settings(max_examples=40, deadline=None)
@given(
    c=st.lists(st.floats(-5, 5), min_size=3, max_size=3),
    t_c=st.floats(0.1, 0.9),
)
def test_quadratic_motion_is_recovered_exactly(c, t_c):
    t = np.arange(0, 1.0, 0.005)
    y = (c[0] + c[1] * t + c[2] * t**2)[:, None]
    p, v = local_polyfit_state(t, y, t_c)
    assert p[0] == pytest.approx(c[0] + c[1] * t_c + c[2] * t_c**2, abs=1e-9)
    assert v[0] == pytest.approx(c[1] + 2 * c[2] * t_c, abs=1e-7)


def test_noise_is_smoothed_and_lost_tail_is_handled():
    rng = np.random.default_rng(0)
    t = np.arange(0, 1.0, 0.005)
    true = np.stack([np.sin(3 * t), np.cos(2 * t), 0.5 * t], axis=1)
    y = true + rng.normal(scale=0.001, size=true.shape)
    t_c = 0.5
    y[t > t_c + 0.005] = np.nan  # tracking lost 5 ms after t_c
    p, v = local_polyfit_state(t, y, t_c)
    np.testing.assert_allclose(p, [np.sin(1.5), np.cos(1.0), 0.25], atol=2.5e-3)
    np.testing.assert_allclose(v, [3 * np.cos(1.5), -2 * np.sin(1.0), 0.5], atol=0.35)


def test_lost_before_tc_is_an_error():
    t = np.arange(0, 1.0, 0.005)
    y = np.ones((t.size, 3))
    y[t > 0.4] = np.nan
    with pytest.raises(RecordError, match=r"nearest finite marker sample is 100\.0 ms from t_c"):
        local_polyfit_state(t, y, 0.5, MarkerFitParams(half_window=0.2))
    with pytest.raises(RecordError, match=r"only 0 finite marker samples"):
        local_polyfit_state(t, y, 0.5)


def test_marker_index_named_in_error():
    t = np.arange(0, 1.0, 0.005)
    m = np.zeros((t.size, 11, 3))
    m[:, 7] = np.nan
    with pytest.raises(RecordError, match=r"^marker 7: only 0 finite"):
        markers_state_at(t, m, 0.5)


def test_bad_params():
    with pytest.raises(ConfigError, match=r"degree: unsupported value 3 \(valid choices: 1, 2\)"):
        MarkerFitParams(degree=3)
    with pytest.raises(ConfigError, match="half_window: must be a finite number > 0"):
        MarkerFitParams(half_window=0)


@settings(max_examples=30, deadline=None)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
)
def test_quat_to_matrix_is_a_rotation(q):
    R = quat_to_matrix(np.array(q))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_to_demo_frame_inverts_the_base_pose():
    R = quat_to_matrix(np.array([np.cos(0.3), 0, 0, np.sin(0.3)]))
    t_b = np.array([0.2, -0.1, 1.0])
    p_base = np.array([[0.3, 0.1, 0.5]])
    p_lab = p_base @ R.T + t_b
    b = np.array([0.05, 0.0, -0.2])
    base_pose = np.r_[t_b, np.cos(0.3), 0, 0, np.sin(0.3)]
    p, v = to_demo_frame(p_lab, p_lab - t_b, base_pose, b)
    np.testing.assert_allclose(p, p_base + b, atol=1e-12)
    np.testing.assert_allclose(v, p_base, atol=1e-12)

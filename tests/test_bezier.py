"""The Bezier command: Bernstein basis, its derivatives, the knot Jacobian, BezierCommand."""

from __future__ import annotations

import dataclasses
from math import comb

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.polynomial import Polynomial

from flyknot.errors import ConfigError
from flyknot.record import JointCommand
from learner.bezier import (
    BezierCommand,
    bernstein_basis,
    sample_command,
    sample_jacobian,
)

T = 0.8
RNG = np.random.default_rng(7)


def _knots(rng: np.random.Generator = RNG) -> np.ndarray:
    k = rng.uniform(-2.0, 2.0, size=(10, 8))
    k[7:] = rng.uniform(-1.0, 1.0, size=(3, 1))  # constant base rows
    return k


def test_partition_of_unity_and_derivative_sums():
    t = np.linspace(0.0, T, 41)
    np.testing.assert_allclose(bernstein_basis(t, T).sum(axis=1), 1.0, atol=1e-14)
    for r in (1, 2, 3):
        # d^r/dt^r of a constant is zero.
        np.testing.assert_allclose(bernstein_basis(t, T, r).sum(axis=1), 0.0, atol=1e-9)
    assert np.all(bernstein_basis(t, T) >= 0.0)


@pytest.mark.parametrize("r", [1, 2, 3])
def test_derivatives_match_central_differences(r):
    h = 1e-5 * T
    t = np.linspace(h, T - h, 23)
    fd = (bernstein_basis(t + h, T, r - 1) - bernstein_basis(t - h, T, r - 1)) / (2 * h)
    exact = bernstein_basis(t, T, r)
    rel = np.linalg.norm(exact - fd) / np.linalg.norm(exact)
    assert rel < 1e-6


@pytest.mark.parametrize("r", [0, 1, 2, 3])
def test_basis_matches_numpy_polynomial(r):
    t = np.linspace(0.0, T, 17)
    s = Polynomial([0.0, 1.0])
    want = np.empty((t.size, 8))
    for i in range(8):
        b = comb(7, i) * s**i * (1 - s) ** (7 - i)
        want[:, i] = b.deriv(r)(t / T) / T**r
    np.testing.assert_allclose(bernstein_basis(t, T, r), want, rtol=1e-12, atol=1e-9)


def test_endpoints_interpolate_first_and_last_knot():
    k = _knots()
    y = sample_command(k, T, np.array([0.0, T]))
    np.testing.assert_allclose(y[0], k[:, 0], atol=1e-14)
    np.testing.assert_allclose(y[1], k[:, -1], atol=1e-14)
    # End slopes: 7 (k1 - k0) / T and 7 (k7 - k6) / T.
    yd = sample_command(k, T, np.array([0.0, T]), derivative=1)
    np.testing.assert_allclose(yd[0], 7 * (k[:, 1] - k[:, 0]) / T, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(yd[1], 7 * (k[:, 7] - k[:, 6]) / T, rtol=1e-12, atol=1e-12)


knot_arrays = arrays(
    np.float64, (10, 8), elements=st.floats(-10.0, 10.0, allow_nan=False, allow_subnormal=False)
)


@settings(max_examples=40, deadline=None)
@given(k1=knot_arrays, k2=knot_arrays, a=st.floats(-3.0, 3.0), T_=st.floats(0.1, 5.0))
def test_linear_in_knots_and_inside_convex_hull(k1, k2, a, T_):
    t = np.linspace(0.0, T_, 13)
    y1, y2 = sample_command(k1, T_, t), sample_command(k2, T_, t)
    np.testing.assert_allclose(sample_command(a * k1 + k2, T_, t), a * y1 + y2, atol=1e-9)
    # Convex hull: each row stays within its knots' range.
    assert np.all(y1 >= k1.min(axis=1) - 1e-9)
    assert np.all(y1 <= k1.max(axis=1) + 1e-9)


@settings(max_examples=25, deadline=None)
@given(k=knot_arrays, r=st.sampled_from([0, 1, 2, 3]), rows=st.sampled_from([(0, 6), (7, 8, 9)]))
def test_jacobian_reproduces_samples(k, r, rows):
    t = np.linspace(0.0, T, 9)
    rows = list(range(rows[0], rows[-1] + 1))
    J = sample_jacobian(t, T, r, rows)
    assert J.shape == (9 * len(rows), 80)
    y = sample_command(k, T, t, r)[:, rows]
    np.testing.assert_allclose(J @ k.ravel(), y.ravel(), atol=1e-8 * (1 + np.abs(y).max()))


@pytest.mark.parametrize("r", [0, 2])
def test_jacobian_against_finite_differences(r):
    t = np.linspace(0.0, T, 11)
    k = _knots()
    J = sample_jacobian(t, T, r)
    h = 1e-6
    fd = np.empty_like(J)
    for c in range(80):
        e = np.zeros(80)
        e[c] = h
        yp = sample_command(k + e.reshape(10, 8), T, t, r)[:, :7].ravel()
        ym = sample_command(k - e.reshape(10, 8), T, t, r)[:, :7].ravel()
        fd[:, c] = (yp - ym) / (2 * h)
    assert np.linalg.norm(J - fd) / np.linalg.norm(J) < 1e-6
    # Default rows are the 7 joints: the base columns are zero.
    assert not J.reshape(-1, 10, 8)[:, 7:].any()


def test_validation_messages():
    t = np.linspace(0.0, T, 5)
    with pytest.raises(ConfigError, match=r"^T: must be a finite number > 0, got 0\.0$"):
        bernstein_basis(t, 0.0)
    with pytest.raises(
        ConfigError, match=r"^derivative: unknown value 4 \(valid choices: 0, 1, 2, 3\)$"
    ):
        bernstein_basis(t, T, 4)
    with pytest.raises(
        ConfigError, match=r"^t: must lie in \[0, T\] = \[0, 0\.8\] s, got values in \[0, 0\.9\]$"
    ):
        bernstein_basis(np.array([0.0, 0.9]), T)
    with pytest.raises(ConfigError, match=r"^knots: must have shape \(10, 8\), got \(7, 8\)$"):
        sample_command(np.zeros((7, 8)), T, t)
    k = _knots()
    k[3, 5] = np.nan
    with pytest.raises(
        ConfigError, match=r"^knots: must be finite; first non-finite value at row 3, knot 5$"
    ):
        sample_command(k, T, t)
    with pytest.raises(
        ConfigError, match=r"^rows: unknown row 10 \(valid choices: 0, 1, 2, 3, 4, 5, 6, 7, 8, 9\)$"
    ):
        sample_jacobian(t, T, 0, [0, 10])


def test_times_within_rounding_of_T_are_accepted():
    b = bernstein_basis(np.array([-1e-12, T * (1 + 1e-12)]), T)
    np.testing.assert_allclose(b[0], np.eye(8)[0])
    np.testing.assert_allclose(b[1], np.eye(8)[7])


def test_command_validation_messages():
    k = _knots()
    k[8, 3] += 0.1
    with pytest.raises(
        ConfigError,
        match=r"^knots: base-offset row 8 must be constant across the 8 knots, varies by 0\.1 m$",
    ):
        BezierCommand(k, T)
    with pytest.raises(ConfigError, match=r"^T: must be a finite number > 0, got -1\.0$"):
        BezierCommand(_knots(), -1)
    # Rounding-level differences in the base rows are accepted.
    k = _knots()
    k[7, 4] *= 1 + 1e-13
    BezierCommand(k, T)


def test_command_joint_command_and_base_offset():
    k = _knots()
    cmd = BezierCommand(k, T)
    jc = cmd.joint_command()
    assert isinstance(jc, JointCommand)
    assert jc.rate_hz == 250.0
    assert jc.q.shape == (201, 7)  # 0, 4 ms, ..., 800 ms inclusive
    np.testing.assert_allclose(jc.q[0], k[:7, 0], atol=1e-14)
    np.testing.assert_allclose(jc.q[-1], k[:7, -1], atol=1e-12)
    np.testing.assert_allclose(jc.q[50], sample_command(k, T, np.array([0.2]))[0, :7], atol=1e-14)
    np.testing.assert_array_equal(cmd.base_offset, k[7:, 0])
    np.testing.assert_allclose(cmd.knot_times, np.arange(8) * T / 7)
    # T not a multiple of the period: the last sample is the last one before T.
    jc2 = BezierCommand(k, 0.803).joint_command()
    assert jc2.q.shape == (201, 7)


def test_command_is_frozen():
    cmd = BezierCommand(_knots(), T)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cmd.T = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        cmd.knots[0, 0] = 1.0

"""The one geometry module: quaternions, rotations, skew matrices, read-only arrays."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from flyknot.errors import ConfigError
from flyknot.geometry import (
    as_vec3,
    matrix_to_quat,
    min_rotation,
    quat_from_x_to,
    quat_sign_continuous,
    quat_to_matrix,
    readonly,
    skew,
)

unit = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3)


def test_quat_to_matrix_matches_scipy_in_batches():
    rots = Rotation.random(50, random_state=1)
    q = rots.as_quat(scalar_first=True) * 3.0  # not unit: normalised first
    np.testing.assert_allclose(quat_to_matrix(q), rots.as_matrix(), atol=1e-14)
    np.testing.assert_allclose(quat_to_matrix(q[0]), rots[0].as_matrix(), atol=1e-14)


def test_matrix_to_quat_round_trip_has_w_nonnegative():
    rots = Rotation.random(200, random_state=2)
    q = matrix_to_quat(rots.as_matrix())
    assert np.all(q[:, 0] >= 0.0)
    np.testing.assert_allclose(quat_to_matrix(q), rots.as_matrix(), atol=1e-12)


def test_zero_quaternion_is_refused_with_the_field_named():
    with pytest.raises(ConfigError, match=r"^quat: has no direction: \[0\.0, 0\.0, 0\.0, 0\.0\]$"):
        quat_to_matrix(np.zeros(4))
    with pytest.raises(ConfigError, match=r"^quat: must have shape \(\.\.\., 4\), got \(3,\)$"):
        quat_to_matrix(np.ones(3))


def test_sign_continuity_flips_only_the_jumps():
    rots = Rotation.from_rotvec(np.linspace(0, 3, 40)[:, None] * np.array([0.0, 0.6, 0.8]))
    q = rots.as_quat(scalar_first=True)
    q[::3] *= -1.0
    out = quat_sign_continuous(q)
    assert np.all(np.sum(out[1:] * out[:-1], axis=1) >= 0.0)
    np.testing.assert_allclose(np.abs(out), np.abs(q))
    first = quat_sign_continuous(-np.abs(q), first_positive=True)
    assert first[0, 0] > 0


@settings(max_examples=60, deadline=None)
@given(u=unit, v=unit)
def test_min_rotation_takes_u_to_v(u, v):
    u, v = np.array(u), np.array(v)
    R = min_rotation(u, v)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-10)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-10)
    np.testing.assert_allclose(R @ (u / np.linalg.norm(u)), v / np.linalg.norm(v), atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(a=unit)
def test_quat_from_x_to_takes_e_x_to_the_axis(a):
    a = np.array(a)
    R = quat_to_matrix(quat_from_x_to(a))
    np.testing.assert_allclose(R[:, 0], a / np.linalg.norm(a), atol=1e-12)


def test_skew_is_the_cross_product_in_batches():
    rng = np.random.default_rng(0)
    w, v = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", skew(w), v), np.cross(w, v), atol=1e-14)
    with pytest.raises(ConfigError, match=r"^w: must have shape \(\.\.\., 3\), got \(2,\)$"):
        skew(np.ones(2))
    with pytest.raises(ConfigError, match=r"^p: must have shape"):
        as_vec3("p", np.ones((2, 4)))


def test_readonly_copies_and_freezes():
    src = np.arange(3)
    out = readonly(src)
    assert out.dtype == float and not out.flags.writeable
    src[0] = 7
    assert out[0] == 0.0
    assert readonly([True, False], bool).dtype == bool

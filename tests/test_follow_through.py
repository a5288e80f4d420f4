"""SO(3) kernels, the matched follow-through reference and J_ft against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from flyknot.constants import XARM7_XML
from flyknot.errors import ConfigError
from flyknot.geometry import right_jacobian_inv, skew, so3_exp, so3_log
from learner.bezier import sample_command
from learner.follow_through import (
    fingertip_errors,
    follow_through_terms,
    matched_reference,
    tip_angular_jacobian,
)
from learner.kinematics import RobotModel

HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
T = 0.8
T_C = 0.45
J_TOL = 1e-5  # relative error of J_ft against central differences


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_mjcf(XARM7_XML)


def _knots(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, 8)
    k = np.zeros((10, 8))
    k[:7] = HOME[:, None] + 0.4 * np.sin(np.pi * s)[None] * rng.uniform(-1, 1, (7, 1))
    k[7:] = np.array([0.1, -0.05, 1.0])[:, None]
    return k


def _samples() -> np.ndarray:
    return np.concatenate([[T_C], np.arange(91, 161) * 0.005])


def _demo_hand(k: int, seed: int):
    """A smooth made-up hand motion with an arbitrary hand frame."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, k)[:, None]
    p = rng.normal(size=3) + s * rng.normal(size=3) + s**2 * rng.normal(size=3)
    v = rng.normal(size=3) + 2 * s * rng.normal(size=3)
    R = so3_exp(rng.normal(size=3) + s * rng.normal(size=3))
    return p, R, v


# ------------------------------------------------------------------------------------ SO(3)


def test_so3_log_matches_scipy():
    rots = Rotation.random(2000, random_state=1)
    np.testing.assert_allclose(so3_log(rots.as_matrix()), rots.as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(so3_exp(rots.as_rotvec()), rots.as_matrix(), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-6, 1e-4, 0.5, np.pi - 1e-6, np.pi - 1e-9])
def test_so3_log_near_zero_and_pi(angle):
    rng = np.random.default_rng(2)
    for _ in range(10):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = Rotation.from_rotvec(angle * axis).as_matrix()
        phi = so3_log(R)
        np.testing.assert_allclose(phi, angle * axis, atol=1e-9 + 1e-12 * angle)
        np.testing.assert_allclose(so3_exp(phi), R, atol=1e-14)


def test_so3_log_at_pi_returns_a_valid_axis():
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis).as_matrix()
        phi = so3_log(R)
        assert np.linalg.norm(phi) == pytest.approx(np.pi, abs=1e-12)
        np.testing.assert_allclose(np.abs(phi), np.pi * axis, atol=1e-12)
        np.testing.assert_allclose(so3_exp(phi), R, atol=1e-14)


@settings(max_examples=200, deadline=None)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
)
def test_exp_of_log_is_identity(q):
    R = Rotation.from_quat(np.array(q)).as_matrix()
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-13)
    assert np.linalg.norm(so3_log(R)) <= np.pi + 1e-12


@settings(max_examples=200, deadline=None)
@given(
    axis=st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(
        lambda a: np.linalg.norm(a) > 0.1
    ),
    angle=st.floats(0.0, np.pi - 1e-6),
)
def test_log_of_exp_is_identity(axis, angle):
    phi = angle * np.array(axis) / np.linalg.norm(axis)
    np.testing.assert_allclose(so3_log(so3_exp(phi)), phi, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.3, 2.0, 3.1])
def test_right_jacobian_inverse_against_finite_differences(angle):
    """Log(Exp(phi) Exp(d)) - phi ~= J_r^-1(phi) d, by central differences."""
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    phi = angle * axis / np.linalg.norm(axis)
    eps = 1e-6
    J = right_jacobian_inv(phi)
    R = so3_exp(phi)
    for c in range(3):
        d = np.zeros(3)
        d[c] = eps
        fd = (so3_log(R @ so3_exp(d)) - so3_log(R @ so3_exp(-d))) / (2 * eps)
        np.testing.assert_allclose(J[:, c], fd, atol=1e-8)


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    w, v = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", skew(w), v), np.cross(w, v), atol=1e-15)
    with pytest.raises(ConfigError, match=r"^R: must have shape \(\.\.\., 3, 3\), got \(3, 4\)$"):
        so3_log(np.zeros((3, 4)))


# ----------------------------------------------------------------------------- kinematics


def test_tip_angular_jacobian_against_finite_differences(robot):
    rng = np.random.default_rng(5)
    q = HOME + rng.uniform(-0.5, 0.5, (4, 7))
    Jw = tip_angular_jacobian(robot, q)
    assert Jw.shape == (4, 3, 7)
    eps = 1e-6
    for a in range(4):
        R0 = np.asarray(robot.fk(q[a])[1])
        for j in range(7):
            dq = np.zeros(7)
            dq[j] = eps
            Rp = np.asarray(robot.fk(q[a] + dq)[1])
            Rm = np.asarray(robot.fk(q[a] - dq)[1])
            fd = (so3_log(R0.T @ Rp) - so3_log(R0.T @ Rm)) / (2 * eps)
            np.testing.assert_allclose(Jw[a, :, j], fd, atol=1e-8)


# --------------------------------------------------------------------------- reference, J_ft


def test_matched_reference_passes_through_the_tip_and_keeps_the_motion():
    p_h, R_h, v_h = _demo_hand(20, 1)
    p_c = np.array([0.4, 0.0, 1.3])
    R_c = so3_exp(np.array([0.3, -1.0, 2.0]))
    p_ref, R_ref, v_ref = matched_reference(p_c, R_c, p_h, R_h, v_h)
    np.testing.assert_allclose(p_ref[0], p_c, atol=1e-15)
    np.testing.assert_allclose(R_ref[0], R_c, atol=1e-14)
    np.testing.assert_allclose(p_ref - p_ref[0], p_h - p_h[0], atol=1e-14)  # same path
    # Same world-frame rotation from t_c on: R_ref(t) R_ref(t_c)^T = R_h(t) R_h(t_c)^T.
    np.testing.assert_allclose(R_ref @ R_ref[0].T, R_h @ R_h[0].T, atol=1e-13)
    np.testing.assert_allclose(v_ref, v_h)


def test_follow_through_errors_are_zero_at_tc_except_velocity(robot):
    knots = _knots(1)
    t = _samples()
    p_h, R_h, v_h = _demo_hand(t.size, 2)
    ft = follow_through_terms(knots, T, t, T_C, p_h, R_h, v_h, robot)
    assert ft.e.shape == (71, 9) and ft.J.shape == (71, 9, 80)
    assert ft.is_tc.tolist() == [True] + [False] * 70
    np.testing.assert_allclose(ft.e[0, :6], 0.0, atol=1e-14)
    # The tip velocity includes the base rows' (here zero) rate: v_tip = J_p(q) qd.
    q, qd = (sample_command(knots, T, t[:1], r)[:, :7] for r in (0, 1))
    v_tip = robot.tip_states(q, qd).v[0]
    np.testing.assert_allclose(ft.e[0, 6:], v_tip - v_h[0], atol=1e-12)
    assert np.all(np.linalg.norm(ft.e[1:, 3:6], axis=1) > 0)


@pytest.mark.parametrize("seed", [1, 2])
def test_follow_through_jacobian_against_finite_differences(robot, seed):
    """J_ft = d e_ft / d kappa with the matched reference held fixed (all 80 columns)."""
    knots = _knots(seed)
    t = _samples()
    p_h, R_h, v_h = _demo_hand(t.size, seed + 10)
    ft = follow_through_terms(knots, T, t, T_C, p_h, R_h, v_h, robot)
    q = sample_command(knots, T, t[:1])[:, :7]
    p_c, R_c = robot.fk(q[0])
    ref = matched_reference(np.asarray(p_c).ravel() + knots[7:, 0], np.asarray(R_c), p_h, R_h, v_h)
    np.testing.assert_allclose(fingertip_errors(knots, T, t, *ref, robot), ft.e, atol=1e-13)
    eps = 1e-6
    fd = np.empty_like(ft.J)
    for c in range(80):
        d = np.zeros(80)
        d[c] = eps
        d = d.reshape(10, 8)
        plus = fingertip_errors(knots + d, T, t, *ref, robot)
        minus = fingertip_errors(knots - d, T, t, *ref, robot)
        fd[:, :, c] = (plus - minus) / (2 * eps)
    assert np.linalg.norm(ft.J - fd) <= J_TOL * np.linalg.norm(fd)
    for block in (slice(0, 3), slice(3, 6), slice(6, 9)):  # position, rotation, velocity
        assert np.linalg.norm(ft.J[:, block] - fd[:, block]) <= J_TOL * np.linalg.norm(fd[:, block])
    # Base columns: identity times the Bezier basis on position, its derivative on velocity.
    assert np.linalg.norm(fd[:, 0:3, 56:]) > 1.0 and np.all(ft.J[:, 3:6, 56:] == 0.0)


def test_follow_through_input_errors(robot):
    knots = _knots(1)
    t = _samples()
    p_h, R_h, v_h = _demo_hand(t.size, 2)
    with pytest.raises(
        ConfigError, match=r"^t_samples: must start at t_c = 0.45 s and end by T = 0.8 s, got"
    ):
        follow_through_terms(knots, T, t[1:], T_C, p_h[1:], R_h[1:], v_h[1:], robot)
    with pytest.raises(ConfigError, match=r"^t_samples: must be strictly increasing$"):
        follow_through_terms(knots, T, t[::-1], T_C, p_h, R_h, v_h, robot)
    with pytest.raises(ConfigError, match=r"^demo_hand_p: must have one row per sample \(71\)"):
        follow_through_terms(knots, T, t, T_C, p_h[:5], R_h[:5], v_h[:5], robot)
    with pytest.raises(ConfigError, match=r"^knots: must have shape \(10, 8\), got \(7, 8\)$"):
        follow_through_terms(knots[:7], T, t, T_C, p_h, R_h, v_h, robot)

"""IFT linearisation of the rope model against finite differences of the full rollout."""

from __future__ import annotations

import numpy as np
import pytest

from flyknot.errors import ConfigError
from learner.rope_model import RopeModelParams, rollout
from learner.rope_sensitivity import fd_sensitivity, state_sensitivity

TIP = np.array([0.0, 0.0, 1.5])
K = 30


def _motion(dt: float, seed: int):
    """A short random smooth fingertip motion with the tube swinging (K steps)."""
    rng = np.random.default_rng(seed)
    t = np.arange(K + 1) * dt
    s = 0.5 * (1.0 - np.cos(np.pi * t / t[-1]))  # starts and ends at rest
    a = rng.normal(size=(3, 2)) * 0.3
    p_tip = TIP + a[:, 0] * s[:, None] + a[:, 1] * s[:, None] ** 2
    ax, ay = rng.normal(size=2)
    d = np.stack([np.sin(ay * s), -np.sin(ax * s) * np.cos(ay * s), -np.cos(ax * s)], 1)
    return p_tip, d / np.linalg.norm(d, axis=1, keepdims=True)


def _smooth_directions(seed: int, n_theta: int) -> np.ndarray:
    """dU (K+1, 6, n_theta): random cubic polynomials in time, like a spline's knot Jacobian."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, K + 1)
    basis = np.stack([s**i for i in range(4)], axis=1)
    return np.einsum("ki,iaq->kaq", basis, rng.normal(size=(4, 6, n_theta)))


@pytest.mark.parametrize(
    "params",
    [RopeModelParams(), RopeModelParams(stiffness=10.0, damping=0.5)],
    ids=["paper", "soft"],
)
def test_ift_matches_central_differences_of_rollout(params):
    p_tip, d_tip = _motion(params.dt, seed=5)
    dU = _smooth_directions(6, 6)
    tr = rollout(p_tip, d_tip, params)
    ift = state_sensitivity(tr, dU)
    fd = fd_sensitivity(p_tip, d_tip, dU, params, p0=tr.p[0], eps=1e-6)
    assert ift.shape == fd.shape == (K + 1, 66, 6)
    assert np.linalg.norm(fd) > 1.0  # the directions really move the rope
    assert np.linalg.norm(ift - fd) / np.linalg.norm(fd) < 1e-4
    # Per step, positions and velocities separately.
    for block in (slice(0, 33), slice(33, 66)):
        err = np.linalg.norm(ift[1:, block] - fd[1:, block], axis=(1, 2))
        assert np.all(err <= 1e-4 * np.linalg.norm(fd[1:, block], axis=(1, 2)) + 1e-8)


def test_selected_steps_equal_the_full_result():
    params = RopeModelParams(stiffness=10.0, damping=0.5)
    p_tip, d_tip = _motion(params.dt, seed=1)
    dU = _smooth_directions(2, 3)
    tr = rollout(p_tip, d_tip, params)
    full = state_sensitivity(tr, dU)
    some = state_sensitivity(tr, dU, steps=[K, 0, 12])
    np.testing.assert_array_equal(some, full[[K, 0, 12]])


def test_rigid_translation_moves_every_point_alike():
    """Gravity is translation invariant: translating the tip and the start translates the rope."""
    params = RopeModelParams()
    p_tip, d_tip = _motion(params.dt, seed=3)
    tr = rollout(p_tip, d_tip, params)
    n = params.n_links
    dU = np.zeros((K + 1, 6, 3))
    dU[:, :3, :] = np.eye(3)
    dx0 = np.zeros((6 * n, 3))
    dx0[: 3 * n] = np.tile(np.eye(3), (n, 1))
    dX = state_sensitivity(tr, dU, dx0=dx0)
    np.testing.assert_allclose(dX[:, : 3 * n], np.tile(dx0[: 3 * n], (K + 1, 1, 1)), atol=1e-8)
    np.testing.assert_allclose(dX[:, 3 * n :], 0.0, atol=1e-6)


def test_initial_velocity_sensitivity_matches_finite_differences():
    params = RopeModelParams(stiffness=10.0, damping=0.5)
    p_tip, d_tip = _motion(params.dt, seed=8)
    n = params.n_links
    rng = np.random.default_rng(9)
    dv0 = rng.normal(size=(n, 3))
    tr = rollout(p_tip, d_tip, params)
    dx0 = np.concatenate([np.zeros(3 * n), dv0.ravel()])[:, None]
    ift = state_sensitivity(tr, np.zeros((K + 1, 6, 1)), dx0=dx0)[:, :, 0]
    eps = 1e-6
    xp = rollout(p_tip, d_tip, params, p0=tr.p[0], v0=eps * dv0, tol=1e-12).x
    xm = rollout(p_tip, d_tip, params, p0=tr.p[0], v0=-eps * dv0, tol=1e-12).x
    fd = (xp - xm) / (2 * eps)
    assert np.linalg.norm(ift - fd) / np.linalg.norm(fd) < 1e-4


def test_validation_messages():
    params = RopeModelParams()
    p_tip, d_tip = _motion(params.dt, seed=0)
    tr = rollout(p_tip, d_tip, params)
    with pytest.raises(ConfigError) as e:
        state_sensitivity(tr, np.zeros((K, 6, 2)))
    assert str(e.value) == "dU: must have shape (31, 6, n_theta), got (30, 6, 2)"
    with pytest.raises(ConfigError) as e:
        state_sensitivity(tr, np.zeros((K + 1, 6, 2)), steps=[3, 31])
    assert str(e.value) == "steps: must be integers in [0, 30], got 31"
    with pytest.raises(ConfigError) as e:
        state_sensitivity(tr, np.zeros((K + 1, 6, 2)), dx0=np.zeros((66, 3)))
    assert str(e.value) == "dx0: must have shape (66, 2), got (66, 3)"
    with pytest.raises(ConfigError) as e:
        state_sensitivity(tr.p, np.zeros((K + 1, 6, 2)))
    assert str(e.value) == "traj: must be a RopeTrajectory, got ndarray"

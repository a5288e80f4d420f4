"""The gymnasium environment: spaces, one trial per step, command constraints, truncation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import flyknot_app.gym_env  # noqa: F401 - registers the environment


@pytest.fixture(scope="module")
def env():
    e = gym.make("flyknot/FlyingKnot-v0", rope=1, demo="fast", max_trials=2, settle_s=0.2)
    yield e
    e.close()


def test_reset_and_step(env):
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs.astype(env.observation_space.dtype))
    assert info["trial"] == 1
    inner = env.unwrapped
    k0 = inner.knots.copy()
    np.testing.assert_array_equal(obs[66:], k0.ravel())
    action = np.linspace(-1, 1, 80)
    obs, reward, terminated, truncated, info = env.step(action)
    assert np.isfinite(reward) and info["trial"] == 2
    k1 = inner.knots
    d = k1 - k0
    np.testing.assert_allclose(d[7:], d[7:, :1].repeat(8, axis=1))  # base fixed in a command
    np.testing.assert_allclose(d[:7, 1], d[:7, 0])  # at rest at the start
    np.testing.assert_allclose(d[:7, 7], d[:7, 6])  # ... and at the end
    assert np.abs(d).max() <= inner.action_scale + 1e-12
    assert truncated or terminated  # max_trials = 2

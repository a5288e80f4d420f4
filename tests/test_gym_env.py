"""The gymnasium environment: spaces, one trial per step, command constraints, truncation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import flyknot_app.gym.env  # noqa: F401 - registers the environment
from flyknot_app.gym.env import FlyknotEnv


@pytest.fixture(scope="module")
def env():
    e = gym.make("flyknot/FlyingKnot-v0", rope=1, demo="robot", max_trials=2, settle_s=0.2)
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


def test_gymnasiums_own_checker_passes():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("flyknot/FlyingKnot-v0", rope=1, max_trials=3, settle_s=0.2)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_reset_with_a_seed_repeats_the_episode(env):
    a = np.full(80, 0.3)
    first = [env.reset(seed=5)[0], env.step(a)[0]]
    second = [env.reset(seed=5)[0], env.step(a)[0]]
    for x, y in zip(first, second, strict=True):
        np.testing.assert_array_equal(x, y)
    other = env.reset(seed=6)[0]
    assert not np.array_equal(other[:66], first[0][:66])


def test_bad_actions_are_refused_before_anything_changes(env):
    from flyknot.errors import ConfigError

    env.reset(seed=0)
    inner = env.unwrapped
    knots, trials = inner.knots.copy(), inner.trials
    bad = np.zeros(80)
    bad[3] = np.nan
    with pytest.raises(ConfigError, match=r"^action: must be finite"):
        inner.step(bad)
    with pytest.raises(ConfigError, match=r"^action: must have shape \(80,\), got \(79,\)$"):
        inner.step(np.zeros(79))
    np.testing.assert_array_equal(inner.knots, knots)
    assert inner.trials == trials
    obs, *_ = inner.step(np.zeros(80))  # still usable
    assert np.all(np.isfinite(obs))


def test_info_names_the_record_and_the_failure_class(env):
    from flyknot.record import TrialRecord
    from flyknot_app.anatomy.diagnosis import LABELS

    _, info = env.reset(seed=1)
    assert info["failure"] in LABELS
    rec = TrialRecord.load(info["record"])
    assert rec.knot == info["knot"]


def test_the_env_is_made_with_gymnasium_alone(tmp_path):
    import subprocess
    import sys

    code = (
        "import gymnasium as gym\n"
        "env = gym.make('flyknot_app.gym.env:flyknot/FlyingKnot-v0', settle_s=0.2)\n"
        "print(type(env.unwrapped).__name__, env.observation_space.is_bounded())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["FlyknotEnv", "True"]


@pytest.mark.parametrize(("klass", "bonus"), [("knot", True), ("wrapped_at_grip", False)])
def test_only_a_knot_in_the_hanging_rope_earns_the_bonus(klass, bonus, monkeypatch):
    import dataclasses

    from tests.knot_curves import verdict

    e = gym.make("flyknot/FlyingKnot-v0", rope=1, demo="robot", max_trials=2, settle_s=0.2)
    inner = e.unwrapped
    play = inner._lab.run

    def judged(command):  # the lab's trial, with the verdict of the case
        v = verdict(klass)
        return dataclasses.replace(play(command), knot=v.knot, verdict=v)

    monkeypatch.setattr(inner._lab, "run", judged)
    e.reset(seed=0)
    _, reward, terminated, _, info = e.step(np.zeros(80))
    assert terminated is bonus and info["verdict"] == klass
    assert (reward > inner.knot_bonus / 2) is bonus
    e.close()


@pytest.mark.slow
def test_the_env_starts_from_ilc_s_initial_command_as_it_is():
    """The main job's demonstration puts the base 1.31 m up in its frame: the env's first
    trial plays ILC's initial command unchanged (a clipped base would move the frame)."""
    env = FlyknotEnv(rope=1, demo="fast-paced", max_trials=2)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.knots, env.initial_knots())
    assert env.knots[-1, 0] > 1.0


def test_the_env_starts_and_scores_as_the_scenarios_do():
    """By default the env starts from the scenarios' demonstration and window and scores a
    trial with their critical weights; ``weights`` scores the same trial with others."""
    from flyknot_app.learner_settings import SCENARIO_DEMO, SCENARIO_WINDOW, scenario_weights
    from learner.ilc import critical_cost
    from learner.inverse_qp import InverseModelWeights

    ours = FlyknotEnv(rope=1, max_trials=2, settle_s=0.2)
    paper = FlyknotEnv(rope=1, max_trials=2, settle_s=0.2, weights=InverseModelWeights())
    assert (ours._demo, ours._window) == (SCENARIO_DEMO, SCENARIO_WINDOW)
    (obs, info), (obs_p, info_p) = ours.reset(seed=0), paper.reset(seed=0)
    err = obs[:66].astype(float)
    np.testing.assert_array_equal(err, obs_p[:66])  # the same trial
    assert info["cost"] == pytest.approx(critical_cost(err, scenario_weights()))
    assert info_p["cost"] == pytest.approx(critical_cost(err, InverseModelWeights()))
    assert info["cost"] > info_p["cost"]  # its velocities weigh 0.1, the paper's 0.00375
    from flyknot.errors import ConfigError

    with pytest.raises(ConfigError) as e:
        FlyknotEnv(rope=1, weights={"w_crit_vel": 0.1})
    assert str(e.value) == "weights: must be an InverseModelWeights, got {'w_crit_vel': 0.1}"

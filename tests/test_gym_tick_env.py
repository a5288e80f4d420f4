"""The tick-level gymnasium environment: spaces, actions, episodes, rewards, reproducibility."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import flyknot_app.gym.tick_env  # noqa: F401 - registers the environment
from flyknot.errors import ConfigError
from flyknot.limits import JointLimits
from flyknot.record import JointCommand, TrialRecord
from flyknot_app.gym.tick_env import FlyknotTickEnv
from flyknot_sim.commands import HOME_Q, SWING_AMPLITUDE, swing_command
from flyknot_sim.lab import LabParams, SimLab

# A short, gentle swing (76 ticks, inside every limit): cheap episodes. Its t_c lies beyond
# the record, so the critical-point cost is the fault penalty ("tracking lost before t_c").
CMD = swing_command(duration=0.3, amplitude=0.2 * SWING_AMPLITUDE)
SETTLE = 0.1


def make(**kw) -> FlyknotTickEnv:
    kw = {"command": CMD, "base_offset": np.zeros(3), "settle_s": SETTLE, **kw}
    return gym.make("flyknot/FlyingKnotTick-v0", **kw).unwrapped


def play(env, actions, seed=None):
    obs, info = env.reset(seed=seed)
    seen = [obs]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        seen.append(obs)
        assert not truncated
        if terminated:
            return seen, reward, info
    raise AssertionError("the episode did not end")


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return make(record_dir=str(tmp_path_factory.mktemp("tick")))


def test_spaces_are_bounded_and_hold_the_observations(env):
    assert env.observation_space.shape == (59,) and env.observation_space.is_bounded()
    assert env.action_space.shape == (7,) and env.action_space.is_bounded()
    seen, _, _ = play(env, [np.ones(7) * 0.5] * CMD.n, seed=0)
    for obs in seen:
        assert env.observation_space.contains(obs)
    mask = seen[5][47:58]
    assert set(np.unique(mask)) <= {0.0, 1.0} and mask.all()  # no self-contact: all seen
    assert seen[0][-1] == 0.0 and seen[-1][-1] == 1.0  # time fraction


def test_a_zero_policy_replays_the_initial_command(env):
    _, reward, info = play(env, [np.zeros(7)] * CMD.n, seed=3)
    assert info["tick"] == CMD.n and len(info["actions"]) == CMD.n
    rec = TrialRecord.load(info["record"])
    ref = SimLab(LabParams(rope=1, seed=3, settle_s=SETTLE)).run(CMD)
    for name in ("q_cmd", "q_meas", "markers", "t_marker", "fingertip_pos"):
        np.testing.assert_array_equal(getattr(rec, name), getattr(ref, name), err_msg=name)
    assert rec.knot == ref.knot == info["knot"] and info["fault"] is None
    # The short command ends before t_c: tracking counts as lost, the penalty is the cost.
    assert "tracking_lost" in info and info["cost"] == env.fault_penalty
    assert reward == -env.fault_penalty and info["success"] is False


def test_actions_offset_the_command_through_the_low_pass(env):
    a = np.linspace(-1, 1, 7)
    alpha = env.smoothing_alpha
    assert alpha == pytest.approx(1 - np.exp(-0.004 / env.smoothing_s))
    _, _, info = play(env, [a] * CMD.n, seed=0)
    rec = TrialRecord.load(info["record"])
    k = np.arange(CMD.n)[:, None]
    want = env.action_scale * a * (1 - (1 - alpha) ** (k + 1))  # o_k = o_{k-1} + alpha (u - o)
    np.testing.assert_allclose(rec.q_cmd[: CMD.n] - CMD.q, want, atol=1e-12)
    np.testing.assert_array_equal(
        rec.q_cmd[CMD.n :], np.repeat(rec.q_cmd[CMD.n - 1 : CMD.n], 25, 0)
    )


def test_without_the_low_pass_an_action_is_the_next_targets_offset(tmp_path):
    env = make(smoothing_s=0.0, action_scale=0.001, record_dir=str(tmp_path))
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (CMD.n, 7)) * 0.1
    _, _, info = play(env, actions, seed=0)
    rec = TrialRecord.load(info["record"])
    np.testing.assert_allclose(rec.q_cmd[: CMD.n], CMD.q + 0.001 * actions, atol=1e-15)


def test_targets_stay_within_the_position_limits(tmp_path):
    q_max = JointLimits().q_max
    q = np.repeat(HOME_Q[None], 30, axis=0)
    q[:, 1] = q_max[1] - 0.001
    env = make(command=JointCommand(q), smoothing_s=0.0, record_dir=str(tmp_path))
    action = np.zeros(7)
    action[1] = 1.0
    _, _, info = play(env, [action] * 30, seed=0)
    rec = TrialRecord.load(info["record"])
    assert info["fault"] is None
    np.testing.assert_array_equal(rec.q_cmd[:30, 1], q_max[1])


def test_a_fault_ends_the_episode_with_its_failure_class():
    env = make(smoothing_s=0.0, action_scale=0.05)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(np.ones(7))  # a 0.05 rad jump from rest ...
    assert not terminated and info["fault"] is None
    _, reward, terminated, truncated, info = env.step(np.ones(7))  # ... known a tick later
    assert terminated and not truncated
    assert "joint 1 velocity 6.25" in info["fault"] and info["knot"] is None  # 0.05 / 0.008 s
    assert info["failure"] == "faulted" and reward == -env.fault_penalty and info["tick"] == 2
    with pytest.raises(ConfigError, match=r"^step: the episode has ended"):
        env.step(np.zeros(7))


def test_reset_with_a_seed_repeats_the_episode(env):
    actions = [np.full(7, 0.3)] * CMD.n
    trials = env.trials
    first, r1, _ = play(env, actions, seed=5)
    second, r2, _ = play(env, actions, seed=5)
    assert r1 == r2
    for x, y in zip(first, second, strict=True):
        np.testing.assert_array_equal(x, y)
    other, _, _ = play(env, actions, seed=6)
    assert not np.array_equal(other[0][14:47], first[0][14:47])  # another settled start
    nxt, _, info = play(env, actions)  # no seed: the lab's next trial of seed 6
    assert info["trial"] == trials + 4 and not np.array_equal(nxt[0][14:47], other[0][14:47])


def test_bad_actions_are_refused_before_anything_changes(env):
    env.reset(seed=0)
    env.step(np.zeros(7))
    session, sent = env._session, env._session.n_sent
    bad = np.zeros(7)
    bad[2] = np.nan
    with pytest.raises(ConfigError, match=r"^action: must be finite"):
        env.step(bad)
    with pytest.raises(ConfigError, match=r"^action: must have shape \(7,\), got \(6,\)$"):
        env.step(np.zeros(6))
    assert env._session is session and session.n_sent == sent and len(env._actions) == sent
    obs, *_ = env.step(np.zeros(7))  # still usable
    assert np.all(np.isfinite(obs)) and session.n_sent == sent + 1


def test_the_reward_is_the_knot_bonus_minus_the_critical_cost(monkeypatch, env):
    import flyknot_app.gym.tick_env as mod

    def score(record, target, base_offset, weights, fault_penalty):
        np.testing.assert_array_equal(base_offset, np.zeros(3))
        return np.zeros(66), 0.25, {"fault": None, "knot": "trefoil", "cost": 0.25}

    monkeypatch.setattr(mod, "score_trial", score)
    _, reward, info = play(env, [np.zeros(7)] * CMD.n, seed=0)
    assert reward == -0.25 and info["success"] is False  # the lab saw no knot
    monkeypatch.setattr(TrialRecord, "succeeded", property(lambda self: True))
    _, reward, info = play(env, [np.zeros(7)] * CMD.n, seed=0)
    assert reward == 1.0 - 0.25 and info["success"] is True


def test_gymnasiums_own_checker_passes():
    from gymnasium.utils.env_checker import check_env

    check_env(make(), skip_render_check=True)


def test_options_are_checked():
    with pytest.raises(ConfigError, match=r"^smoothing_s: must be a finite number >= 0"):
        make(smoothing_s=-1.0)
    with pytest.raises(ConfigError, match=r"^command: must be a JointCommand at 250 Hz$"):
        make(command=JointCommand(CMD.q, rate_hz=100.0))
    with pytest.raises(ConfigError, match=r"^base_offset: must be 3 finite numbers"):
        make(base_offset=np.zeros(2))
    spec = gym.spec("flyknot/FlyingKnotTick-v0")
    assert spec.entry_point == "flyknot_app.gym.tick_env:FlyknotTickEnv"


def test_the_tick_env_scores_with_the_scenarios_weights(env):
    from flyknot.errors import ConfigError
    from flyknot_app.learner_settings import scenario_weights
    from learner.inverse_qp import InverseModelWeights

    assert env._weights == scenario_weights()
    assert make(weights=InverseModelWeights())._weights == InverseModelWeights()
    with pytest.raises(ConfigError, match=r"^weights: must be an InverseModelWeights, got 0.1$"):
        make(weights=0.1)

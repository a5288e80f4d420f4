"""Tests of the hand-pace envelope the arm and a person share (hand_demos.envelope)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import ConfigError
from flyknot.limits import JointLimits
from flyknot_tools.hand_demos.envelope import (
    HAND_PACE,
    ROBOT_THROW,
    PaceEnvelope,
    arm_envelope,
    fingertip_pace,
    shared_envelope,
    time_scale_limit,
)
from learner.bezier import sample_command
from learner.kinematics import RobotModel
from learner.limit_rows import sampled_violation


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def throw() -> tuple[np.ndarray, float]:
    with np.load(ROBOT_THROW) as z:
        return np.array(z["knots"]), float(z["T"])


def _no_torque(scale: float = 0.0):
    """A stand-in robot whose torque is ``scale`` * (qd^2 + qdd) elementwise."""
    return SimpleNamespace(torques=lambda q, qd, qdd: scale * (qd**2 + qdd))


@settings(max_examples=40, deadline=None)
@given(
    vel=st.lists(st.floats(0.1, 5.0), min_size=7, max_size=7),
    acc=st.lists(st.floats(1.0, 300.0), min_size=7, max_size=7),
    margin=st.floats(0.0, 0.5),
)
def test_time_scale_without_torque_is_the_closed_form(vel, acc, margin):
    qd = np.array([vel, [-v for v in vel]])
    qdd = np.array([acc, [-a for a in acc]])
    q = np.zeros_like(qd)
    s, what = time_scale_limit(q, qd, qdd, _no_torque(), margin)
    s_v = (1 - margin) * QD_MAX / np.array(vel)
    s_a = np.sqrt((1 - margin) * QDD_MAX / np.array(acc))
    assert s == pytest.approx(min(s_v.min(), s_a.min()), rel=1e-12)
    kind, j = what.split(" J")
    expected = ("velocity", int(np.argmin(s_v))) if s_v.min() <= s_a.min() else None
    if expected is None:
        expected = ("acceleration", int(np.argmin(s_a)))
    assert (kind, int(j) - 1) == expected


def test_time_scale_bisects_a_torque_limit():
    # torque = k (qd^2 + qdd) on joint 4 only; at scale s it is k (s^2 + s^2) = 2 k s^2
    qd = np.zeros((1, 7))
    qdd = np.zeros((1, 7))
    qd[0, 3], qdd[0, 3] = 1.0, 1.0
    k = 5.0
    s, what = time_scale_limit(np.zeros((1, 7)), qd, qdd, _no_torque(k), 0.05)
    assert what == "torque J4"
    assert s == pytest.approx(math.sqrt(0.95 * TAU_MAX[3] / (2 * k)), abs=2e-4)


def test_time_scale_errors():
    q = np.zeros((2, 7))
    with pytest.raises(ConfigError) as e:
        time_scale_limit(q, q, q, _no_torque(), 1.0)
    assert str(e.value) == "margin: must lie in [0, 1), got 1.0"
    with pytest.raises(ConfigError) as e:
        time_scale_limit(q, q, q, _no_torque(), 0.05)
    assert str(e.value) == "qd: the trajectory does not move"
    heavy = SimpleNamespace(torques=lambda q, qd, qdd: np.full_like(q, 1e4))
    qd = np.ones((2, 7))
    with pytest.raises(ConfigError) as e:
        time_scale_limit(q, qd, qd, heavy, 0.05)
    assert str(e.value) == "q: gravity alone breaks a torque limit on this trajectory"


def test_fingertip_pace_matches_finite_differences(robot, throw):
    knots, T = throw
    t = np.linspace(0.0, T, 4001)
    q, qd, qdd = (sample_command(knots, T, t, k)[:, :7] for k in (0, 1, 2))
    speed, rate, accel = fingertip_pace(q, qd, qdd, robot)
    st_ = robot.tip_states(q, qd)
    dt = t[1] - t[0]
    fd_v = np.gradient(st_.p, dt, axis=0)
    fd_d = np.gradient(st_.R[:, :, 2], dt, axis=0)
    fd_a = np.gradient(st_.v, dt, axis=0)
    inner = slice(5, -5)
    np.testing.assert_allclose(speed[inner], np.linalg.norm(fd_v, axis=1)[inner], atol=2e-3)
    np.testing.assert_allclose(rate[inner], np.linalg.norm(fd_d, axis=1)[inner], atol=5e-3)
    np.testing.assert_allclose(accel[inner], np.linalg.norm(fd_a, axis=1)[inner], atol=5e-2)


def test_the_sped_up_throw_touches_the_reduced_limits(robot, throw):
    knots, T = throw
    arm = arm_envelope(robot=robot)
    assert arm.scale > 1.0  # the shipped throw does not use the arm's full pace
    reduced = JointLimits(qd_max=0.95 * QD_MAX, qdd_max=0.95 * QDD_MAX, tau_max=0.95 * TAU_MAX)
    t_fast = np.linspace(0.0, T / arm.scale, 2001)
    assert sampled_violation(knots, T / arm.scale, t_fast, robot, reduced) <= 1e-4
    t_faster = np.linspace(0.0, T / (1.01 * arm.scale), 2001)
    assert sampled_violation(knots, T / (1.01 * arm.scale), t_faster, robot, reduced) > 1e-3
    env = arm.envelope
    assert env.speed == pytest.approx(arm.scale * arm.speed)
    assert env.axis_rate == pytest.approx(arm.scale * arm.axis_rate)
    assert env.accel == pytest.approx(arm.scale**2 * arm.accel)
    # the numbers stated in docs/demo-synthesis.md
    assert (round(env.speed, 2), round(env.axis_rate, 2), round(env.accel, 1)) == (2.71, 4.91, 39.7)
    assert arm.limiting == "torque J4"


def test_shared_envelope_is_the_smaller_pace():
    arm = PaceEnvelope(2.7, 4.9, 45.0, "arm")
    env = shared_envelope(arm)
    assert (env.speed, env.axis_rate, env.accel) == (2.7, 4.9, HAND_PACE[2])
    assert shared_envelope(arm, (1.0, 50.0, 50.0)).speed == 1.0
    with pytest.raises(ConfigError) as e:
        PaceEnvelope(0.0, 1.0, 1.0)
    assert str(e.value) == "PaceEnvelope.speed: must be a number > 0, got 0.0"
    with pytest.raises(ConfigError) as e:
        shared_envelope(arm, (1.0, -1.0, 1.0))
    assert str(e.value).startswith("hand.axis_rate")


def test_arm_envelope_errors(tmp_path):
    with pytest.raises(ConfigError) as e:
        arm_envelope(tmp_path / "none.npz")
    assert str(e.value) == f"path: no command file {str(tmp_path / 'none.npz')!r}"
    bad = tmp_path / "bad.npz"
    np.savez(bad, knots=np.zeros((10, 8)))
    with pytest.raises(ConfigError) as e:
        arm_envelope(bad)
    assert str(e.value) == f"path: {str(bad)!r} needs arrays 'knots' and 'T'"


def test_a_run_s_learned_command_is_a_command_file(tmp_path):
    """A run's final_knots.npy with T from the result.json beside it (robot-rate --start)."""
    from flyknot_tools.hand_demos.envelope import load_command_file

    knots = np.arange(80.0).reshape(10, 8)
    np.save(tmp_path / "final_knots.npy", knots)
    with pytest.raises(ConfigError) as e:
        load_command_file(tmp_path / "final_knots.npy", "--start")
    assert str(e.value).startswith(
        f"--start: command file {str(tmp_path / 'final_knots.npy')!r} holds Bezier knots "
        "(10, 8): their duration T is read from result.json beside it, which is missing"
    )
    (tmp_path / "result.json").write_text('{"T": 1.044}')
    got, T = load_command_file(tmp_path / "final_knots.npy", "--start")
    assert T == 1.044 and np.array_equal(got, knots)
    np.save(tmp_path / "final_knots.npy", np.zeros((7, 8)))
    with pytest.raises(ConfigError) as e:
        load_command_file(tmp_path / "final_knots.npy", "--start")
    assert str(e.value).endswith("holds (7, 8), not Bezier knots (10, 8)")


def test_hand_pace_is_the_slowest_shipped_hand_demonstration():
    from flyknot.constants import DEMOS_DIR
    from flyknot.demo import Demonstration
    from flyknot_sim.hand_motion import KnotMotion
    from flyknot_tools.hand_demos.variants import get_variant

    peaks = []
    for name in ("fast", "slow", "swipe", "inverse"):
        motion = KnotMotion.from_dict(
            Demonstration.load(DEMOS_DIR / f"{name}.npz").metadata["motion"]
        )
        peaks.append(get_variant(name).pace(motion))
    slowest = np.min(np.array(peaks), axis=0)
    np.testing.assert_allclose(slowest, HAND_PACE, atol=0.05)

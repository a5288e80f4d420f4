"""Fault checks of a 250 Hz joint command: derivatives, torques, limits, first violation."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import Q4_MIN_NEW_SERIALS, Q_MAX, Q_MIN, QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import CommandError, ConfigError
from flyknot_sim import robot
from flyknot_sim.faults import (
    Fault,
    JointLimits,
    command_derivatives,
    command_torques,
    first_fault,
)

DT = 0.004  # 250 Hz
HOME = np.array([0, -0.247, 0, 0.909, 0, 1.15644, 0])


def rest(n: int) -> np.ndarray:
    return np.tile(HOME, (n, 1))


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return robot.load_robot_model()


# --- derivatives ---------------------------------------------------------------------

coef = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    c=st.lists(st.lists(coef, min_size=4, max_size=4), min_size=7, max_size=7),
    n=st.integers(3, 300),
    dt=st.sampled_from([0.001, 0.004, 0.01]),
)
def test_derivatives_of_a_cubic_are_exact(c, n, dt):
    # q(t) = c0 + c1 t + c2 t^2 + c3 t^3 per joint; central differences give exactly
    #   qd_i = q'(t_i) + c3 dt^2,  qdd_i = q''(t_i)  in the interior.
    c = np.array(c).T  # (4, 7)
    t = (np.arange(n) * dt)[:, None]
    q = c[0] + c[1] * t + c[2] * t**2 + c[3] * t**3
    qd, qdd = command_derivatives(q, dt)
    assert qd.shape == qdd.shape == (n, 7)
    qmax = np.abs(q).max() + 1.0  # round-off of the differences: a few eps * |q|
    tol_v, tol_a = 16 * np.finfo(float).eps * qmax / dt, 16 * np.finfo(float).eps * qmax / dt**2
    dq = c[1] + 2 * c[2] * t + 3 * c[3] * t**2 + c[3] * dt**2
    ddq = 2 * c[2] + 6 * c[3] * t
    np.testing.assert_allclose(qd[1:-1], dq[1:-1], rtol=0, atol=tol_v)
    np.testing.assert_allclose(qdd[1:-1], ddq[1:-1], rtol=0, atol=tol_a)
    # rest before q[0] and hold after q[-1]
    np.testing.assert_allclose(qd[0], (q[1] - q[0]) / (2 * dt), rtol=0, atol=tol_v)
    np.testing.assert_allclose(qdd[0], (q[1] - q[0]) / dt**2, rtol=0, atol=tol_a)
    np.testing.assert_allclose(qd[-1], (q[-1] - q[-2]) / (2 * dt), rtol=0, atol=tol_v)
    np.testing.assert_allclose(qdd[-1], (q[-2] - q[-1]) / dt**2, rtol=0, atol=tol_a)


def test_derivatives_of_a_resting_command_are_zero():
    qd, qdd = command_derivatives(rest(1), DT)
    np.testing.assert_array_equal(qd, 0.0)
    np.testing.assert_array_equal(qdd, 0.0)


@pytest.mark.parametrize(
    ("q", "message"),
    [
        (np.zeros((5, 6)), "q must have shape (n, 7) with n >= 1, got (5, 6)"),
        (np.zeros(7), "q must have shape (n, 7) with n >= 1, got (7,)"),
        (np.zeros((0, 7)), "q must have shape (n, 7) with n >= 1, got (0, 7)"),
    ],
)
def test_derivatives_reject_bad_shapes(q, message):
    with pytest.raises(CommandError) as err:
        command_derivatives(q, DT)
    assert str(err.value) == message


def test_derivatives_reject_nan_and_bad_dt():
    q = rest(4)
    q[2, 5] = np.nan
    with pytest.raises(CommandError) as err:
        command_derivatives(q, DT)
    assert str(err.value) == "q is not finite at sample 2, joint 6"
    with pytest.raises(ConfigError) as err:
        command_derivatives(rest(4), 0.0)
    assert str(err.value) == "dt: must be a finite number > 0, got 0.0"


# --- torques -------------------------------------------------------------------------


def test_torques_are_rigid_body_inverse_dynamics(model):
    # independent check: tau = (M(q) - diag(armature)) qdd + qfrc_bias(q, qd)
    rng = np.random.default_rng(11)
    q, qd, qdd = rng.uniform(-2, 2, (3, 5, 7))
    tau = command_torques(model, q, qd, 20 * qdd)
    data = mujoco.MjData(model)
    M = np.zeros((7, 7))
    for i in range(5):
        data.qpos[:], data.qvel[:] = q[i], qd[i]
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, M)
        expected = (M - np.diag(model.dof_armature)) @ (20 * qdd[i]) + data.qfrc_bias
        np.testing.assert_allclose(tau[i], expected, rtol=1e-10, atol=1e-10)


def test_torques_at_rest_hold_gravity(model):
    tau = command_torques(model, rest(2), np.zeros((2, 7)), np.zeros((2, 7)))
    # joint 1 is vertical (no gravity torque); joints 2 and 4 carry the arm at home
    assert abs(tau[0, 0]) < 1e-12
    assert 5.0 < abs(tau[0, 1]) < 20.0 and 5.0 < abs(tau[0, 3]) < 20.0
    data = mujoco.MjData(model)
    data.qpos[:] = HOME
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(tau[1], data.qfrc_bias, atol=1e-12)


def test_torques_reject_a_scene_model_and_mismatched_shapes(model):
    spec = robot.load_robot_spec()
    ball = spec.worldbody.add_body(name="ball", pos=[1, 0, 0])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02, 0, 0])
    scene = spec.compile()
    with pytest.raises(ConfigError) as err:
        command_torques(scene, rest(2), rest(2), rest(2))
    assert str(err.value) == "model: must be the robot alone (nq = nv = 7), got nq=14, nv=13"
    with pytest.raises(CommandError) as err:
        command_torques(model, rest(2), rest(3), rest(2))
    assert str(err.value) == "q, qd, qdd shapes differ: (2, 7), (3, 7), (2, 7)"


# --- limits --------------------------------------------------------------------------


def test_default_limits_are_the_papers():
    lim = JointLimits()
    for a, b in [
        (lim.q_min, Q_MIN),
        (lim.q_max, Q_MAX),
        (lim.qd_max, QD_MAX),
        (lim.qdd_max, QDD_MAX),
        (lim.tau_max, TAU_MAX),
    ]:
        np.testing.assert_array_equal(a, b)
        assert not a.flags.writeable
    assert lim == JointLimits()
    assert lim != JointLimits(qd_max=np.full(7, 2.0))


def test_stricter_takes_the_elementwise_stricter_bound():
    paper = JointLimits()
    q_min = np.array([-6.28319, -2.059, -6.28319, Q4_MIN_NEW_SERIALS, -6.28319, -1.69297, -6.28319])
    q_max = np.array([6.28319, 2.0944, 6.28319, 3.927, 6.28319, 3.14159, 6.28319])
    arm = JointLimits(
        q_min=q_min,
        q_max=q_max,
        qd_max=np.full(7, 3.14),
        qdd_max=np.array([200, 200, 200, 200, 50, 200, 200.0]),
        tau_max=np.array([50, 50, 30, 30, 30, 20, 20.0]),
    )
    s = JointLimits.stricter(paper, arm)
    assert s == JointLimits.stricter(arm, paper)
    np.testing.assert_array_equal(s.q_min, [-6.28, -1.8, -6.28, -0.1047, -6.28, -1.69, -6.28])
    np.testing.assert_array_equal(s.q_max, [6.28, 1.9, 6.28, 3.92, 6.28, 3.14, 6.28])
    np.testing.assert_array_equal(s.qdd_max, [100, 100, 100, 100, 50, 100, 100])
    np.testing.assert_array_equal(s.tau_max, [50, 50, 30, 30, 30, 20, 20])
    np.testing.assert_array_equal(s.qd_max, 3.14)


def test_stricter_of_disjoint_ranges_is_an_error():
    a = JointLimits(q_min=np.full(7, -1.0), q_max=np.full(7, 0.0))
    b = JointLimits(q_min=np.full(7, 0.5), q_max=np.full(7, 1.0))
    with pytest.raises(ConfigError) as err:
        JointLimits.stricter(a, b)
    assert str(err.value) == "limits.q_min: must be < limits.q_max; joint 1 has 0.5 >= 0.0"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"q_min": np.zeros(6)}, "limits.q_min: must have shape (7,), got (6,)"),
        ({"qd_max": [1, 1, 1, 0, 1, 1, 1]}, "limits.qd_max: must be > 0; joint 4 is 0.0"),
        ({"tau_max": [1, 1, 1, 1, 1, 1, -2]}, "limits.tau_max: must be > 0; joint 7 is -2.0"),
        ({"qdd_max": [1, np.inf, 1, 1, 1, 1, 1]}, "limits.qdd_max: must be finite; joint 2 is inf"),
        (
            {"q_max": [6.28, 1.9, 6.28, -0.19, 6.28, 3.14, 6.28]},
            "limits.q_min: must be < limits.q_max; joint 4 has -0.19 >= -0.19",
        ),
    ],
)
def test_limit_validation_messages(kwargs, message):
    with pytest.raises(ConfigError) as err:
        JointLimits(**kwargs)
    assert str(err.value) == message


# --- first fault ---------------------------------------------------------------------


def smooth_move(n: int, joint: int, start: float, stop: float) -> np.ndarray:
    """Home, with one joint moved by a quintic from start to stop over n samples [rad]."""
    q = rest(n)
    x = np.linspace(0.0, 1.0, n)
    q[:, joint] = start + (stop - start) * (10 * x**3 - 15 * x**4 + 6 * x**5)
    return q


def test_a_command_inside_the_limits_has_no_fault(model):
    q = smooth_move(250, 1, -0.247, 0.3)  # joint 2, 1 s: 1.0 rad/s, 3.2 rad/s^2 peaks
    qd, qdd = command_derivatives(q, DT)
    tau = command_torques(model, q, qd, qdd)
    assert first_fault(q, DT, torques=tau) is None
    assert first_fault(rest(3), DT) is None


def test_position_fault_at_the_first_sample_past_the_limit():
    q = smooth_move(250, 1, -1.7, -1.95)  # joint 2 below the paper's -1.8
    tick = int(np.flatnonzero(q[:, 1] < -1.8)[0])
    f = first_fault(q, DT)
    assert f == Fault(tick, tick * DT, 2, "position", q[tick, 1], -1.8)
    value = f"{q[tick, 1]:.4f}".rstrip("0")
    assert f.reason == f"joint 2 position {value} rad exceeds limit -1.8 rad at t={tick * DT:.3f} s"
    # the same move is legal for an arm whose range is wider
    assert first_fault(q, DT, limits=JointLimits(q_min=np.full(7, -2.0))) is None


def test_velocity_fault_on_a_constant_acceleration_ramp():
    # joint 3 at 50 rad/s^2 from rest: qd_i = 50 * i * dt exactly (central differences of a
    # parabola), so |qd| first exceeds 3.14 at i = 16 (3.2 rad/s); qdd = 50 stays legal.
    q = rest(30)
    i = np.arange(30)
    q[:, 2] = 0.5 * 50.0 * (i * DT) ** 2
    f = first_fault(q, DT)
    assert (f.tick, f.joint, f.quantity, f.limit) == (16, 3, "velocity", 3.14)
    assert f.value == pytest.approx(3.2, abs=1e-12)
    assert f.reason == "joint 3 velocity 3.2 rad/s exceeds limit 3.14 rad/s at t=0.064 s"
    # negative direction: the crossed bound is -3.14
    q[:, 2] *= -1
    f = first_fault(q, DT)
    assert (f.tick, f.value, f.limit) == (16, pytest.approx(-3.2, abs=1e-12), -3.14)
    assert f.reason == "joint 3 velocity -3.2 rad/s exceeds limit -3.14 rad/s at t=0.064 s"


def test_acceleration_fault_when_a_parabola_starts():
    # joint 5 rests until sample 40, then q = 75 (t - t_40)^2: qdd_40 = 75 (half a step of the
    # 150 rad/s^2 parabola), qdd_41 = 150 > 100.
    q = rest(60)
    k = np.arange(60) - 40
    q[:, 4] = np.where(k > 0, 75.0 * (k * DT) ** 2, 0.0)
    f = first_fault(q, DT)
    assert (f.tick, f.joint, f.quantity, f.limit) == (41, 5, "acceleration", 100.0)
    assert f.value == pytest.approx(150.0, rel=1e-9)
    assert f.reason == "joint 5 acceleration 150 rad/s^2 exceeds limit 100 rad/s^2 at t=0.164 s"


def test_torque_fault_from_given_torques():
    q = rest(80)
    tau = np.zeros((80, 7))
    tau[40, 5] = -25.0
    tau[60, 0] = 131.0
    f = first_fault(q, DT, torques=tau)
    assert f == Fault(40, 0.16, 6, "torque", -25.0, -20.0)
    assert f.reason == "joint 6 torque -25 N m exceeds limit -20 N m at t=0.160 s"
    assert first_fault(q, DT) is None  # torque not checked without torques


def test_torque_fault_of_a_fast_elbow_move(model):
    # joint 4 from home by 0.17 rad in 0.104 s: 3.05 rad/s and 90 rad/s^2 peaks are legal, but
    # ~0.45 kg m^2 x 90 rad/s^2 plus gravity exceeds joint 4's 40 N m.
    q = smooth_move(27, 3, HOME[3], HOME[3] + 0.17)
    qd, qdd = command_derivatives(q, DT)
    assert np.abs(qd).max() < 3.14 and np.abs(qdd).max() < 100
    tau = command_torques(model, q, qd, qdd)
    f = first_fault(q, DT, torques=tau)
    assert (f.joint, f.quantity, f.limit) == (4, "torque", 40.0)
    assert f.tick == int(np.flatnonzero(np.abs(tau[:, 3]) > 40)[0])
    assert first_fault(q, DT, torques=tau, limits=JointLimits(tau_max=np.full(7, 60.0))) is None


def test_ties_follow_position_velocity_acceleration_torque_then_joint():
    q = rest(10)
    q[1:, 2] += 0.1  # jump on joint 3: velocity and acceleration fault at tick 0
    tau = np.zeros((10, 7))
    tau[0, 0] = 200.0
    assert first_fault(q, DT, torques=tau).quantity == "velocity"
    q[:, 6] = 7.0  # joint 7 out of range from tick 0 on: position wins the tie
    assert first_fault(q, DT, torques=tau).quantity == "position"
    assert first_fault(q, DT, torques=tau).joint == 7
    q = rest(10)
    q[0, 1] += 1e-3  # joint 2: qd_0 = -0.125, qdd_0 = -62.5, qdd_1 = 62.5, all legal
    q[1:, 0] += 2e-3  # joint 1: qdd_0 = 125 > 100
    q[1:, 3] += 2e-3  # joint 4 as well: the lower joint wins
    f = first_fault(q, DT, torques=tau)
    assert (f.tick, f.joint, f.quantity) == (0, 1, "acceleration")
    q = rest(10)
    assert first_fault(q, DT, torques=tau) == Fault(0, 0.0, 1, "torque", 200.0, 130.0)


def test_first_fault_rejects_bad_torques_and_fault_fields():
    with pytest.raises(CommandError) as err:
        first_fault(rest(5), DT, torques=np.zeros((4, 7)))
    assert str(err.value) == "torques must have the shape of q (5, 7), got (4, 7)"
    with pytest.raises(ConfigError) as err:
        Fault(0, 0.0, 8, "torque", 1.0, 1.0)
    assert str(err.value) == ("fault.joint: unknown value 8 (valid choices: 1, 2, 3, 4, 5, 6, 7)")
    with pytest.raises(ConfigError) as err:
        Fault(0, 0.0, 1, "jerk", 1.0, 1.0)
    assert str(err.value) == (
        "fault.quantity: unknown value 'jerk' "
        "(valid choices: position, velocity, acceleration, torque)"
    )

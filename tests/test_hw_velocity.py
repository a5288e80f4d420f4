"""Velocity streaming (mode 4) for throws faster than servo mode's TCP limit (C60).

The math of :class:`flyknot_hw.velocity_stream.VelocityStream`, the lab file's ``robot.stream``,
the preflight that checks C60's speed only in servo mode, and a fast throw through the real SDK
against our fake controller with C60 modelled: refused by the firmware in servo mode, played
in velocity mode.
"""

from __future__ import annotations

import numpy as np
import pytest
from fakes import SimFingertip, StandInMocap, lab_doc
from fakes.fake_xarm import HOME
from hypothesis import given, settings
from hypothesis import strategies as st
from test_hw_xarm import cells, make_fake, throw  # noqa: F401 - fixtures

from flyknot.errors import CommandError, ConfigError
from flyknot.record import JointCommand
from flyknot_hw.config import parse_lab_config
from flyknot_hw.preflight import PreflightError
from flyknot_hw.velocity_stream import VelocityStream
from flyknot_hw.xarm_cell import XArmCell
from tests.knot_curves import verdict

DT = 0.004
FAST = dict(n=250, amp=0.6)  # fingertip 1.97 m/s, flange ~1.65 m/s: above C60's 1.2 m/s


# --- the velocities --------------------------------------------------------------------------
@given(st.integers(0, 10_000), st.integers(2, 60))
@settings(max_examples=30, deadline=None)
def test_feed_forward_alone_passes_through_every_sample(seed, n):
    q = np.random.default_rng(seed).normal(size=(n, 7))
    vs = VelocityStream(q, DT, gain=0.0)
    x = q[0].copy()
    for i in range(n - 1):
        x = x + vs.at(i, None) * DT  # the controller integrating each velocity for a tick
        np.testing.assert_allclose(x, q[i + 1], atol=1e-9)
    np.testing.assert_array_equal(vs.at(n - 1, None), np.zeros(7))


def test_the_position_term_pulls_towards_the_previous_sample_and_is_clipped():
    q = np.outer(np.arange(5), np.full(7, 0.01))  # 2.5 rad/s on every joint
    vs = VelocityStream(q, DT, gain=10.0, qd_max=np.full(7, 3.0))
    behind = q[1] - 0.02  # measured 0.02 rad behind the previous sample at tick 2
    np.testing.assert_allclose(vs.at(2, behind), np.full(7, 2.5 + 10.0 * 0.02))
    np.testing.assert_allclose(vs.at(2, q[1]), np.full(7, 2.5))  # on track: feed-forward
    np.testing.assert_allclose(vs.at(2, q[1] - 0.5), np.full(7, 3.0))  # clipped to qd_max
    nan = np.full(7, np.nan)
    np.testing.assert_allclose(vs.at(0, nan), np.full(7, 2.5))  # no measurement: ignored


def test_bad_inputs_name_what_is_wrong():
    with pytest.raises(CommandError) as e:
        VelocityStream(np.zeros((1, 7)), DT, 1.0)
    assert str(e.value) == "q must be a finite (n >= 2, 7) array, got shape (1, 7)"
    with pytest.raises(ConfigError, match=r"^gain: "):
        VelocityStream(np.zeros((3, 7)), DT, -1.0)
    with pytest.raises(CommandError) as e:
        VelocityStream(np.zeros((3, 7)), DT, 1.0).at(3, None)
    assert str(e.value) == "tick 3 outside the command's 0..2"


# --- the lab file ----------------------------------------------------------------------------
def test_lab_file_stream_and_gain_are_validated():
    doc = {"robot": {"address": "192.168.1.185", "stream": "torque"}}
    base = {
        "mocap": {"kind": "file", "system": "c3d", "file": "x_*.c3d"},
        "rope": {"id": 1},
        "base": {"pose": [0, 0, 0, 1, 0, 0, 0]},
        "safety": {"margin": 0.05, "workspace": {"min": [-1, -1, 0], "max": [1, 1, 2]}},
        "settle": {"mode": "seconds"},
    }
    with pytest.raises(ConfigError) as e:
        parse_lab_config({**base, **doc})
    assert str(e.value) == ("robot.stream: unknown value 'torque' (valid choices: servo, velocity)")
    doc["robot"].update(stream="velocity", velocity_gain=80.0)
    with pytest.raises(ConfigError) as e:
        parse_lab_config({**base, **doc})
    assert str(e.value).startswith("robot.velocity_gain: must be at most 50 1/s")
    doc["robot"]["velocity_gain"] = 5.0
    robot = parse_lab_config({**base, **doc}).robot
    assert (robot.stream, robot.velocity_gain) == ("velocity", 5.0)


# --- through the SDK, against the fake controller with C60 modelled ---------------------------
def _cell(fake, stream: str, **kw) -> XArmCell:
    doc = lab_doc(fake, robot={"stream": stream}, safety={"tip_speed_max": 1.2})
    return XArmCell(
        parse_lab_config(doc), fingertip=SimFingertip(), judge=lambda r: verdict("knot"),
        mocap=StandInMocap(fake), **kw,
    )  # fmt: skip


def test_servo_mode_preflight_refuses_a_fast_throw_that_velocity_mode_accepts(make_fake):  # noqa: F811
    fk = make_fake(servo_tcp_speed_max=1.2)
    command = JointCommand(throw(**FAST))
    with _cell(fk, "servo") as cell, pytest.raises(PreflightError, match="fingertip speed"):
        cell.preflight(command)
    with _cell(fk, "velocity") as cell:
        report = cell.preflight(command)
    assert report.tip_speed_peak > 1.9  # measured, but not a limit in velocity mode


def test_the_fake_firmware_faults_c60_on_a_fast_servo_stream(make_fake):  # noqa: F811
    fk = make_fake(servo_tcp_speed_max=1.2)
    doc = lab_doc(fk)  # tip_speed_max 4.0: the preflight lets it through, the firmware not
    with XArmCell(
        parse_lab_config(doc), fingertip=SimFingertip(), judge=lambda r: verdict("knot"),
        mocap=StandInMocap(fk),
    ) as cell:  # fmt: skip
        rec = cell.run(JointCommand(throw(**FAST)))
    assert rec.fault is not None and "C60" in rec.fault
    assert rec.metadata["controller"]["code"] == 60
    assert any(name == "error" and v == 60 for _, name, v in fk.events)


def test_velocity_mode_plays_the_fast_throw_through_the_sdk(make_fake):  # noqa: F811
    fk = make_fake(servo_tcp_speed_max=1.2)
    q = throw(**FAST)
    with _cell(fk, "velocity") as cell:
        rec = cell.run(JointCommand(q))
    assert rec.fault is None and rec.knot == "trefoil"
    modes = [v for _, name, v in fk.events if name == "set_mode"]
    assert modes == [0, 4, 0]  # start move in position mode, the throw in mode 4, back
    vel = [v for _, name, v in fk.events if name == "velocity"]
    assert len(vel) == 251  # one per tick, then a zero velocity
    np.testing.assert_array_equal(vel[-1], np.zeros(7))
    assert not fk.servo  # no servo_j at all
    # the measured joints follow the command (the simulated servos' lag, as in servo mode)
    err = np.max(np.abs(rec.q_meas[:250] - q), axis=1)
    assert np.all(np.isfinite(rec.q_meas)) and err.max() < 0.05
    np.testing.assert_allclose(rec.q_meas[-1], q[-1], atol=0.01)
    assert not any(name == "error" for _, name, _ in fk.events)


def test_a_velocity_above_the_joint_limit_is_a_c24_fault(make_fake):  # noqa: F811
    from xarm.wrapper import XArmAPI

    fk = make_fake(arm="exact", q0=HOME)
    api = XArmAPI(fk.host, is_radian=True, do_not_open=False)
    try:
        api.motion_enable(True)
        api.set_mode(4)
        api.set_state(0)
        assert fk.wait_for(lambda: fk.mode == 4)
        api.vc_set_joint_velocity([4.0, 0, 0, 0, 0, 0, 0], is_radian=True)
        assert fk.wait_for(lambda: fk.error_code == 24)
    finally:
        api.disconnect()

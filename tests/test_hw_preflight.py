"""Preflight: a whole command against the stricter of the paper's and the robot's limits."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from flyknot.constants import Q4_MIN_NEW_SERIALS, Q_MAX, Q_MIN, QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import CommandError, ConfigError, FlyknotError, HardwareError
from flyknot.limits import JointLimits, difference_matrices
from flyknot.record import JointCommand
from flyknot_hw.config import Margins, Workspace
from flyknot_hw.preflight import (
    PreflightError,
    check_pose,
    command_derivatives,
    effective_limits,
    preflight,
    published_robot_limits,
)
from flyknot_sim import faults

LIM = effective_limits()
MID = 0.5 * (LIM.q_min + LIM.q_max)
RATE = 250.0


def smooth(n: int = 500, amp=0.5, freq=0.5, joints=(1, 3)) -> np.ndarray:
    """A command at rest at both ends: q = mid + amp (1 - cos(2 pi f t)) on ``joints``."""
    t = np.arange(n) / RATE
    q = np.tile(MID, (n, 1))
    for j in joints:
        q[:, j] += amp * (1 - np.cos(2 * np.pi * freq * t)) / 2
    return q


def test_smooth_command_passes_with_its_peak_use():
    q = smooth()
    report = preflight(JointCommand(q), LIM)
    assert report.checked == ("position", "velocity", "acceleration")
    qd, qdd = command_derivatives(q, 1 / RATE)
    np.testing.assert_allclose(report.peak_use["velocity"], np.abs(qd).max(0) / LIM.qd_max)
    np.testing.assert_allclose(report.peak_use["acceleration"], np.abs(qdd).max(0) / LIM.qdd_max)
    half = 0.5 * (LIM.q_max - LIM.q_min)
    np.testing.assert_allclose(report.peak_use["position"], np.abs(q - MID).max(0) / half)
    assert report.allowed["velocity"] == pytest.approx(0.95)
    assert report.worst()[0] in report.checked
    json.dumps(report.as_metadata())  # plain data for a record


def test_effective_limits_are_the_stricter():
    lim = effective_limits()
    assert lim.q_min[3] == pytest.approx(Q4_MIN_NEW_SERIALS)  # newer serials' joint 4
    assert lim.q_min[1] == Q_MIN[1] and lim.q_max[1] == Q_MAX[1]  # the paper's joint 2
    np.testing.assert_array_equal(lim.tau_max, TAU_MAX)
    np.testing.assert_array_equal(lim.qd_max, np.minimum(QD_MAX, math.pi))
    old = effective_limits(published_robot_limits(newer_serial=False))
    assert old.q_min[3] == pytest.approx(max(Q_MIN[3], -0.19198))
    np.testing.assert_array_equal(published_robot_limits().qdd_max, QDD_MAX)


def _fmt(x: float) -> str:
    return f"{x:.4f}".rstrip("0").rstrip(".")


def _towards(j: int, target: float, n: int = 500) -> np.ndarray:
    """From rest at the middle, smoothly (1 - cos) to ``target`` on joint j over n samples."""
    q = np.tile(MID, (n, 1))
    s = (1 - np.cos(np.pi * np.arange(n) / (n - 1))) / 2
    q[:, j] = MID[j] + (target - MID[j]) * s
    return q


def _step(j: int, size: float, at: int, n: int = 500) -> np.ndarray:
    q = np.tile(MID, (n, 1))
    q[at:, j] += size
    return q


@pytest.mark.parametrize(
    ("q", "quantity", "joint", "sample"),
    [
        (_towards(1, 1.87), "position", 2, None),  # paper's joint 2 max 1.9, 95 %: 1.8075
        (smooth(amp=2.0, freq=0.5, joints=(3,)), "velocity", 4, None),  # peak pi > 2.983
        (_step(6, 0.01, 200), "acceleration", 7, 199),  # 625 rad/s^2 where the step shows
    ],
)
def test_violation_names_joint_sample_time_value_limit(q, quantity, joint, sample):
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q), LIM)
    err = e.value
    msg = str(err)
    assert (err.quantity, err.joint) == (quantity, joint), msg
    if sample is not None:
        assert err.sample == sample
    assert f"joint {joint} {quantity} {_fmt(err.value)}" in msg
    assert f"{_fmt(err.limit)} " in msg and f"the limit {_fmt(err.raw_limit)} " in msg
    assert f"at sample {err.sample} (t = {err.sample / RATE:.3f} s)" in msg
    assert "nothing was sent to the robot" in msg
    assert isinstance(err, HardwareError) and isinstance(err, FlyknotError)
    assert abs(err.value) > abs(err.limit) or quantity == "position"
    if quantity == "position":  # the first sample past 95 % of the half-range
        c, h = MID[1], 0.5 * (LIM.q_max[1] - LIM.q_min[1])
        use = np.abs(q[:, 1] - c) / h
        assert err.sample == int(np.flatnonzero(use > 0.95)[0])


def test_position_limit_is_reported_with_its_margin():
    q = _towards(1, LIM.q_max[1] - 0.01)  # inside the raw limit, outside the 5 % margin
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q), LIM)
    c, h = MID[1], 0.5 * (LIM.q_max[1] - LIM.q_min[1])
    assert (e.value.joint, e.value.quantity) == (2, "position")
    assert e.value.limit == pytest.approx(c + 0.95 * h)
    assert e.value.raw_limit == pytest.approx(LIM.q_max[1])
    preflight(JointCommand(q), LIM, margins=Margins(0.0, 0.05, 0.05, 0.05))  # passes at 0 %


def test_torque_and_workspace_checks():
    q = smooth()
    n = q.shape[0]
    tau = np.zeros((n, 7))
    tau[250, 5] = -19.5  # joint 6 limit 20 N m: 97.5 % > 95 %
    with pytest.raises(PreflightError, match=r"joint 6 torque -19\.5 N m is below -19 N m"):
        preflight(JointCommand(q), LIM, torques=tau)
    rep = preflight(JointCommand(q), LIM, torques=tau * 0.9)
    assert rep.peak_use["torque"][5] == pytest.approx(0.8775)
    ws = Workspace([-0.5, -0.5, 0.1], [0.5, 0.5, 1.0])
    line = np.tile([-0.2, 0.0, 0.5], (n, 1))
    line[:, 0] += 0.0008 * np.arange(n)  # 0.2 m/s along x
    rep = preflight(JointCommand(q), LIM, fingertip=line, workspace=ws)
    assert rep.tip_speed_peak == pytest.approx(0.2)
    assert rep.peak_use["workspace"][0] == pytest.approx(0.4)  # |x| <= 0.2 in [-0.5, 0.5]
    tip = np.tile([0.2, 0.0, 0.5], (n, 1))
    tip[400:, 1] = 0.6
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q), LIM, fingertip=tip, workspace=ws)
    assert e.value.quantity == "workspace" and e.value.axis == "y" and e.value.sample == 400
    assert "fingertip y = 0.6 m leaves the workspace box" in str(e.value)
    assert "safety.workspace.max y = 0.5 m" in str(e.value)


def test_earliest_sample_wins_then_quantity_order():
    q = smooth()
    tau = np.zeros_like(q)
    tau[10, 0] = 500.0
    q2 = q.copy()
    q2[50:, 0] = MID[0] + 6.2  # out of range from sample 50; the speed shows at 49
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q2), LIM, torques=tau)
    assert (e.value.quantity, e.value.sample) == ("torque", 10)
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q2), LIM)
    assert (e.value.quantity, e.value.sample) == ("velocity", 49)
    q3 = np.tile(MID, (100, 1))
    q3[:, 0] = MID[0] + 6.2  # out of range from the start, and a speed jump at sample 60
    q3[60:, 2] += 1.0
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q3), LIM, torques=np.zeros_like(q3) + 1e3)
    assert (e.value.quantity, e.value.sample, e.value.joint) == ("position", 0, 1)


def test_bad_inputs():
    q = smooth()
    with pytest.raises(CommandError, match=r"torques must have shape \(500, 7\)"):
        preflight(JointCommand(q), LIM, torques=np.zeros((10, 7)))
    with pytest.raises(CommandError, match="fingertip is not finite at sample 3"):
        tip = np.zeros((500, 3))
        tip[3, 1] = np.nan
        preflight(JointCommand(q), LIM, fingertip=tip, workspace=Workspace([-1] * 3, [1] * 3))
    with pytest.raises(ConfigError, match="workspace"):
        preflight(JointCommand(q), LIM, fingertip=np.zeros((500, 3)))
    with pytest.raises(CommandError):
        preflight(q, LIM)  # type: ignore[arg-type]


def test_check_pose():
    check_pose(MID, LIM)
    q = MID.copy()
    q[3] = -0.1
    with pytest.raises(PreflightError, match=r"current pose: joint 4 position -0\.1 rad is below"):
        check_pose(q, LIM, what="current pose")


# --- properties --------------------------------------------------------------------------
@st.composite
def commands(draw, n_max: int = 120):
    """A random command: knots (k, 7) inside the limits, linearly interpolated to n samples."""
    n = draw(st.integers(3, n_max))
    k = draw(st.integers(2, 6))
    u = draw(st.lists(st.floats(-1.0, 1.0), min_size=k * 7, max_size=k * 7))
    span = draw(st.floats(0.001, 1.5))
    knots = MID + span * np.array(u).reshape(k, 7) * 0.5 * (LIM.q_max - LIM.q_min)
    s = np.linspace(0, k - 1, n)
    q = np.stack([np.interp(s, np.arange(k), knots[:, j]) for j in range(7)], 1)
    return q


@given(commands())
def test_derivatives_are_the_simulated_controllers_and_the_learners(q):
    assert command_derivatives is faults.command_derivatives  # one rule for both cells
    qd, qdd = command_derivatives(q, 1 / RATE)
    d1, d2 = difference_matrices(len(q), 1 / RATE)  # what the learner bounds
    np.testing.assert_allclose(d1 @ q, qd, rtol=0, atol=1e-9 * max(1.0, np.abs(qd).max()))
    np.testing.assert_allclose(d2 @ q, qdd, rtol=0, atol=1e-9 * max(1.0, np.abs(qdd).max()))


def _margined(lim: JointLimits, m: float) -> JointLimits:
    c, h = 0.5 * (lim.q_min + lim.q_max), 0.5 * (lim.q_max - lim.q_min)
    return JointLimits(
        c - (1 - m) * h, c + (1 - m) * h, (1 - m) * lim.qd_max, (1 - m) * lim.qdd_max,
        (1 - m) * lim.tau_max,
    )  # fmt: skip


@given(commands(), st.floats(0.0, 0.5))
def test_passes_exactly_when_the_simulated_controller_would_not_fault(q, m):
    """Preflight with margin m == the sim's fault check on limits shrunk by m."""
    margins = Margins(m, m, m, m)
    shrunk = _margined(LIM, m)
    qd, qdd = command_derivatives(q, 1 / RATE)
    c, h = MID, 0.5 * (LIM.q_max - LIM.q_min)
    uses = [np.abs(q - c) / h, np.abs(qd) / LIM.qd_max, np.abs(qdd) / LIM.qdd_max]
    assume(all(np.min(np.abs(u - (1 - m))) > 1e-9 for u in uses))  # no ties at the bound
    fault = faults.first_fault(q, 1 / RATE, limits=shrunk)
    try:
        report = preflight(JointCommand(q), LIM, margins=margins)
    except PreflightError as e:
        assert fault is not None
        assert (e.sample, e.joint, e.quantity) == (fault.tick, fault.joint, fault.quantity)
    else:
        assert fault is None
        for name in ("position", "velocity", "acceleration"):
            assert np.all(report.peak_use[name] <= 1 - m)


@given(commands(), st.floats(0.05, 1.6))
def test_scaling_a_command_moves_its_use_proportionally(q, f):
    """Scaling the motion about its start by f scales speed and acceleration use by f."""
    base = preflight(JointCommand(q), LIM, margins=Margins(0, 0, 0, 0)) if _ok(q) else None
    assume(base is not None)
    q_f = q[0] + f * (q - q[0])
    assume(_ok(q_f, position_only=True))
    expected = f * base.peak_use["velocity"]
    try:
        rep = preflight(JointCommand(q_f), LIM, margins=Margins(0, 0, 0, 0))
    except PreflightError as e:
        assert e.quantity in ("velocity", "acceleration")
        assert max(expected.max(), f * base.peak_use["acceleration"].max()) > 1 - 1e-9
    else:
        np.testing.assert_allclose(rep.peak_use["velocity"], expected, atol=1e-12)


def _ok(q, position_only: bool = False) -> bool:
    try:
        if position_only:
            check_pose(q.min(0), LIM, Margins(0, 0, 0, 0))
            check_pose(q.max(0), LIM, Margins(0, 0, 0, 0))
        else:
            preflight(JointCommand(q), LIM, margins=Margins(0, 0, 0, 0))
    except PreflightError:
        return False
    return True


@given(st.integers(0, 99), st.integers(0, 6), st.sampled_from([-1.0, 1.0]))
def test_an_injected_violation_is_found_where_it_is(i, j, sign):
    """A single out-of-range sample is reported at its sample and joint (or the one before,
    where its speed already shows)."""
    q = np.tile(MID, (100, 1))
    q[i, j] = MID[j] + sign * 0.999 * 0.5 * (LIM.q_max[j] - LIM.q_min[j])
    with pytest.raises(PreflightError) as e:
        preflight(JointCommand(q), LIM)
    assert e.value.joint == j + 1
    assert e.value.sample in (max(i - 1, 0), i)
    assert f"joint {j + 1} " in str(e.value) and f"sample {e.value.sample} " in str(e.value)


def test_the_fingertip_speed_limit_c60_refuses_a_fast_throw():
    n = 100
    q = np.tile(np.array([0.0, -0.2, 0.0, 0.9, 0.0, 1.1, 0.0]), (n, 1))
    cmd = JointCommand(q=q, rate_hz=250.0)
    tip = np.zeros((n, 3))
    tip[:, 0] = 0.3 + np.clip(np.arange(n) - 50, 0, None) * (2.0 / 250.0)  # 2 m/s from 50
    box = Workspace([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    limits = effective_limits()
    with pytest.raises(PreflightError) as e:
        preflight(cmd, limits, fingertip=tip, workspace=box, tip_speed_max=1.2)
    assert e.value.quantity == "tip_speed" and e.value.sample == 51
    assert str(e.value) == (
        "command: fingertip speed 2 m/s exceeds 1.14 m/s (safety.tip_speed_max 1.2 m/s, the "
        "controller's servo-mode TCP speed limit (C60), with the safety margin) at sample 51 "
        '(t = 0.204 s); streaming joint velocities instead (robot.stream = "velocity") has '
        "no such limit; nothing was sent to the robot"
    )
    report = preflight(cmd, limits, fingertip=tip, workspace=box, tip_speed_max=2.5)
    assert report.tip_speed_peak == pytest.approx(2.0)
    assert "tip_speed" in report.checked

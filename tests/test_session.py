"""Tick-by-tick trials: the online fault check, the session's records and observations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flyknot.errors import CommandError
from flyknot.record import JointCommand
from flyknot_sim import robot
from flyknot_sim.commands import HOME_Q, SWING_AMPLITUDE, swing_command
from flyknot_sim.faults import (
    StreamCheck,
    command_derivatives,
    command_torques,
    first_fault,
)
from flyknot_sim.lab import LabParams, SimLab

DT = 0.004


@pytest.fixture(scope="module")
def model():
    return robot.load_robot_model()


def _stream(q, model=None):
    """Push every sample, then close; (the first fault, the sample count when it was seen)."""
    check = StreamCheck(q[0], DT, torque_model=model)
    for i, row in enumerate(q):
        fault = check.push(row)
        if fault is not None:
            return fault, i + 1
    return check.close(), len(q)


def _ramp_then_stop(v: float = 0.48, a: float = 80.0, n: int = 60) -> np.ndarray:
    """Joint 2 accelerates at ``a`` up to ``v`` and stops dead at the last sample."""
    vel = np.minimum(a * DT * np.arange(n), v)
    q = np.repeat(HOME_Q[None], n, axis=0)
    q[:, 1] += np.cumsum(vel) * DT
    return q


def _random_commands(n_cmd: int = 60, seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(n_cmd):
        n = int(rng.integers(2, 40))
        steps = rng.normal(0.0, rng.choice([0.001, 0.004, 0.012]), (n, 7))
        steps[:, rng.integers(0, 7)] *= rng.choice([1.0, 3.0])
        yield HOME_Q + np.cumsum(steps, axis=0)


@pytest.mark.parametrize("torques", [False, True])
def test_the_online_check_finds_what_the_whole_command_check_finds(model, torques):
    cases = [*_random_commands(), _ramp_then_stop(), swing_command(amplitude=np.full(7, 3.0)).q]
    kinds = set()
    for q in cases:
        tau = None
        if torques:
            tau = command_torques(model, q, *command_derivatives(q, DT))
        want = first_fault(q, DT, torques=tau)
        got, seen = _stream(q, model if torques else None)
        assert got == want
        if want is not None:
            kinds.add(want.quantity)
            # Known as soon as the controller can know it: a position at its sample, the
            # derivatives one sample later (the last sample's when the stream ends).
            expected = want.tick + (want.quantity != "position")
            assert seen == min(expected + 1, len(q))
    assert {"velocity", "acceleration"} <= kinds
    if torques:
        assert "torque" in kinds


def test_a_fault_on_the_last_sample_is_found_when_the_stream_ends():
    q = _ramp_then_stop()
    want = first_fault(q, DT)
    assert want.tick == len(q) - 1 and want.quantity == "acceleration"
    check = StreamCheck(q[0], DT)
    assert all(check.push(row) is None for row in q)
    assert check.close() == want
    assert check.close() is None  # closed once
    with pytest.raises(CommandError, match="faulted at sample 59"):
        check.push(q[-1])


def test_the_start_pose_is_the_sample_before_the_first():
    q0 = HOME_Q.copy()
    check = StreamCheck(q0, DT)
    assert check.push(q0 + 0.02) is None  # a jump from rest shows when the next arrives
    fault = check.push(q0 + 0.02)
    assert (fault.tick, fault.joint, fault.quantity) == (0, 1, "acceleration")
    assert fault.value == pytest.approx(-0.02 / DT**2)
    still = StreamCheck(q0 + 0.02, DT)  # from rest at the first sample: no jump
    assert still.push(q0 + 0.02) is None and still.push(q0 + 0.02) is None


def test_bad_samples_are_refused_before_anything_changes():
    check = StreamCheck(HOME_Q, DT)
    check.push(HOME_Q)
    with pytest.raises(CommandError, match=r"^sample must have shape \(7,\), got \(6,\)$"):
        check.push(HOME_Q[:6])
    with pytest.raises(CommandError, match=r"^sample is not finite at joint 3$"):
        check.push(np.where(np.arange(7) == 2, np.nan, HOME_Q))
    assert check.n == 1 and check.push(HOME_Q) is None


# --- the session -------------------------------------------------------------------------
PARAMS = LabParams(rope=1, seed=2, settle_s=0.1)


def _fields(rec):
    return {f.name: getattr(rec, f.name) for f in dataclasses.fields(rec)}


def _assert_identical(a, b, path="record"):
    if isinstance(a, dict):
        assert set(a) == set(b), path
        for k in a:
            _assert_identical(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.tobytes() == b.tobytes(), path
    else:
        assert a == b, path


@pytest.fixture(scope="module")
def streamed():
    """A short swing streamed tick by tick, and the record ``run`` gives for it."""
    cmd = swing_command(duration=0.4, amplitude=0.3 * SWING_AMPLITUDE)
    lab = SimLab(PARAMS)
    session = lab.start(cmd.q[0])
    first = session.observe()
    obs = [session.tick(row) for row in cmd.q]
    rec = session.finish()
    ref = SimLab(PARAMS).run(cmd)
    return cmd, first, obs, rec, ref


def test_a_streamed_command_gives_the_record_run_gives(streamed):
    _, _, _, rec, ref = streamed
    assert rec.fault is None and rec.knot is not None
    _assert_identical(_fields(rec), _fields(ref))


def test_observations_are_what_the_record_measured(streamed):
    cmd, first, obs, rec, _ = streamed
    assert first.tick == 0 and first.t == 0.0 and first.fault is None
    np.testing.assert_array_equal(first.q, rec.q_meas[0])
    np.testing.assert_allclose(first.q, cmd.q[0], atol=1e-4)  # at rest at the start
    for o in [first, *obs]:
        assert o.t == pytest.approx(o.tick * DT)
        if o.tick < len(rec.q_meas):
            np.testing.assert_array_equal(o.q, rec.q_meas[o.tick])  # measured at the next tick
        k = round(o.t_marker * 200)
        assert rec.t_marker[k] == o.t_marker
        np.testing.assert_allclose(o.markers, rec.markers[k], rtol=0, atol=1e-12)
    # The newest frame is at most one frame period and one step old.
    lag = [o.t + rec.metadata["start_delay_s"] - o.t_marker for o in obs]
    assert max(lag) <= 0.005 + 0.002
    assert len({o.t_marker for o in obs}) > 0.7 * len(obs) * 200 / 250
    assert np.any([np.abs(o.qd).max() > 0.1 for o in obs])


def test_an_online_fault_brakes_the_arm_and_ends_the_trial():
    amp = np.zeros(7)
    amp[0] = 1.0
    cmd = swing_command(amplitude=amp, duration=0.8)  # joint 1 too fast (tests/test_lab.py)
    want = first_fault(cmd.q, cmd.dt)
    assert want.quantity == "velocity"
    session = SimLab(PARAMS).start(cmd.q[0])
    faults = [session.send(row) for row in cmd.q[: want.tick + 2]]
    assert faults[:-1] == [None] * (want.tick + 1) and faults[-1] == want
    assert session.observe().fault == want
    n = session.n_ticks
    with pytest.raises(CommandError, match=r"^the controller faulted"):
        session.tick(cmd.q[want.tick + 2])
    assert session.n_ticks == n
    rec = session.finish()
    brake = want.tick + 1  # known one tick after the offending sample
    assert rec.fault == want.reason and rec.knot is None and not rec.succeeded
    assert rec.fault_time == pytest.approx(want.time)
    assert len(rec.t_joint) == brake + round(PARAMS.brake_s / DT) + 1
    np.testing.assert_array_equal(rec.q_cmd[:brake], cmd.q[:brake])
    np.testing.assert_array_equal(rec.q_cmd[brake:], np.repeat(rec.q_meas[brake][None], 76, 0))
    with pytest.raises(CommandError, match=r"^the trial is finished already$"):
        session.finish()


def test_bad_targets_are_refused_before_anything_changes():
    session = SimLab(PARAMS).start(HOME_Q)
    with pytest.raises(CommandError, match=r"^no target was sent"):
        session.finish()
    session.tick(HOME_Q)
    before = (session.n_ticks, session.j, session.observe().q)
    with pytest.raises(CommandError, match=r"^sample must have shape \(7,\), got \(8,\)$"):
        session.tick(np.zeros(8))
    with pytest.raises(CommandError, match=r"^sample is not finite at joint 1$"):
        session.tick(np.r_[np.nan, HOME_Q[1:]])
    assert (session.n_ticks, session.j) == before[:2]
    np.testing.assert_array_equal(session.observe().q, before[2])
    rec = session.finish()
    assert rec.fault is None and rec.metadata["command_duration_s"] == 0.0
    assert rec.metadata["trial_index"] == 0


def test_run_of_a_command_is_the_same_through_either_entry():
    # The lab's trial index counts sessions and runs alike.
    lab = SimLab(PARAMS)
    lab.start(HOME_Q).tick(HOME_Q)  # abandoned: counted, never finished
    cmd = JointCommand(np.repeat(HOME_Q[None], 5, axis=0))
    rec = lab.run(cmd)
    assert rec.metadata["trial_index"] == 1


@pytest.mark.parametrize("mode", ["all", "random"])
def test_observed_frames_lose_tracking_as_the_record_does(monkeypatch, mode):
    from flyknot_sim.mocap import MocapParams

    params = dataclasses.replace(PARAMS, mocap=MocapParams(loss_mode=mode, loss_fraction=0.5))
    cmd = swing_command(duration=0.4, amplitude=0.3 * SWING_AMPLITUDE)
    labs = SimLab(params), SimLab(params)
    # MjData's contacts after a step belong to the state before it (tests/test_lab.py).
    monkeypatch.setattr(
        type(labs[0].rope),
        "self_contact",
        lambda self, m, d: d.time - m.opt.timestep >= 0.2 - 1e-12,
    )
    session = labs[0].start(cmd.q[0])
    obs = [session.tick(row) for row in cmd.q]
    rec = session.finish()
    _assert_identical(_fields(rec), _fields(labs[1].run(cmd)))
    assert rec.first_contact_time == pytest.approx(0.2, abs=1e-9)
    frames = {round(o.t_marker * 200): o.markers for o in obs}
    late = [k for k in frames if rec.t_marker[k] >= 0.22 - 1e-9]
    assert len(late) > 10
    for k, m in frames.items():
        if mode == "all" or k not in late:
            np.testing.assert_allclose(m, rec.markers[k], rtol=0, atol=1e-12)
        else:  # the observation's own draw of lost markers; the positions are the record's
            seen = ~np.isnan(m[:, 0])
            ok = seen & ~np.isnan(rec.markers[k][:, 0])
            np.testing.assert_allclose(m[ok], rec.markers[k][ok], rtol=0, atol=1e-12)
    lost = np.array([np.isnan(frames[k][:, 0]).mean() for k in late])
    assert lost.min() == 1.0 if mode == "all" else 0.25 < lost.mean() < 0.75


def test_the_session_holds_the_plant_not_the_lab():
    """The lab opens a trial (index, variation, reset) and hands over one frozen plant; the
    session holds no reference to the lab and changes nothing of it but through the plant."""
    from flyknot_sim.session import Plant

    lab = SimLab(LabParams(rope=1, settle_s=0.1))
    session = lab.start(np.zeros(7))
    assert lab.trial_index == 1 and session.trial_index == 0
    assert isinstance(session.plant, Plant) and session.plant is lab.plant
    assert not any(isinstance(v, SimLab) for v in vars(session).values())
    with pytest.raises(dataclasses.FrozenInstanceError):
        lab.plant.tip_site = 0
    with pytest.raises(ValueError, match="read-only"):
        lab.plant.qadr[0] = 0

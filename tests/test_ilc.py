"""The ILC loop against a cell: learning, stopping, faults, failed QPs and resuming."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot.record import JointCommand, TrialRecord
from learner.bezier import BezierCommand
from learner.ilc import ILCParams, critical_cost, learn
from learner.inverse_qp import InverseModelWeights
from learner.kinematics import RobotModel
from learner.rope_model import RopeModelParams
from learner.run_directory import RunDirectory
from learner.system_model import model_demonstration, model_record
from learner.target import DemoTarget
from learner.update import UpdateSettings
from tests.knot_curves import judged

HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
T = 0.6
T_C = 0.565  # t_f = t_c + 35 ms, as the demo timing selection gives
ROPE = RopeModelParams(stiffness=1e3, damping=5.0)


@pytest.fixture(scope="module")
def robot():
    return RobotModel.from_mjcf()


def _knots(delta):
    k = np.zeros((10, 8))
    s = np.sin(np.linspace(0, np.pi, 8))
    s[[1, 6]] = s[[0, 7]]  # tied end knots: at rest at both ends, as every command is
    k[:7] = HOME[:, None] + np.outer(delta, s)
    k[7:] = np.array([0.0, 0.0, 1.0])[:, None]
    return k


class ModelCell:
    """The learner's own model as the 'real system'; a knot = critical cost below a bound."""

    def __init__(self, robot, target, knot_cost=5e-3, fault_on=()):
        self.robot, self.target, self.knot_cost, self.fault_on = robot, target, knot_cost, fault_on
        self.n = 0
        self.played = []

    def run(self, command: JointCommand) -> TrialRecord:
        knots = self.current
        self.played.append(knots.copy())
        rec = model_record(BezierCommand(knots, T), self.robot, ROPE)
        i = self.n
        self.n += 1
        if i in self.fault_on:
            return dataclasses.replace(rec, fault="joint 2 velocity exceeds limit", knot=None)
        from learner.critical_state import critical_state_from_record

        err = critical_state_from_record(rec, self.target.t_c, knots[7:, 0]) - self.target.x_c
        cost = critical_cost(err, InverseModelWeights())
        return judged(rec, cost < self.knot_cost)


def model_problem(robot):
    """The learner's own model as the lab: a target made by a command 0.1 rad off the start's,
    and that start (its knots)."""
    target_knots = _knots(np.array([0.3, 0.25, -0.2, 0.3, 0.2, -0.3, 0.2]))
    demo = model_demonstration(BezierCommand(target_knots, T), T_C, robot, ROPE)
    target = DemoTarget.from_demonstration(demo, dt=ROPE.dt)
    start = _knots(np.array([0.22, 0.3, -0.12, 0.22, 0.26, -0.22, 0.25]))
    return target, start


@pytest.fixture(scope="module")
def problem(robot):
    return model_problem(robot)


def _cell_for(robot, target, **kw):
    """A ModelCell and a spy that tells it which knots are being played (a cell sees joints)."""
    cell = ModelCell(robot, target, **kw)
    orig = BezierCommand.joint_command

    def spy(self, rate_hz=250.0):
        cell.current = np.asarray(self.knots)
        return orig(self, rate_hz)

    return cell, spy


def test_loop_learns_without_mismatch(robot, problem, monkeypatch, tmp_path):
    target, start = problem
    cell, spy = _cell_for(robot, target)
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    params = ILCParams(max_trials=6, rope_model=ROPE)
    res = learn(cell, target, start, robot, params, run_dir=tmp_path / "run")
    costs = [c for c in res.costs if c is not None]
    assert costs[0] > 1e-3
    assert res.first_success_trial is not None and res.first_success_trial <= 4
    assert costs[-1] < 0.01 * costs[0]
    assert res.stopped_because == "success"
    # Everything was written as it happened.
    rd = RunDirectory(tmp_path / "run")
    assert len(rd.ledger()) == len(res.trials)
    for s in res.trials:
        assert rd.knots_path(s.trial).is_file()
        TrialRecord.load(rd.record_stem(s.trial, s.attempt))


def test_resume_neither_loses_nor_repeats_a_trial(robot, problem, monkeypatch, tmp_path):
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0)  # never succeeds
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    params = ILCParams(max_trials=2, rope_model=ROPE)
    learn(cell, target, start, robot, params, run_dir=tmp_path / "run")
    assert cell.n == 2
    more = dataclasses.replace(params, max_trials=4)
    res = learn(cell, target, start, robot, more, run_dir=tmp_path / "run", resume=True)
    assert cell.n == 4  # two more trials, none repeated
    assert [s.trial for s in res.trials] == [0, 1, 2, 3]
    with pytest.raises(ConfigError, match="already holds a run; use resume"):
        learn(cell, target, start, robot, more, run_dir=tmp_path / "run")


def test_tracking_alone_plays_once_and_keeps_the_initial_command(robot, problem, monkeypatch):
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0)
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    res = learn(cell, target, start, robot, ILCParams(max_trials=0, rope_model=ROPE))
    assert cell.n == 1 and len(res.costs) == 1
    np.testing.assert_array_equal(res.final_knots, start)


def test_fault_steps_halfway_back(robot, problem, monkeypatch):
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0, fault_on=(1,))
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    res = learn(cell, target, start, robot, ILCParams(max_trials=3, rope_model=ROPE))
    assert res.trials[1].fault is not None and res.trials[1].cost is None
    p = cell.played
    np.testing.assert_allclose(p[2], p[0] + 0.5 * (p[1] - p[0]), atol=1e-12)


def test_faults_in_a_row_step_back_toward_the_last_measured_command(robot, problem, monkeypatch):
    """The gain step: each fault halves the distance to the last command that measured an
    error, so a run of faults converges on it (not on a midpoint of two faulted commands)."""
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0, fault_on=(1, 2, 3))
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    res = learn(cell, target, start, robot, ILCParams(max_trials=5, rope_model=ROPE))
    p = cell.played
    for k in (2, 3, 4):
        np.testing.assert_allclose(p[k], p[0] + 0.5 * (p[k - 1] - p[0]), atol=1e-12)
    assert [s.action for s in res.trials[1:4]] == ["fault: step halfway back"] * 3


def test_a_fault_under_the_damped_step_steps_from_the_best_more_damped(robot, problem, monkeypatch):
    """The damped step: a trial that faulted is a failed step (cost +inf): lambda grows by
    ``grow`` and the next command is the best command's update with that lambda."""
    from learner.steps import DampingParams

    target, start = problem
    damping = DampingParams(start=1.0)
    params = ILCParams(max_trials=4, rope_model=ROPE, step="damped", damping=damping)
    cell, spy = _cell_for(robot, target, knot_cost=0.0, fault_on=(1, 2))
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    res = learn(cell, target, start, robot, params)
    lam1 = damping.start / damping.shrink  # after trial 1, the first best
    lam2, lam3 = lam1 * damping.grow, lam1 * damping.grow**2
    assert [s.action for s in res.trials[1:3]] == [
        f"fault: from the best command (trial 1), lambda {lam2:.3g}",
        f"fault: from the best command (trial 1), lambda {lam3:.3g}",
    ]
    p = cell.played
    steps = [np.linalg.norm(p[k] - p[0]) for k in (1, 2, 3)]
    assert steps[0] > steps[1] > steps[2] > 0  # each more damped, all from the best
    assert not np.allclose(p[2], p[0] + 0.5 * (p[1] - p[0]))


def test_faulting_initial_command_stops(robot, problem, monkeypatch):
    target, start = problem
    cell, spy = _cell_for(robot, target, fault_on=(0,))
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    res = learn(cell, target, start, robot, ILCParams(max_trials=3, rope_model=ROPE))
    assert res.stopped_because == "initial command faults" and len(res.trials) == 1


def test_params_validation():
    with pytest.raises(
        ConfigError,
        match=r"objective: unknown value 'x' \(valid choices: critical, equal, launch\)",
    ):
        ILCParams(update=UpdateSettings(objective="x"))
    with pytest.raises(ConfigError, match="max_trials: must be an integer >= 0, got -1"):
        ILCParams(max_trials=-1)


def test_safe_step_halves_a_step_that_would_break_a_limit(robot):
    from flyknot.limits import JointLimits
    from learner.ilc_step import safe_step as _safe_step
    from learner.limit_rows import sampled_violation

    knots = _knots(np.zeros(7))
    dk = np.zeros((10, 8))
    dk[0, 2:6] = [-1.5, 1.5, -1.5, 1.5]  # a fast wiggle of joint 1 if taken whole
    t = BezierCommand(knots, T).sample_times()
    assert sampled_violation(knots - dk, T, t, robot, JointLimits()) > 0
    new = _safe_step(knots, dk, T, robot, JointLimits())
    assert sampled_violation(new, T, t, robot, JointLimits()) <= 1e-9
    alpha = (knots - new)[0, 2] / dk[0, 2]
    assert alpha in (0.5, 0.25, 0.125, 0.0625)
    small = 0.01 * dk
    np.testing.assert_allclose(_safe_step(knots, small, T, robot, JointLimits()), knots - small)
    # With no halving allowed the whole step is taken, limits or not.
    np.testing.assert_allclose(_safe_step(knots, dk, T, robot, JointLimits(), 0), knots - dk)


def test_gain_scales_the_step(robot, problem, monkeypatch):
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0)
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    full = learn(cell, target, start, robot, ILCParams(max_trials=2, rope_model=ROPE))
    step_full = cell.played[1] - cell.played[0]
    cell.played.clear()
    learn(cell, target, start, robot, ILCParams(max_trials=2, rope_model=ROPE, gain=0.25))
    np.testing.assert_allclose(cell.played[1] - cell.played[0], 0.25 * step_full, atol=1e-9)
    assert full.trials[0].cost is not None
    with pytest.raises(ConfigError, match=r"gain: must lie in \(0, 1\], got 0"):
        ILCParams(gain=0)


def test_trust_region_caps_every_arm_knot_step(robot, problem, monkeypatch):
    target, start = problem
    cell, spy = _cell_for(robot, target, knot_cost=0.0)
    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    learn(cell, target, start, robot, ILCParams(max_trials=2, rope_model=ROPE))
    free = np.abs(cell.played[1] - cell.played[0])[:7].max()
    radius = 0.3 * free
    cell.played.clear()
    learn(
        cell,
        target,
        start,
        robot,
        ILCParams(max_trials=2, rope_model=ROPE, update=UpdateSettings(trust_region=radius)),
    )
    boxed = np.abs(cell.played[1] - cell.played[0])[:7].max()
    assert boxed <= radius * (1 + 1e-4) and boxed >= radius * (1 - 1e-3)
    with pytest.raises(ConfigError, match="trust_region: must be a finite number > 0, got 0"):
        ILCParams(update=UpdateSettings(trust_region=0))

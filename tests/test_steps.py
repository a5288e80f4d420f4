"""The step rules of the ILC loop: the paper's fixed gain and the damped (Levenberg-Marquardt)
step on the measured cost."""

from __future__ import annotations

import dataclasses
from functools import partial

import numpy as np
import pytest

from flyknot.errors import ConfigError, RecordError
from flyknot.record import TrialRecord
from learner.bezier import BezierCommand
from learner.critical_state import MarkerFitParams, critical_state_from_record
from learner.ilc import ILCParams, learn
from learner.inverse_qp import InverseModelWeights
from learner.kinematics import RobotModel
from learner.objectives import error_at
from learner.run_directory import RunDirectory, TrialSummary
from learner.steps import STEPS, Damping, DampingParams
from learner.stops import DampedStep
from learner.system_model import model_record
from learner.trial_view import Trial
from learner.update import UpdateSettings, ilc_update
from tests.test_confirm import DisturbedCell, _spy
from tests.test_ilc import ROPE, model_problem


@pytest.fixture(scope="module")
def arm():
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def setup(arm):
    return model_problem(arm)


def test_damping_memory():
    d = Damping(DampingParams(start=1.0, shrink=2.0, grow=4.0, smallest=0.3))
    assert d.observe(5.0, 0) is True and d.lam == 0.5 and d.best == (5.0, 0)
    assert d.observe(6.0, 1) is False and d.lam == 2.0 and d.best == (5.0, 0)
    assert d.observe(None, 2) is None and d.lam == 2.0
    assert d.observe(1.0, 3) is True and d.lam == 1.0 and d.best == (1.0, 3)
    assert d.observe(0.5, 4) is True and d.lam == 0.5
    assert d.observe(0.4, 5) is True and d.lam == 0.3  # not below the smallest


def test_damping_noise_band():
    """A rise within nu of the best is the same cost: the full step from it, lambda kept, the
    best unchanged; a rise beyond it steps back from the best, more damped."""
    d = Damping(DampingParams(start=1.0, shrink=2.0, grow=4.0, noise=0.3))
    assert d.observe(1.0, 0) is True and d.lam == 0.5 and d.is_best(0)
    assert d.observe(1.3, 1) is True and d.lam == 0.5 and d.best == (1.0, 0)
    assert not d.is_best(1)
    assert d.observe(1.31, 2) is False and d.lam == 2.0 and d.best == (1.0, 0)
    assert d.observe(0.9, 3) is True and d.lam == 1.0 and d.is_best(3)
    plain = Damping(DampingParams(start=1.0, shrink=2.0, grow=4.0))
    assert plain.observe(1.0, 0) is True and plain.observe(1.0, 1) is False  # as before


def test_damping_weighs_against_the_best_at_a_given_time():
    d = Damping(DampingParams(start=1.0, shrink=2.0, grow=4.0))
    assert d.observe(1.0, 0) is True
    assert d.observe(0.9, 1, against=0.8, own=1.2) is False and d.best == (1.0, 0)
    assert d.observe(0.7, 2, against=0.8, own=1.1) is True and d.best == (1.1, 2)


class _Seen(Trial):
    """A trial as the damped step sees it: a cost at its own t_eff and refitted ones."""

    def __init__(self, k, cost, t_eff, refit):
        line = TrialSummary(k, 0, None, "unknot", False, cost, True, "Solved", None, "", 0.0)
        super().__init__(dataclasses.replace(line, t_eff=t_eff), np.zeros((10, 8)), None)
        self.refit = refit

    def record(self):
        raise AssertionError

    def cost_at(self, t):
        return self.refit[t]

    def own_update(self):
        return True, None

    def average_over(self, group):
        return None


@pytest.mark.parametrize("common_time", [False, True])
def test_damped_step_at_a_common_time(common_time):
    """Trial 2's markers were lost earlier (0.88 s) than the best's (0.90 s): at its own time
    it costs more than the best did at 0.90 s, at 0.88 s less than the best there."""
    damping = DampingParams(start=1.0, common_time=common_time)
    rule = DampedStep(ILCParams(step="damped", damping=damping))
    best = _Seen(0, 0.40, 0.90, {0.88: 0.48})
    rule.verdict(best)
    later = _Seen(1, 0.43, 0.88, {})
    rule.verdict(later)
    assert (rule.best is later) is common_time
    assert later.summary.action == "" and rule.damping.best[0] == (0.43 if common_time else 0.40)


def test_error_at_the_critical_point_and_before(arm, setup):
    """error_at gives the critical point's error at t_c, a model step's before it, and names
    a time that is neither."""
    target, start = setup
    command = BezierCommand(start, target.T)
    rec = model_record(command, arm, ROPE)
    base = command.base_offset
    fit = MarkerFitParams()
    at_c = error_at(rec, target, base, fit, target.t_c)
    want = critical_state_from_record(rec, target.t_c, base, fit) - target.x_c
    np.testing.assert_array_equal(at_c, want)
    k = len(target.x_pre) - 3
    before = error_at(rec, target, base, fit, float(target.t[k]))
    np.testing.assert_array_equal(
        before, critical_state_from_record(rec, float(target.t[k]), base, fit) - target.x_pre[k]
    )
    with pytest.raises(RecordError, match="no demonstration state at t = "):
        error_at(rec, target, base, fit, float(target.t[k]) + 0.4 * target.dt)


def test_step_options_are_checked():
    assert set(STEPS) == {"gain", "damped"}
    with pytest.raises(ConfigError) as e:
        ILCParams(step="newton")
    assert str(e.value) == "step: unknown step rule 'newton' (valid choices: damped, gain)"
    with pytest.raises(ConfigError) as e:
        ILCParams(step="damped", safeguard=True)
    assert str(e.value) == (
        "step: 'damped' returns to the best command itself: it takes no safeguard or average > 1"
    )
    with pytest.raises(ConfigError) as e:
        DampingParams(grow=0.5)
    assert str(e.value) == "damping.grow: must be > 1, got 0.5"
    with pytest.raises(ConfigError) as e:
        DampingParams(common_time="yes")
    assert str(e.value) == "damping.common_time: must be a bool, got 'yes'"
    with pytest.raises(ConfigError) as e:
        DampingParams(noise=-0.1)
    assert str(e.value) == "damping.noise: must be a finite number >= 0, got -0.1"


def _damped_run(
    arm, target, start, monkeypatch, run_dir, trials, resume=False, cell=None, noise=0.0
):
    cell = cell or DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    damping = DampingParams(start=1.0, noise=noise)  # round numbers, not the default
    params = ILCParams(max_trials=trials, rope_model=ROPE, step="damped", gain=1.0, damping=damping)
    res = learn(cell, target, start, arm, params, run_dir=run_dir, resume=resume)
    return cell, res


def test_damped_step_goes_back_to_the_best_with_more_damping(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    cell, res = _damped_run(arm, target, start, monkeypatch, tmp_path / "run", 4)
    costs = res.costs
    assert costs[1] < costs[0] and costs[2] > costs[1]  # trial 2 measured worse (disturbed)
    actions = [s.action for s in res.trials]
    assert actions[:2] == ["update (damped, lambda 1)", "update (damped, lambda 0.5)"]
    assert actions[2] == "cost rose: from the best command (trial 2), lambda 1"
    # trial 3 = the best command (trial 1) less the update about its record at lambda 1
    rd = RunDirectory(tmp_path / "run")
    best = TrialRecord.load(rd.record_stem(1, 0))
    settings = UpdateSettings(weights=InverseModelWeights(w_control=1.0))
    expect = ilc_update(best, BezierCommand(cell.played[1], target.T), target, arm, ROPE, settings)
    np.testing.assert_allclose(cell.played[3], expect.new_knots, atol=1e-12)


def test_damped_step_within_the_noise_steps_on(arm, setup, monkeypatch, tmp_path):
    """The same disturbed trial 2 inside a wide noise band: the full step from its own update,
    lambda kept, the best still trial 1's."""
    target, start = setup
    cell = DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    damping = DampingParams(start=1.0, noise=100.0)
    params = ILCParams(max_trials=4, rope_model=ROPE, step="damped", gain=1.0, damping=damping)
    res = learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    assert res.costs[2] > res.costs[1]
    assert res.trials[2].action == (
        "update (damped, lambda 0.25; within the noise of the best, trial 2)"
    )
    rd = RunDirectory(tmp_path / "run")
    rec = TrialRecord.load(rd.record_stem(2, 0))
    settings = UpdateSettings(weights=InverseModelWeights(w_control=0.25))
    expect = ilc_update(rec, BezierCommand(cell.played[2], target.T), target, arm, ROPE, settings)
    np.testing.assert_allclose(cell.played[3], expect.new_knots, atol=1e-12)


@pytest.mark.parametrize("noise", [0.0, 100.0])
def test_damped_run_resumed_is_the_uninterrupted_run(arm, setup, monkeypatch, tmp_path, noise):
    target, start = setup
    run = partial(_damped_run, arm, target, start, monkeypatch, noise=noise)
    whole, res = run(tmp_path / "whole", 5)
    part, _ = run(tmp_path / "part", 3)
    part, again = run(tmp_path / "part", 5, resume=True, cell=part)
    assert [s.action for s in again.trials] == [s.action for s in res.trials]
    for a, b in zip(part.played, whole.played, strict=True):
        np.testing.assert_array_equal(a, b)
    assert dataclasses.asdict(ILCParams(step="damped"))["step"] == "damped"


def test_damped_with_confirmation_resumed_is_the_uninterrupted_run(
    arm, setup, monkeypatch, tmp_path
):
    """A tie (trial 1) is replayed to confirm it (trial 2 misses): the damped step learns on
    from there, and a run resumed after the confirmation replays the same rules."""
    from tests.test_confirm import ScriptedCell

    target, start = setup
    script = [False, True, False, False, False, False]
    params = ILCParams(max_trials=5, rope_model=ROPE, step="damped", gain=1.0, confirm=(2, 2))

    def run(out, trials, resume=False, cell=None):
        cell = cell or ScriptedCell(arm, target, script)
        _spy(cell, monkeypatch)
        p = dataclasses.replace(params, max_trials=trials)
        return cell, learn(cell, target, start, arm, p, run_dir=out, resume=resume)

    whole, res = run(tmp_path / "whole", 5)
    actions = [s.action for s in res.trials]
    assert actions[1].startswith("confirm 1/2") and actions[2].startswith("update (damped")
    np.testing.assert_array_equal(whole.played[2], whole.played[1])  # the tie replayed
    part, _ = run(tmp_path / "part", 3)
    part, again = run(tmp_path / "part", 5, resume=True, cell=part)
    assert [s.action for s in again.trials] == actions
    for a, b in zip(part.played, whole.played, strict=True):
        np.testing.assert_array_equal(a, b)

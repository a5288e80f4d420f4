"""A trial whose update fails (the learner's model fails on its measured motion) still counts:
its knot stops the run, and a resumed run goes past it the same way."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flyknot.errors import SolverError
from learner import ilc_step
from learner.ilc import ILCParams, learn
from learner.kinematics import RobotModel
from learner.run_directory import RunDirectory
from tests.test_confirm import _cell
from tests.test_ilc import ROPE, model_problem


@pytest.fixture(scope="module")
def arm():
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def setup(arm):
    return model_problem(arm)


def _failing_on(monkeypatch, trials: set[int]):
    """ilc_update raising SolverError for the trials in ``trials`` (by the cell's count)."""
    real = ilc_step.ilc_update
    calls = {"n": 0}

    def update(*args, **kwargs):
        i = calls["n"]
        calls["n"] += 1
        if i in trials:
            raise SolverError("rope model", "not converged", "Newton at step 41")
        return real(*args, **kwargs)

    monkeypatch.setattr(ilc_step, "ilc_update", update)


def test_a_tying_trial_whose_update_fails_ends_the_run_with_its_knot(
    arm, setup, monkeypatch, tmp_path
):
    target, start = setup
    cell = _cell(arm, target, [False, True, False], monkeypatch)
    _failing_on(monkeypatch, {1})
    res = learn(cell, target, start, arm, ILCParams(rope_model=ROPE), run_dir=tmp_path / "run")
    assert res.stopped_because == "success" and res.first_success_trial == 1
    line = res.trials[1]
    assert line.update_solved is False and line.cost is None
    assert line.update_status == (
        "update failed: rope model failed with status 'not converged': Newton at step 41"
    )
    again = learn(
        cell, target, start, arm, ILCParams(rope_model=ROPE), run_dir=tmp_path / "run", resume=True
    )
    assert cell.n == 2  # nothing played again
    assert again.stopped_because == "success" and again.trials == res.trials


def test_a_failed_update_keeps_the_command_and_resume_goes_past_it(
    arm, setup, monkeypatch, tmp_path
):
    target, start = setup
    params = ILCParams(rope_model=ROPE, max_trials=2)
    cell = _cell(arm, target, [False] * 4, monkeypatch)
    _failing_on(monkeypatch, {1})
    learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    rd = RunDirectory(tmp_path / "run")
    np.testing.assert_array_equal(rd.load_knots(2), rd.load_knots(1))  # command unchanged
    assert rd.ledger()[1].action == "update failed: command unchanged"
    more = dataclasses.replace(params, max_trials=3)
    res = learn(cell, target, start, arm, more, run_dir=tmp_path / "run", resume=True)
    assert [s.trial for s in res.trials] == [0, 1, 2]
    np.testing.assert_array_equal(cell.played[2], cell.played[1])

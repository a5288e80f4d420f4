"""The confirmed-success stop rule of the ILC loop: a tie must repeat k of n."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from flyknot.errors import ConfigError
from learner.bezier import BezierCommand
from learner.ilc import ILCParams, learn
from learner.kinematics import RobotModel
from learner.run_directory import RunDirectory
from tests.knot_curves import judged, verdict
from tests.test_ilc import ROPE, ModelCell, model_problem


@pytest.fixture(scope="module")
def arm():
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def setup(arm):
    return model_problem(arm)


class ScriptedCell(ModelCell):
    """The model cell, but the knot of trial i is ``script[i]`` (True: trefoil)."""

    def __init__(self, arm, target, script):
        super().__init__(arm, target)
        self.script = script

    def run(self, command):
        i = self.n
        rec = super().run(command)
        return judged(rec, self.script[i])


def _cell(arm, target, script, monkeypatch):
    cell = ScriptedCell(arm, target, script)
    orig = BezierCommand.joint_command

    def spy(self, rate_hz=250.0):
        cell.current = np.asarray(self.knots)
        return orig(self, rate_hz)

    monkeypatch.setattr(BezierCommand, "joint_command", spy)
    return cell


def test_confirmed_after_k_of_n(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    cell = _cell(arm, target, [False, True, False, True, True, True], monkeypatch)
    params = ILCParams(max_trials=8, rope_model=ROPE, confirm=(2, 3))
    res = learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    assert res.stopped_because == "confirmed"
    assert res.first_success_trial == 1
    assert [s.confirm for s in res.trials] == [None, 1, 2, 3]
    # The tying command was played three times unchanged.
    np.testing.assert_array_equal(cell.played[1], cell.played[2])
    np.testing.assert_array_equal(cell.played[1], cell.played[3])
    assert not np.array_equal(cell.played[0], cell.played[1])
    assert res.trials[2].action.startswith("confirm 2/3: ")


def test_a_failed_confirmation_learns_on_from_its_last_trial(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    cell = _cell(arm, target, [True, False, True, True, True, True], monkeypatch)
    params = ILCParams(max_trials=6, rope_model=ROPE, confirm=(3, 3))
    res = learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    # [T, F]: 3 of 3 can no longer be reached -> update; trial 2 is a new command that ties
    # and is confirmed by trials 3 and 4.
    assert [s.confirm for s in res.trials] == [1, 2, 1, 2, 3]
    np.testing.assert_array_equal(cell.played[0], cell.played[1])
    assert not np.array_equal(cell.played[1], cell.played[2])
    assert res.stopped_because == "confirmed"


def test_resume_inside_a_confirmation(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    script = [False, True, True, False, True, True, True, True]
    whole = _cell(arm, target, script, monkeypatch)
    params = ILCParams(max_trials=8, rope_model=ROPE, confirm=(3, 4))
    res = learn(whole, target, start, arm, params, run_dir=tmp_path / "a")
    cut = _cell(arm, target, script, monkeypatch)
    learn(
        cut, target, start, arm, dataclasses.replace(params, max_trials=3), run_dir=tmp_path / "b"
    )
    again = learn(cut, target, start, arm, params, run_dir=tmp_path / "b", resume=True)
    assert again.stopped_because == res.stopped_because == "confirmed"
    strip = [
        {k: v for k, v in json.loads(line).items() if k != "wall_s"}
        for line in (tmp_path / "a" / "ledger.jsonl").read_text().splitlines()
    ]
    strip_b = [
        {k: v for k, v in json.loads(line).items() if k != "wall_s"}
        for line in (tmp_path / "b" / "ledger.jsonl").read_text().splitlines()
    ]
    assert strip == strip_b
    assert len(RunDirectory(tmp_path / "b").ledger()) == len(res.trials) == 5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"confirm": (3, 2)}, "confirm: must be [k, n] (or k/n) with 1 <= k <= n, got (3, 2)"),
        ({"confirm": (0, 2)}, "confirm: must be [k, n] (or k/n) with 1 <= k <= n, got (0, 2)"),
        ({"confirm": (1, 2), "stop_at_success": False}, "confirm: needs stop_at_success = true"),
    ],
)
def test_confirm_errors(kwargs, message):
    with pytest.raises(ConfigError) as e:
        ILCParams(**kwargs)
    assert str(e.value) == message


def test_outcome_line_reports_both_stop_rules():
    from flyknot_app.reports.report import outcome_line
    from flyknot_app.reports.run_summary import RunSummary

    def run(name, n, why):
        return RunSummary(
            {"name": name, "confirm": [2, 3]}, trials_to_success=n, stopped_because=why
        )

    runs = [run("a", 3, "confirmed"), run("b", 2, "max_trials"), run("c", None, "max_trials")]
    assert outcome_line("learn", runs) == (
        "Knot learned in 2 of 3 runs; confirmed (2 of 3 repeats tied) in 1 of 3."
    )
    one = RunSummary({"name": "d"}, trials_to_success=1, stopped_because="success")
    assert outcome_line("learn", [one]) == "Knot learned in 1 of 1 runs."


def _spy(cell, monkeypatch):
    orig = BezierCommand.joint_command

    def spy(self, rate_hz=250.0):
        cell.current = np.asarray(self.knots)
        return orig(self, rate_hz)

    monkeypatch.setattr(BezierCommand, "joint_command", spy)


class DisturbedCell(ModelCell):
    """The model cell with the markers of trial ``bad`` shifted 5 cm (a bad measurement)."""

    def __init__(self, arm, target, bad):
        super().__init__(arm, target, knot_cost=0.0)
        self.bad = bad

    def run(self, command):
        i = self.n
        rec = super().run(command)
        if i == self.bad:
            rec = dataclasses.replace(rec, markers=rec.markers + np.array([0.05, 0.0, 0.0]))
        return rec


def test_safeguard_returns_to_the_best_command_with_a_shrunk_step(
    arm, setup, monkeypatch, tmp_path
):
    target, start = setup
    cell = DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    params = ILCParams(max_trials=4, rope_model=ROPE, safeguard=True, gain=1.0)
    res = learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    costs = res.costs
    assert costs[2] > costs[1]  # the disturbed trial measured worse
    assert res.trials[2].action.startswith("cost rose: back to the best command")
    rd = RunDirectory(tmp_path / "run")
    dk_best = np.asarray(rd.load_update(1)["dkappa"])
    np.testing.assert_allclose(cell.played[3], cell.played[1] - 0.5 * dk_best, atol=1e-12)
    # Resuming after the rejection rebuilds the same state.
    again = learn(
        cell,
        target,
        start,
        arm,
        dataclasses.replace(params, max_trials=5),
        run_dir=tmp_path / "run",
        resume=True,
    )
    assert len(again.trials) == 5


def test_without_safeguard_the_disturbed_update_is_taken(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    cell = DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    params = ILCParams(max_trials=4, rope_model=ROPE, gain=1.0)
    learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    rd = RunDirectory(tmp_path / "run")
    dk2 = np.asarray(rd.load_update(2)["dkappa"])
    assert not np.allclose(
        cell.played[3], cell.played[1] - 0.5 * np.asarray(rd.load_update(1)["dkappa"])
    )
    assert np.linalg.norm(cell.played[3] - cell.played[2]) > 0
    assert np.all(np.isfinite(dk2))


def test_average_updates_on_the_mean_error_of_its_plays(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    cell = DisturbedCell(arm, target, bad=1)
    _spy(cell, monkeypatch)
    params = ILCParams(max_trials=4, rope_model=ROPE, average=3)
    res = learn(cell, target, start, arm, params, run_dir=tmp_path / "run")
    assert [s.average for s in res.trials] == [1, 2, 3, 1]
    np.testing.assert_array_equal(cell.played[0], cell.played[1])
    np.testing.assert_array_equal(cell.played[0], cell.played[2])
    assert not np.array_equal(cell.played[2], cell.played[3])
    rd = RunDirectory(tmp_path / "run")
    e0, e1, e2 = (np.asarray(rd.load_update(k)["err"]) for k in range(3))
    # Plays 0 and 2 measure the same (a deterministic cell); play 1 was disturbed.
    np.testing.assert_allclose(e2, (2 * e0 + e1) / 3, atol=1e-9)
    assert res.trials[2].action == "update on the mean error of 3 plays"


def test_resume_inside_an_averaging_group(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    params = ILCParams(max_trials=5, rope_model=ROPE, average=3)
    whole = DisturbedCell(arm, target, bad=1)
    _spy(whole, monkeypatch)
    learn(whole, target, start, arm, params, run_dir=tmp_path / "a")
    cut = DisturbedCell(arm, target, bad=1)
    _spy(cut, monkeypatch)
    learn(
        cut, target, start, arm, dataclasses.replace(params, max_trials=2), run_dir=tmp_path / "b"
    )
    learn(cut, target, start, arm, params, run_dir=tmp_path / "b", resume=True)

    def ledger(d):
        rows = [json.loads(x) for x in (d / "ledger.jsonl").read_text().splitlines()]
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]

    assert ledger(tmp_path / "a") == ledger(tmp_path / "b")
    np.testing.assert_array_equal(whole.played[3], cut.played[3])


def test_average_must_be_a_positive_integer():
    with pytest.raises(ConfigError) as e:
        ILCParams(average=0)
    assert str(e.value) == "average: must be an integer >= 1, got 0"
    with pytest.raises(ConfigError) as e:
        ILCParams(average_first=0)
    assert str(e.value) == "average_first: must be an integer >= 1, got 0"
    with pytest.raises(ConfigError) as e:
        ILCParams(average_first=2, safeguard=True)
    assert str(e.value) == (
        "average_first: the safeguard steps by a trial's own update: it takes no average_first > 1"
    )
    # the damped step and the secant take an averaged first command (not every command)
    assert ILCParams(step="damped", average_first=3).average_first == 3


def test_the_stop_rule_asks_the_judge_not_the_cell(arm, setup, monkeypatch):
    target, start = setup
    cell = _cell(arm, target, [True] * 4, monkeypatch)  # the cell says "knot" every time
    asked = []

    def judge(record):  # a person who sees a knot only in the third trial
        asked.append(record.verdict.klass)
        return verdict("knot" if len(asked) == 3 else "wrapped_at_grip")

    res = learn(cell, target, start, arm, ILCParams(max_trials=5, rope_model=ROPE), judge=judge)
    assert res.first_success_trial == 2 and res.stopped_because == "success"
    assert [s.verdict["klass"] for s in res.trials] == ["wrapped_at_grip"] * 2 + ["knot"]
    assert asked == ["knot"] * 3

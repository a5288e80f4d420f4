"""The stop rules of the ILC loop (learner/stops.py): one registry that the loop and a resumed
run share, so a run resumed after any line of its ledger holds the state the loop held there."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest

from flyknot.errors import ConfigError, FlyknotError
from flyknot.judge import CellVerdict
from flyknot.limits import JointLimits
from learner import ilc, stops
from learner.bezier import BezierCommand
from learner.ilc import ILCParams, learn
from learner.ilc_params import ExploreParams, PlateauParams
from learner.ilc_step import Context, LoopState
from learner.kinematics import RobotModel
from learner.run_directory import RunDirectory, TrialSummary
from learner.steps import DampingParams
from learner.stops import STOP, STOPS, Ruling, StopRule, StopRules, stop_rule
from learner.trial_view import Trial
from learner.update import UpdateSettings
from tests.knot_curves import judged
from tests.test_ilc import ROPE, ModelCell, model_problem


@pytest.fixture(scope="module")
def arm():
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def setup(arm):
    return model_problem(arm)


class EventCell(ModelCell):
    """The learner's model as the lab, with scripted plays (by the play's index): a knot for
    those in ``ties``, markers shifted 5 cm in ``shifted`` (a bad measurement), lost in
    ``lost``, a fault in ``fault_on``; ``die_at`` raises instead of playing (a kill)."""

    def __init__(self, arm, target, ties=(), shifted=(), lost=(), fault_on=(), die_at=None):
        super().__init__(arm, target, knot_cost=0.0, fault_on=fault_on)
        self.ties, self.shifted, self.lost, self.die_at = ties, shifted, lost, die_at

    def run(self, command):
        i = self.n
        if i == self.die_at:
            raise KeyboardInterrupt("killed")
        rec = super().run(command)
        if rec.fault is not None:
            return rec
        if i in self.shifted:
            rec = dataclasses.replace(rec, markers=rec.markers + np.array([0.05, 0.0, 0.0]))
        if i in self.lost:
            rec = dataclasses.replace(rec, markers=np.full_like(rec.markers, np.nan))
        return judged(rec, i in self.ties)


def _spy(cell, monkeypatch):
    """Tell the cell which knots are played (a cell sees only joints)."""
    orig = BezierCommand.joint_command

    def spy(self, rate_hz=250.0):
        cell.current = np.asarray(self.knots)
        return orig(self, rate_hz)

    monkeypatch.setattr(BezierCommand, "joint_command", spy)


def _state(state: LoopState) -> dict:
    """Everything the loop carries from one trial to the next, as plain data."""
    return {
        "k": state.k,
        "knots": state.knots.tolist(),
        "prev_knots": None if state.prev_knots is None else state.prev_knots.tolist(),
        "stop": state.stop,
        "trials": [dataclasses.replace(s, wall_s=0.0) for s in state.trials],
        "rules": state.rules.memory(),
    }


def _loop_states(monkeypatch) -> dict[int, dict]:
    """The loop's state after each ledger line (by the ledger's length), as the run goes."""
    shots: dict[int, dict] = {}
    commit, advance = ilc._commit, LoopState.advance

    def spy_commit(rd, state, step, on_trial):
        commit(rd, state, step, on_trial)
        shots[len(state.trials)] = _state(state)

    def spy_advance(self, step):
        advance(self, step)
        shots[len(self.trials)] = _state(self)

    monkeypatch.setattr(ilc, "_commit", spy_commit)
    monkeypatch.setattr(LoopState, "advance", spy_advance)
    return shots


class Prefix(RunDirectory):
    """A run directory whose ledger ends after its first ``n`` lines (a kill there)."""

    def __init__(self, path, n: int):
        super().__init__(path)
        self.n = n

    def ledger(self):
        return super().ledger()[: self.n]


def _resumed(run_dir, n, start, target, arm, params) -> dict:
    """The state a run resumed after ledger line ``n`` starts from."""
    ctx = Context(target, arm, params, JointLimits(), CellVerdict())
    state = ilc._restore(Prefix(run_dir, n), LoopState.initial(start, params), ctx)
    return _state(state)


SCENARIOS = {
    # name: (ILCParams options, EventCell script, ledger actions the run must show)
    "success": ({"max_trials": 5}, {"ties": {2}}, ["update"]),
    "confirm": (
        {"max_trials": 8, "confirm": (2, 3)},
        {"ties": {0, 4, 5}},
        ["confirm 1/3", "confirm 3/3"],
    ),
    "safeguard": (
        {"max_trials": 5, "safeguard": True},
        {"shifted": {2}},
        ["cost rose: back to the best command"],
    ),
    "average": (
        {"max_trials": 6, "average": 3},
        {"shifted": {1}},
        ["play 2/3 of the command", "update on the mean error of 3 plays"],
    ),
    "damped": (
        {"max_trials": 5, "step": "damped"},
        {"shifted": {2}},
        ["update (damped", "cost rose: from the best command"],
    ),
    "retry and fault": (
        {"max_trials": 5, "tracking_retries": 2},
        {"lost": {1, 2, 5, 6, 7}, "fault_on": {4}},
        ["repeat (tracking lost", "fault: step halfway back"],
    ),
    "initial fault": ({"max_trials": 3}, {"fault_on": {0}}, ["fault"]),
    "damped and faults": (
        {"max_trials": 6, "step": "damped"},
        {"fault_on": {2, 3}},
        ["update (damped", "fault: from the best command"],
    ),
    "damped, secant and the first command averaged": (
        {
            "max_trials": 7,
            "step": "damped",
            "average_first": 3,
            "update": UpdateSettings(jacobian="secant"),
        },
        {"fault_on": {3}, "shifted": {5}},
        [
            "play 2/3 of the command",
            "update (damped, lambda 0.25, on the mean error of 3 plays)",
            "fault: from the best command (trial 3)",
        ],
    ),
    "explore": (
        {"max_trials": 7, "step": "damped", "explore": ExploreParams(size=0.05, band=1e3)},
        {"shifted": {2, 3}},
        ["update (damped", "cost rose: from the best command", "explore: from the best command"],
    ),
    "converged knot": (
        {"max_trials": 6, "step": "damped", "converged_knot": True},
        {"ties": {1, 2, 3, 4, 5}},
        ["update (damped"],
    ),
    "plateau": (
        {"max_trials": 8, "plateau": PlateauParams(patience=2, noise=0.5)},
        {"shifted": {2}},
        ["update"],
    ),
    "confirm and average": (
        {"max_trials": 6, "average": 2, "confirm": (2, 3)},
        {"ties": {1}},
        ["play 1/2", "confirm 2/3", "update on the mean error of 2 plays"],
    ),
    "safeguard and average": (
        {"max_trials": 5, "average": 2, "safeguard": True},
        {"shifted": {1, 4}},  # a shifted play measures a lower cost here
        ["update on the mean error of 2 plays", "cost rose: back to the best command"],
    ),
}


def _run(arm, setup, monkeypatch, run_dir, options, script, **kw):
    target, start = setup
    cell = EventCell(arm, target, **script, **kw)
    _spy(cell, monkeypatch)
    params = ILCParams(rope_model=ROPE, gain=1.0, **options)
    return cell, params, learn(cell, target, start, arm, params, run_dir=run_dir)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_resume_after_every_line_holds_the_loops_state(name, arm, setup, monkeypatch, tmp_path):
    options, script, shows = SCENARIOS[name]
    shots = _loop_states(monkeypatch)
    _, params, res = _run(arm, setup, monkeypatch, tmp_path / "run", options, script)
    actions = " | ".join(s.action for s in res.trials)
    for text in shows:  # the run exercised the rules it is meant to
        assert text in actions, actions
    n_lines = len(RunDirectory(tmp_path / "run").ledger())
    assert sorted(shots) == list(range(1, n_lines + 1))
    target, start = setup
    for n in range(n_lines + 1):
        expect = shots[n] if n else _state(LoopState.initial(start, params))
        got = _resumed(tmp_path / "run", n, start, target, arm, params)
        assert got == expect, f"{name}: resumed after line {n}"


def _ledger(run_dir):
    rows = [json.loads(x) for x in (run_dir / "ledger.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]


@pytest.mark.parametrize(
    ("name", "kill_at"),
    [
        ("retry and fault", 2),  # after a lost attempt with retries left
        ("retry and fault", 5),  # after a counted trial, before a lost attempt
        ("damped and faults", 3),  # between two faults, lambda grown once
        ("confirm and average", 2),  # inside a confirmation, with a play being averaged
        ("safeguard and average", 2),  # after a group whose last play is the best trial
        ("safeguard and average", 4),  # then back to the best command
        ("explore", 5),  # after an exploring step
        ("converged knot", 3),  # after two knots the learner has not converged on
        ("damped, secant and the first command averaged", 2),  # inside the first group
        ("damped, secant and the first command averaged", 5),  # after a rise, from the group
    ],
)
def test_a_killed_run_resumed_is_the_uninterrupted_run(
    name, kill_at, arm, setup, monkeypatch, tmp_path
):
    options, script, _ = SCENARIOS[name]
    whole, _, res = _run(arm, setup, monkeypatch, tmp_path / "whole", options, script)
    with pytest.raises(KeyboardInterrupt):
        _run(arm, setup, monkeypatch, tmp_path / "cut", options, script, die_at=kill_at)
    assert len(RunDirectory(tmp_path / "cut").ledger()) == kill_at
    target, start = setup
    cut = EventCell(arm, target, **script)
    cut.n = kill_at  # the lab goes on with its next play
    _spy(cut, monkeypatch)
    params = ILCParams(rope_model=ROPE, gain=1.0, **options)
    again = learn(cut, target, start, arm, params, run_dir=tmp_path / "cut", resume=True)
    assert _ledger(tmp_path / "cut") == _ledger(tmp_path / "whole")
    assert again.stopped_because == res.stopped_because
    for a, b in zip(cut.played, whole.played[kill_at:], strict=True):
        np.testing.assert_array_equal(a, b)


def test_an_unknown_rule_names_the_valid_ones():
    with pytest.raises(ConfigError) as e:
        stop_rule("patience")
    assert str(e.value) == (
        "stop_rule: unknown stop rule 'patience' (valid choices: retry, success, confirm, "
        "plateau, safeguard, average, explore, damped, gain)"
    )
    assert isinstance(e.value, FlyknotError)
    with pytest.raises(ConfigError, match=r"unknown stop rule 3 \(valid choices: retry, "):
        stop_rule(3)
    with pytest.raises(ConfigError, match=r"unknown stop rule 'x' \(valid choices: retry, "):
        StopRules(ILCParams(), names=("retry", "x"))
    rules = StopRules(ILCParams(), names=("retry", "gain"))
    with pytest.raises(ConfigError) as e:
        rules["confirm"]
    assert str(e.value) == "stop_rule: no stop rule 'confirm' (valid choices: retry, gain)"


def test_the_registry_is_the_order_the_loop_asks():
    assert list(STOPS) == [
        "retry", "success", "confirm", "plateau", "safeguard", "average", "explore", "damped",
        "gain",
    ]  # fmt: skip
    for name, rule in STOPS.items():
        assert rule.name == name and rule.description and rule.__doc__
        assert stop_rule(name) is rule
    rules = StopRules(ILCParams())
    assert [r.name for r in rules.rules] == list(STOPS)
    assert rules.w_control() is None
    assert StopRules(ILCParams(step="damped")).w_control() == DampingParams().start


class StopAtCost(StopRule):
    """Stop once a trial measures a cost below ``BOUND`` (a rule a test adds)."""

    name = "cost"
    description = "stop at a small measured cost"
    BOUND = 1e-3

    def verdict(self, trial):
        c = trial.summary.cost
        return Ruling(STOP, self.name, "small cost") if c is not None and c < self.BOUND else None


def test_a_new_rule_is_one_class_and_one_registry_line(arm, setup, monkeypatch, tmp_path):
    monkeypatch.setattr(stops, "STOPS", {"cost": StopAtCost, **STOPS})
    shots = _loop_states(monkeypatch)
    _, params, res = _run(arm, setup, monkeypatch, tmp_path / "run", {"max_trials": 8}, {})
    assert res.stopped_because == "small cost"
    assert res.costs[-1] < StopAtCost.BOUND <= min(c for c in res.costs[:-1])
    target, start = setup
    n = len(res.trials)
    assert _resumed(tmp_path / "run", n, start, target, arm, params) == shots[n]
    # a run resumed after the stop plays nothing more
    again = learn(
        EventCell(arm, target), target, start, arm, params, run_dir=tmp_path / "run", resume=True
    )
    assert again.stopped_because == "small cost" and again.trials == res.trials


def test_a_chain_without_a_last_rule_says_so():
    rules = StopRules(ILCParams(), names=("success",))

    class Line(Trial):
        def record(self):
            raise AssertionError

        def cost_at(self, t):
            raise AssertionError

        def own_update(self):
            return None, None

        def average_over(self, group):
            return None

    line = TrialSummary(0, 0, None, None, False, 1.0, True, "solved", 0.5, "update", 0.0)
    with pytest.raises(ConfigError, match="no rule ruled on trial 0: the last must always rule"):
        rules.verdict(Line(line, np.zeros((10, 8)), None))


def test_a_ledger_that_does_not_follow_the_rules_is_refused(arm, setup, monkeypatch, tmp_path):
    _run(arm, setup, monkeypatch, tmp_path / "run", {"max_trials": 3}, {})
    target, start = setup
    p = tmp_path / "run" / "ledger.jsonl"
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0], lines[2]]) + "\n")  # trial 1 left out
    with pytest.raises(ConfigError, match="ledger line 2 \\(trial 2\\) does not follow"):
        learn(
            EventCell(arm, target),
            target,
            start,
            arm,
            ILCParams(rope_model=ROPE, max_trials=4),
            run_dir=tmp_path / "run",
            resume=True,
        )


def test_the_plateau_stops_after_patience_trials_without_progress(
    arm, setup, monkeypatch, tmp_path
):
    """Progress is a cost below the best by more than the noise floor: with a floor above
    every cost after the first trial, the loop stops after ``patience`` more trials; with
    none, it learns on to its budget."""
    options = {"max_trials": 8, "plateau": PlateauParams(patience=2, noise=1e3)}
    _, _, res = _run(arm, setup, monkeypatch, tmp_path / "a", options, {})
    assert res.stopped_because == "plateau" and len(res.trials) == 3
    options = {"max_trials": 4, "plateau": PlateauParams(patience=2, noise=0.0)}
    _, _, res = _run(arm, setup, monkeypatch, tmp_path / "b", options, {})
    assert res.stopped_because != "plateau"  # every trial of the model-as-lab lowers the cost
    rule = stops.Plateau(ILCParams(plateau=PlateauParams(patience=2, noise=0.1)))
    for cost, since in ((1.0, 0), (0.95, 1), (None, 2), (0.85, 0)):
        rule.observe(_Line(cost))
        assert rule.since == since
    assert rule.best == 0.85


def _seen(k, cost, knot):
    """A counted trial as a rule sees it: its index, cost and verdict (its command: k
    everywhere; a rule that asks for its record or update is not tested with it)."""
    summary = TrialSummary(
        trial=k, attempt=0, fault=None, knot="trefoil" if knot else "unknot",
        tracking_lost=cost is None, cost=cost, update_solved=True, update_status="solved",
        predicted_cost_after=None, action="update", wall_s=0.0,
        verdict={"klass": "knot" if knot else "unknot"},
    )  # fmt: skip
    hooks = dict.fromkeys(("record", "cost_at", "own_update", "average_over"))
    return type("Seen", (Trial,), hooks)(summary, np.full((10, 8), float(k)), None)


@pytest.mark.parametrize(
    ("costs_knots", "rulings"),
    [
        # the paper's rope-1 seed 1: a knot while the cost falls 8.5 -> 2.52, another at 2.37
        ([(8.5, False), (2.52, True), (2.37, True)], [None, None, "success (converged)"]),
        # a rise is converged too; a fall of exactly the band is (c_k >= 0.7 c*)
        ([(3.0, False), (3.2, True)], [None, "success (converged)"]),
        ([(3.0, False), (2.1, True)], [None, "success (converged)"]),
        (
            [(3.0, False), (2.09, True), (2.0, False), (2.5, True)],
            [None, None, None, "success (converged)"],
        ),
        # a knot with nothing measured before it, or without a cost, learns on
        ([(3.0, True), (None, True), (2.9, True)], [None, None, "success (converged)"]),
        # the last trial stops at its knot whatever its cost
        ([(9.0, False), (8.0, False), (7.0, False), (1.0, True)], [None, None, None, "success"]),
    ],
)
def test_a_knot_stops_the_converged_rule_once_the_cost_stops_falling(costs_knots, rulings):
    """c_k >= (1 - nu) min_{j<k} c_j with nu = damping.noise 0.3 (``converged_knot``)."""
    params = ILCParams(
        max_trials=4, step="damped", converged_knot=True, damping=DampingParams(noise=0.3)
    )
    rule = stops.StopAtSuccess(params)
    got = []
    for k, (cost, knot) in enumerate(costs_knots):
        trial = _seen(k, cost, knot)
        rule.observe(trial)
        ruling = rule.verdict(trial)
        got.append(None if ruling is None else ruling.why)
    assert got == rulings
    paper = stops.StopAtSuccess(ILCParams(max_trials=4))
    trial = _seen(0, 8.5, True)
    paper.observe(trial)
    assert paper.verdict(trial).why == "success"  # the paper's: the first knot
    for off in ({"stop_at_success": False}, {"confirm": (2, 3)}):  # no stop at a knot here
        rule = stops.StopAtSuccess(ILCParams(max_trials=4, converged_knot=True, **off))
        for k, (cost, knot) in enumerate([(8.5, False), (8.4, True)]):
            trial = _seen(k, cost, knot)
            rule.observe(trial)
            assert rule.verdict(trial) is None
        assert rule.tied is None  # nor does it keep a command


def test_the_converged_knot_learns_on_past_a_falling_knot(arm, setup, monkeypatch, tmp_path):
    """On the model-as-lab every update lowers the cost far beyond the noise band, so a knot
    on trials 2-6 learns on to the last trial, which stops at its knot; the paper's rule
    stops at the first."""
    options, script, _ = SCENARIOS["converged knot"]
    cell, _, res = _run(arm, setup, monkeypatch, tmp_path / "a", options, script)
    costs = [s.cost for s in res.trials]
    assert all(b < 0.7 * a for a, b in itertools.pairwise(costs)), costs
    assert res.first_success_trial == 1
    assert len(res.trials) == 6 and res.stopped_because == "success"
    np.testing.assert_array_equal(res.final_knots, cell.played[-1])
    paper = {k: v for k, v in options.items() if k != "converged_knot"}
    _, _, first = _run(arm, setup, monkeypatch, tmp_path / "b", paper, script)
    assert len(first.trials) == 2 and first.stopped_because == "success"
    # a knot that never converged before the budget ran out: the command of the last tie
    cell, _, res = _run(arm, setup, monkeypatch, tmp_path / "c", options, {"ties": {1, 3}})
    assert res.stopped_because == "max_trials (knot tied)" and len(res.trials) == 6
    np.testing.assert_array_equal(res.final_knots, cell.played[3])
    assert not np.array_equal(res.final_knots, cell.played[5])


class _Line:
    """A counted trial as the plateau sees it: its cost."""

    def __init__(self, cost):
        self.summary = type("S", (), {"cost": cost})()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ({"patience": -1}, "plateau.patience: must be an integer >= 0, got -1"),
        ({"patience": True}, "plateau.patience: must be an integer >= 0, got True"),
        ({"noise": -0.1}, "plateau.noise: must be a finite number >= 0, got -0.1"),
    ],
)
def test_plateau_settings_are_checked(value, message):
    with pytest.raises(ConfigError) as e:
        PlateauParams(**value)
    assert str(e.value).startswith(message)


def test_an_exploration_offset_is_seeded_scaled_and_on_the_arm_rows():
    r = stops.exploration_offset(0.05, 3, 4)
    assert r.shape == (10, 8)
    assert np.sqrt(np.mean(r[:7] ** 2)) == pytest.approx(0.05, rel=1e-12)
    assert not np.any(r[7:])
    np.testing.assert_array_equal(r, stops.exploration_offset(0.05, 3, 4))
    assert not np.allclose(r, stops.exploration_offset(0.05, 3, 5))
    assert not np.allclose(r, stops.exploration_offset(0.05, 4, 4))


def test_exploring_waits_for_patience_near_the_floor_and_a_new_best_hands_back():
    """Costs 5, 1, 3 (a rise beyond the band), 1.2, 1.4 (patience 2, band 0.5): the fifth
    trial explores from the second; a trial that then lowers the best cost is the damped
    step's again."""
    explore = ExploreParams(size=0.1, patience=2, band=0.5)
    rule = stops.Explore(ILCParams(step="damped", explore=explore))

    rulings = []
    for k, cost in enumerate([5.0, 1.0, 3.0, 1.2, 1.4, 0.5]):
        trial = _seen(k, cost, knot=False)
        rule.observe(trial)
        rulings.append(rule.verdict(trial))
    assert [r is not None for r in rulings] == [False, False, False, False, True, False]
    assert rulings[4].kind == stops.STEP and rulings[4].rule == "explore"
    assert rule.best.summary.trial == 5 and rule.since == 0
    off = stops.Explore(ILCParams(step="damped"))  # size 0: never
    for k, cost in enumerate([5.0, 6.0, 7.0, 8.0]):
        trial = _seen(k, cost, knot=False)
        off.observe(trial)
        assert off.verdict(trial) is None


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ({"size": -0.1}, "explore.size: must be a finite number >= 0, got -0.1"),
        ({"patience": 0}, "explore.patience: must be an integer >= 1, got 0"),
        ({"band": -1}, "explore.band: must be a finite number >= 0, got -1"),
        ({"w_control": 0.0}, "explore.w_control: must be a finite number > 0, got 0.0"),
        ({"seed": "a"}, "explore.seed: must be an integer >= 0, got 'a'"),
    ],
)
def test_bad_explore_settings_raise_exact_messages(value, message):
    with pytest.raises(ConfigError) as e:
        ExploreParams(**value)
    assert str(e.value) == message


def test_a_step_from_an_averaged_best_is_on_its_groups_mean_error(
    arm, setup, monkeypatch, tmp_path
):
    """After the fault the damped step goes back to the averaged first command and solves
    about it again: on the mean error of its three plays, at lambda 0.25 halved by the new
    best and grown x4 by the fault."""
    from learner import ilc_step

    calls = []
    assess = ilc_step.assess

    def spy(record, command, ctx, k, attempt, extra_records=(), **kw):
        calls.append((k, len(extra_records), kw.get("w_control"), kw.get("judged", True)))
        return assess(record, command, ctx, k, attempt, extra_records, **kw)

    monkeypatch.setattr(ilc_step, "assess", spy)
    options, script, _ = SCENARIOS["damped, secant and the first command averaged"]
    _, _, res = _run(arm, setup, monkeypatch, tmp_path / "run", options, script)
    assert [s.average for s in res.trials[:3]] == [1, 2, 3]
    assert (2, 2, 0.25, True) in calls  # the group's update, at the loop's own lambda
    assert (2, 2, 0.5, False) in calls  # from the best again after the fault


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"converged_knot": "yes"}, "converged_knot: must be true or false, got 'yes'"),
    ],
)
def test_bad_converged_knot_settings_raise_exact_messages(kwargs, message):
    with pytest.raises(ConfigError) as e:
        ILCParams(**kwargs)
    assert str(e.value) == message

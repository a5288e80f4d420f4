"""Scenario files: every shipped file validates; bad input gets exact messages."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from flyknot.constants import SCENARIOS_DIR
from flyknot.errors import ConfigError
from flyknot_app.learner_settings import SCENARIO_DEMO, SCENARIO_WINDOW, scenario_weights
from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary
from flyknot_app.scenario import (
    RUN_KEYS,
    limit_runs,
    load_scenario,
    parse_overrides,
    parse_scenario,
)

FILES = sorted(SCENARIOS_DIR.glob("*.toml"))


def test_the_paper_experiments_are_all_there():
    names = {p.stem for p in FILES}
    for n in (
        "quick",
        "learn-rope1",
        "01-tracking",
        "02-objectives",
        "03-ropes",
        "04-success-rate",
        "05-demos",
        "06-transfer",
        "07-sensitivity",
    ):
        assert n in names


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_every_scenario_file_validates(path: Path):
    scen = load_scenario(str(path))
    assert scen.runs
    waves = scen.order()
    assert sum(len(w) for w in waves) == len(scen.runs)
    # what the gym envs, the baselines and the floor take as "the scenarios'" is each file's
    for run in scen.runs:
        assert run.learner.update.weights == scenario_weights(), run.name
        assert run.window == SCENARIO_WINDOW, run.name
        assert run.demo == SCENARIO_DEMO or scen.kind == "demos", run.name
        # a knot the learner converged on, but where a confirmation is the stop or none is
        stops_at_knot = run.learner.stop_at_success and run.learner.confirm is None
        assert run.learner.converged_knot is stops_at_knot, run.name


def test_transfer_covers_all_49_pairs_after_the_learning_runs():
    scen = load_scenario("06-transfer")
    waves = scen.order()
    assert [len(w) for w in waves] == [7, 49]
    pairs = {(r.start_from, r.rope) for r in waves[1]}
    assert len(pairs) == 49


def test_sensitivity_matches_the_paper_table():
    scen = load_scenario("07-sensitivity")
    got = [(r.learner.rope_model.stiffness, r.learner.rope_model.end_mass) for r in scen.runs]
    assert got == [(1e5, 5.0), (1e4, 5.0), (1e3, 5.0), (1e2, 5.0), (1e5, 0.05), (1e5, 0.005)]


def test_overrides_apply_to_every_run():
    ov = parse_overrides(["max_trials=2", "rope_model.stiffness=1e3", "settle_s=0.5"])
    scen = load_scenario("03-ropes", ov)
    assert all(r.learner.max_trials == 2 and r.settle_s == 0.5 for r in scen.runs)
    assert all(r.learner.rope_model.stiffness == 1e3 for r in scen.runs)


def test_limit_runs_keeps_dependencies():
    scen = load_scenario("06-transfer", parse_overrides(["max_runs=1"]))
    assert [r.name for r in scen.runs] == ["learn-rope1"]
    doc = {"run": [{"name": "b", "start_from": "a"}, {"name": "a"}, {"name": "c"}]}
    sub = limit_runs(parse_scenario(doc, name="x"), 1)
    assert [r.name for r in sub.runs] == ["b", "a"]  # b needs a; c is dropped
    assert [[r.name for r in w] for w in sub.order()] == [["a"], ["b"]]


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        (
            {"kind": "dance", "run": [{"name": "a"}]},
            "kind: unknown value 'dance' (valid choices: learn, track, transfer, sensitivity, "
            "objectives, demos, smoke)",
        ),
        (
            {"run": [{"name": "a", "rope": 9}]},
            "rope: unknown value 9 (valid choices: 1, 2, 3, 4, 5, 6, 7)",
        ),
        (
            {"run": [{"name": "a", "objective": "best"}]},
            "objective: unknown value 'best' (valid choices: critical, equal, launch)",
        ),
        (
            {"run": [{"name": "a", "max_trial": 3}]},
            # every run option, in field order (the run's, the loop's, the update's)
            f"run[0].max_trial: unknown field (valid choices: {', '.join(RUN_KEYS)})",
        ),
        ({"run": [{"name": "a"}, {"name": "a"}]}, "run.name: duplicate run names: a"),
        (
            {"run": [{"name": "a", "start_from": "b"}]},
            "run 'a' start_from: unknown value 'b' (valid choices: )",
        ),
        (
            {"run": [{"name": "a", "rope_model": {"stiff": 1.0}}]},
            "run[0].rope_model.stiff: unknown field (valid choices: stiffness, damping, "
            "link_mass, end_mass, link_length, n_links, dt, gravity)",
        ),
        (
            {"runs": []},
            "runs: unknown top-level field (valid choices: name, description, kind, "
            "paper, ropes, cell, defaults, run, grid)",
        ),
        ({}, "run: the scenario defines no runs"),
    ],
)
def test_bad_scenarios_have_exact_messages(doc, message):
    with pytest.raises(ConfigError) as e:
        parse_scenario(doc, name="x")
    assert str(e.value) == message


def test_unknown_scenario_lists_names():
    with pytest.raises(
        ConfigError, match=r"no scenario file or name 'nope' \(valid choices: .*quick"
    ):
        load_scenario("nope")


def test_gain_and_weight_overrides():
    scen = load_scenario("quick", parse_overrides(["gain=0.5", "weights.w_control=5"]))
    learner = scen.runs[0].learner
    assert learner.gain == 0.5 and learner.update.weights.w_control == 5
    with pytest.raises(ConfigError, match=r"gain: must lie in \(0, 1\], got 2"):
        load_scenario("quick", parse_overrides(["gain=2"]))
    with pytest.raises(ConfigError, match="weights key: unknown value 'w_x'"):
        parse_overrides(["weights.w_x=1"])


def test_trust_region_override_and_bad_value():
    assert load_scenario("quick").runs[0].learner.update.trust_region is None
    scen = load_scenario("quick", parse_overrides(["trust_region=0.1"]))
    assert scen.runs[0].learner.update.trust_region == 0.1
    assert (
        load_scenario("quick", parse_overrides(["trust_region=none"]))
        .runs[0]
        .learner.update.trust_region
        is None
    )
    with pytest.raises(ConfigError) as e:
        load_scenario("quick", parse_overrides(["trust_region=-1"]))
    assert str(e.value) == "trust_region: must be a finite number > 0, got -1"


def test_demo_window_fields(tmp_path):
    bare = tmp_path / "bare.toml"
    bare.write_text('name = "bare"\nkind = "learn"\n[[run]]\nname = "r"\n')
    assert load_scenario(str(bare)).runs[0].window == (0.035, 0.05)  # the paper's
    assert load_scenario("quick").runs[0].window == (0.25, 0.0)  # the scenario files' own
    scen = load_scenario("05-demos", parse_overrides(["follow_through_s=0.1", "path_frac=0"]))
    assert all(r.window == (0.1, 0.0) for r in scen.runs)
    with pytest.raises(ConfigError) as e:
        load_scenario("quick", parse_overrides(["path_frac=1"]))
    assert str(e.value) == "path_frac: must lie in [0, 1), got 1"
    with pytest.raises(ConfigError) as e:
        load_scenario("quick", parse_overrides(["follow_through_s=-0.1"]))
    assert str(e.value) == "follow_through_s: must be a finite number >= 0, got -0.1"


def test_guess_cache_name_separates_windows_and_base_heights():
    from flyknot_app.runner import guess_cache_name

    assert guess_cache_name("fast", (0.035, 0.05), 1.2) == "fast_base1.2000.npz"
    assert guess_cache_name("/x/robot.npz", (0.25, 0.0), 0.9) == "robot_ft0.25_p0_base0.9000.npz"


def test_a_lab_with_another_base_height_gets_its_own_initial_guess(tmp_path, monkeypatch):
    """The guess keeps the fingertip z_min above the floor: a cell whose base stands lower
    than the simulated one must not start from the simulated lab's cached guess."""
    import flyknot_app.runner as runner
    from learner import initial_guess as ig

    heights = []

    def fake_guess(t, p, R, T, robot, params, on_iteration=None):
        heights.append(params.base_height)

        from types import SimpleNamespace

        return SimpleNamespace(
            success=True,
            status="ok",
            cost=0.0,
            solve_time=0.0,
            max_errors={},
            rms_errors={},
            knots=np.full((10, 8), params.base_height),
        )

    monkeypatch.setattr(ig, "initial_guess", fake_guess)
    monkeypatch.setenv("FLYKNOT_CACHE", str(tmp_path / "cache"))  # no stand-in guess kept
    a, _ = runner.initial_knots("robot", tmp_path, None, 0.005, 1.3, (0.25, 0.0))
    b, _ = runner.initial_knots("robot", tmp_path, None, 0.005, 0.8, (0.25, 0.0))
    again, _ = runner.initial_knots("robot", tmp_path, None, 0.005, 1.3, (0.25, 0.0))
    assert heights == [1.3, 0.8]  # the third call is the first one's cache
    assert a[0, 0] == again[0, 0] == 1.3 and b[0, 0] == 0.8


def test_a_changed_demonstration_file_gets_a_new_initial_guess(tmp_path, monkeypatch):
    """The cache is named by the demonstration's stem; a guess made from another version of
    the file (another content) is made again, not reused."""
    import shutil

    import flyknot_app.runner as runner
    from flyknot.constants import DEMOS_DIR
    from learner import initial_guess as ig

    made = []

    def fake_guess(t, p, R, T, robot, params, on_iteration=None):
        from types import SimpleNamespace

        made.append(T)
        return SimpleNamespace(
            success=True, status="ok", cost=0.0, solve_time=0.0, max_errors={}, rms_errors={},
            knots=np.full((10, 8), float(len(made))),
        )  # fmt: skip

    monkeypatch.setattr(ig, "initial_guess", fake_guess)
    monkeypatch.setenv("FLYKNOT_CACHE", str(tmp_path / "cache"))  # no stand-in guess kept
    demo = tmp_path / "mine.npz"
    shutil.copy(DEMOS_DIR / "slow.npz", demo)
    a, _ = runner.initial_knots(str(demo), tmp_path, None, 0.005, 1.0)
    again, _ = runner.initial_knots(str(demo), tmp_path, None, 0.005, 1.0)
    shutil.copy(DEMOS_DIR / "fast.npz", demo)  # same name, another demonstration
    other, info = runner.initial_knots(str(demo), tmp_path, None, 0.005, 1.0)
    assert len(made) == 2 and a[0, 0] == again[0, 0] == 1.0 and other[0, 0] == 2.0
    assert info["demo_sha256"] == runner.hashlib.sha256(demo.read_bytes()).hexdigest()


def test_bad_override():
    with pytest.raises(ConfigError, match="--set: expected key=value, got 'max_trials'"):
        parse_overrides(["max_trials"])
    with pytest.raises(ConfigError, match="--set key: unknown value 'trials'"):
        parse_overrides(["trials=3"])


def test_window_changes_the_target():
    from flyknot_app.runner import prepare_target

    _, paper = prepare_target("fast", 0.005)
    _, longer = prepare_target("fast", 0.005, (0.25, 0.0))
    assert paper.T - paper.t_c == pytest.approx(0.035, abs=0.005)
    assert longer.T - longer.t_c == pytest.approx(0.25, abs=0.005)
    assert longer.t_c > paper.t_c  # t_0 moved back to the start of the hand motion


def test_outcome_line_for_learning_and_tracking():
    from flyknot_app.reports.report import outcome_line

    runs = [
        RunSummary({"name": "a"}, trials_to_success=3, repeat_classes=["knot", "unknot"]),
        RunSummary({"name": "b"}, repeat_classes=["wrapped_at_grip", "knot"]),
        RunSummary({"name": "c"}),
    ]
    assert outcome_line("learn", runs) == "Knot learned in 1 of 3 runs."
    assert outcome_line("track", runs) == (
        "Tracking alone (no learning): the first trial tied in 1 of 3 runs; "
        "the repeats tied in 2 of 4."
    )
    assert outcome_line("track", runs[2:]) == (
        "Tracking alone (no learning): the first trial tied in 0 of 1 runs."
    )


def test_wilson_interval_known_values():
    from flyknot_app.reports.report import wilson_interval

    # the bounds solve |p - k/n| = z sqrt(p (1 - p) / n) (z = 1.96)
    for k, n in [(15, 40), (1, 10), (7, 20), (39, 40)]:
        for p in wilson_interval(k, n):
            assert abs(p - k / n) == pytest.approx(1.96 * (p * (1 - p) / n) ** 0.5, rel=1e-9)
    lo, hi = wilson_interval(15, 40)
    assert (round(lo, 3), round(hi, 3)) == (0.242, 0.530)
    assert wilson_interval(0, 20)[0] == 0.0 and 0.15 < wilson_interval(0, 20)[1] < 0.17
    assert wilson_interval(40, 40)[1] == 1.0
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def test_confirm_field_from_toml_and_command_line():
    scen = load_scenario("learn-rope1", parse_overrides(["confirm=19/20", "step=gain"]))
    assert scen.runs[0].learner.confirm == (19, 20)
    scen = load_scenario("learn-rope1", parse_overrides(["confirm=[7, 8]"]))  # as the file
    assert scen.runs[0].learner.confirm == (7, 8)
    with pytest.raises(ConfigError) as e:  # not TOML: the string, named by the field
        load_scenario("learn-rope1", parse_overrides(["confirm=[7,"]))
    assert str(e.value) == "confirm: must be [k, n] (or k/n) with 1 <= k <= n, got '[7,'"
    ov = parse_overrides(["rope_model={ stiffness = 3.0, damping = 1.0 }"])
    assert load_scenario("quick", ov).runs[0].learner.rope_model.stiffness == 3.0
    from flyknot.options import from_mapping
    from flyknot_app.scenario import RunSpec

    def run(**options):
        return from_mapping(RunSpec, {"name": "a", **options})

    assert run(confirm=[2, 3]).learner.confirm == (2, 3)
    with pytest.raises(ConfigError) as e:
        run(confirm="3/2")
    assert str(e.value) == "confirm: must be [k, n] (or k/n) with 1 <= k <= n, got '3/2'"
    with pytest.raises(ConfigError) as e:
        run(confirm=[1, 2], stop_at_success=False)
    assert str(e.value) == "confirm: needs stop_at_success = true"


def test_paper_settings_set_the_papers_learner(tmp_path, monkeypatch):
    from flyknot_app import cli, runner
    from flyknot_app.learner_settings import PAPER_SETTINGS

    scen = load_scenario("learn-rope1", parse_overrides(list(PAPER_SETTINGS)))
    run = scen.runs[0]
    assert (run.learner.gain, run.path_frac, run.follow_through_s) == (1.0, 0.05, 0.035)
    assert run.learner.update.weights.w_control == 0.5
    assert (run.learner.step, run.learner.update.jacobian) == ("gain", "model")
    assert run.learner.update.follow_through is True
    assert (run.learner.rope_model.stiffness, run.learner.rope_model.damping) == (1e5, 50.0)
    seen = {}

    def fake_run(scen, out, **kw):
        seen["scen"], seen["overrides"] = scen, kw["overrides"]
        return ScenarioSummary(scen.name, scen.kind, ())

    monkeypatch.setattr(runner, "run_scenario", fake_run)
    argv = ["run", "learn-rope1", "--paper-settings", "--set", "gain=0.7"]
    assert cli.main([*argv, "--out", str(tmp_path / "r")]) == 0
    assert seen["overrides"]["gain"] == 0.7  # a later --set wins
    under = seen["overrides"]["defaults"]
    assert under["rope_model"] == {"stiffness": 1e5, "damping": 50}
    assert under["objective"] == "critical"
    assert seen["scen"].runs[0].follow_through_s == 0.035
    assert seen["scen"].runs[0].learner.gain == 0.7


def test_paper_settings_lie_under_each_runs_own_fields():
    """The paper's settings replace a scenario's defaults, not what its runs compare: the
    equal run keeps its objective, each sensitivity run its rope model; a --set wins over all."""
    objectives = load_scenario("02-objectives", parse_overrides(None, paper_settings=True))
    assert [r.learner.update.objective for r in objectives.runs] == ["critical", "equal", "launch"]
    sens = load_scenario("07-sensitivity", parse_overrides(None, paper_settings=True))
    models = [(r.learner.rope_model.stiffness, r.learner.rope_model.end_mass) for r in sens.runs]
    assert models == [(1e5, 5.0), (1e4, 5.0), (1e3, 5.0), (1e2, 5.0), (1e5, 0.05), (1e5, 0.005)]
    assert {r.learner.rope_model.damping for r in sens.runs} == {50.0}
    assert {r.learner.update.jacobian for r in sens.runs} == {"model"}
    top = parse_overrides(["jacobian=model"], paper_settings=True)
    assert {r.learner.update.jacobian for r in load_scenario("02-objectives", top).runs} == {
        "model"
    }


@pytest.mark.parametrize(
    ("scenario", "pair", "values"),
    [
        ("02-objectives", "objective=equal", "'critical', 'equal', 'launch'"),
        ("03-ropes", "rope=2", "1, 2, 3, 4, 5, 6, 7"),
        (
            "05-demos",
            "demo=fast-paced",
            "'fast-paced', 'inverse-paced', 'slow-paced', 'swipe-paced'",
        ),
        ("07-sensitivity", "rope_model.end_mass=1", "0.005, 0.05, 5.0"),
    ],
)
def test_a_set_of_what_the_runs_compare_is_refused(scenario, pair, values):
    """A --set of a field every run sets itself would run one setting under every run's own
    name: refused, naming the field and the runs' values; a field some runs leave to the
    defaults (02-objectives' jacobian, which only the equal run sets) is still set."""
    key = pair.split("=")[0]
    message = (
        f"--set {key}: {scenario!r} compares its runs by {key} ({values}); a --set would give "
        "every run the same value under its own name: set it on a scenario that does not vary "
        "it (learn-rope1)"
    )
    with pytest.raises(ConfigError) as e:
        load_scenario(scenario, parse_overrides([pair]))
    assert str(e.value) == message
    assert load_scenario(scenario, parse_overrides(None, defaults=[pair])).runs


@pytest.mark.parametrize("name", sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml")))
def test_every_scenarios_description_says_what_it_runs(name):
    """The demonstration, the ropes, the trial budget, the repeats and a fixed settle."""
    scen = load_scenario(name)
    text = scen.description
    demos = {r.demo for r in scen.runs}
    for demo in demos:
        assert ("robot demonstration" if demo == "robot" else demo.capitalize()) in text, demo
    ropes = {r.rope for r in scen.runs}
    if len(ropes) == 1:
        assert f"rope {next(iter(ropes))}" in text
    else:
        assert any(w in text for w in ("each rope", "every rope", "all 7 ropes"))
    assert f"{max(r.learner.max_trials for r in scen.runs)} trials" in text
    repeats = max(r.repeats for r in scen.runs)
    if repeats:
        assert f"{repeats} repeats" in text or f"{repeats} times" in text
    settles = {r.settle_s for r in scen.runs}
    if settles != {None}:
        assert all(f"{s:g} s settle" in text for s in settles)


def test_the_smoke_line_says_whether_the_pipeline_worked():
    from flyknot_app.reports.report import outcome_line

    ok = RunSummary(
        {"name": "a"},
        costs=[0.6, 0.4],
        faults=[None, None],
        verdicts=[{"klass": "unknot"}, {"klass": "wrapped_at_grip"}],
    )
    assert outcome_line("smoke", [ok]) == (
        "Smoke run: the pipeline works: 2 trials played (0 faulted), judged (unknot 1, "
        "wrapped_at_grip 1), the critical-point error measured in 2."
    )
    bad = replace(ok, costs=[None], faults=["joint 4 torque limit"], verdicts=[None])
    assert outcome_line("smoke", [bad]).startswith("Smoke run: the pipeline FAILED: 1 trials")


def test_a_runs_learner_options_are_the_loops():
    """A run's learner options are the loop's and the update's, read by one generic parser:
    every field of ILCParams and UpdateSettings (but the cell's limits) is a run option."""
    from dataclasses import fields

    from flyknot.options import from_mapping, option_names
    from flyknot_app.scenario import RUN_KEYS, RunSpec
    from learner.ilc import ILCParams
    from learner.update import UpdateSettings

    loop = [f.name for f in fields(ILCParams) if f.name != "update"]
    update = [f.name for f in fields(UpdateSettings) if f.name != "limits"]
    assert option_names(ILCParams) == (*loop, *update)
    own = ("name", "rope", "demo", "seed", "repeats", "settle_s", "start_from")
    own += ("follow_through_s", "path_frac", "label")
    assert (*own, *option_names(ILCParams)) == RUN_KEYS
    values = {"name": "a", "gain": 0.5, "weights": {"w_control": 5.0}}
    spec = from_mapping(RunSpec, {**values, "rope_model": {"damping": 0.5}, "margin": 0.25})
    params = spec.learner
    assert (params.gain, params.update.weights.w_control, params.rope_model.damping) == (
        0.5,
        5.0,
        0.5,
    )
    assert params.update.margin == 0.25 and params.update.weights.w_crit_pos == 25.0
    with pytest.raises(ConfigError, match=r"^gain: must lie in \(0, 1\], got 2$"):
        from_mapping(RunSpec, {"name": "a", "gain": 2})


def test_an_initial_guess_is_reused_from_the_machines_cache(tmp_path, monkeypatch):
    """A scenario run into a new directory reuses the guess this machine made from the same
    inputs (and copies it into the run directory); other inputs make their own."""
    import flyknot_app.runner as runner
    from learner import initial_guess as ig

    made = []

    def fake_guess(t, p, R, T, robot, params, on_iteration=None):
        from types import SimpleNamespace

        made.append(params.base_height)
        return SimpleNamespace(
            success=True, status="ok", cost=0.0, solve_time=0.0, max_errors={}, rms_errors={},
            knots=np.full((10, 8), float(len(made))),
        )  # fmt: skip

    monkeypatch.setattr(ig, "initial_guess", fake_guess)
    monkeypatch.setenv("FLYKNOT_CACHE", str(tmp_path / "cache"))
    a, _ = runner.initial_knots("robot", tmp_path / "a", None, 0.005, 1.3)
    b, info = runner.initial_knots("robot", tmp_path / "b", None, 0.005, 1.3)
    assert made == [1.3] and a[0, 0] == b[0, 0] == 1.0
    assert (
        tmp_path
        / "b"
        / "initial_guess"
        / runner.guess_cache_name("robot", (runner.FOLLOW_THROUGH_S, runner.PATH_FRAC), 1.3)
    ).is_file()
    assert (
        info["demo_sha256"]
        == runner.hashlib.sha256(runner.demo_path("robot").read_bytes()).hexdigest()
    )
    runner.initial_knots("robot", tmp_path / "c", None, 0.005, 0.8)  # another base height
    runner.initial_knots("robot", tmp_path / "d", None, 0.005, 1.3, (0.1, 0.0))  # window
    assert made == [1.3, 0.8, 1.3]
    assert len(list((tmp_path / "cache" / "initial_guess").glob("*.npz"))) == 3


def test_the_guess_key_names_every_input():
    from flyknot_app.guess_cache import guess_key
    from learner.initial_guess import InitialGuessParams, initial_guess
    from learner.kinematics import RobotModel

    base = ("a" * 64, (0.25, 0.0), 0.005, InitialGuessParams(base_height=1.3), None, initial_guess)
    key = guess_key(*base)
    assert key == guess_key(*base) and len(key) == 32
    changed = [
        ("b" * 64, *base[1:]),
        (base[0], (0.2, 0.0), *base[2:]),
        (*base[:2], 0.004, *base[3:]),
        (*base[:3], InitialGuessParams(base_height=1.0), *base[4:]),
        (*base[:4], RobotModel.from_mjcf(include_damping=False), base[5]),
        (*base[:5], guess_key),
    ]
    assert len({guess_key(*c) for c in changed} | {key}) == len(changed) + 1

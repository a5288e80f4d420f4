"""``flyknot paper``: the paper's scenarios over seeds, and the results table read from them."""

from __future__ import annotations

import json
import re

import pytest

from flyknot_app.cli import main
from flyknot_app.reports.paper import (
    paper_table,
    repeats_text,
    transfer_cell,
    trials_text,
)
from flyknot_app.reports.paper_variants import VARIANTS
from flyknot_app.reports.results import git_commit
from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary


def _run(name, seed, tts, n=10, repeats=(), **options):
    return RunSummary(
        {"name": f"{name}-seed{seed}", "seed": seed, "demo": "robot", **options},
        costs=[0.5] * (tts or n),
        trials_to_success=tts,
        repeat_classes=list(repeats),
        judge="verdict",
    )


def test_trials_and_repeats_over_seeds():
    runs = [_run("r", 0, 3, repeats=["knot"] * 38 + ["unknot"] * 2), _run("r", 1, None)]
    runs.append(_run("r", 2, 5, repeats=["knot"] * 40))
    assert trials_text(runs) == "4 (3-5), 2 of 3 seeds tied"
    assert trials_text(runs[1:2]) == "none in 10 (1 seed)"
    assert repeats_text(runs) == "78/80 (91-99 %)"
    assert repeats_text(runs[1:2]) == "-"
    assert transfer_cell(runs) == "4 (2/3)"
    assert transfer_cell(runs[::2]) == "4"
    assert transfer_cell(runs[1:2]) == "-"


def _write(out, name, kind, runs):
    (out / name).mkdir(parents=True)
    doc = ScenarioSummary(name, kind, tuple(runs)).to_json()
    (out / name / "summary.json").write_text(json.dumps(doc))


def test_the_table_has_every_experiment_beside_the_paper(tmp_path):
    _write(tmp_path, "03-ropes", "learn", [_run("rope1", s, 2 + s, rope=1) for s in (0, 1)])
    sens = [
        _run("k1e2-me5", s, None, rope_model={"stiffness": 100.0, "end_mass": 5.0}) for s in (0, 1)
    ]
    _write(tmp_path, "07-sensitivity", "sensitivity", sens)
    transfer = [_run("learn-rope1", 0, 2, rope=1), _run("learn-rope2", 0, 4, rope=2)]
    transfer += [
        _run("r1-on-r2", 0, 3, rope=2, start_from="learn-rope1-seed0"),
        _run("r2-on-r1", 0, None, rope=1, start_from="learn-rope2-seed0"),
    ]
    _write(tmp_path, "06-transfer", "transfer", transfer)
    (tmp_path / "03-ropes" / "manifest.json").write_text(json.dumps({"commit": "abc1234"}))
    resumed = {"commit": "unrecorded", "resumed": [{"commit": "def5678"}, {"commit": "abc1234"}]}
    (tmp_path / "07-sensitivity" / "manifest.json").write_text(json.dumps(resumed))
    text = paper_table(tmp_path, "flyknot paper --seeds 0-1")
    assert "lab seeds 0, 1;" in text and "by `flyknot paper --seeds 0-1` from runs made" in text
    assert "from runs made at abc1234, def5678, unrecorded (each run directory's" in text
    assert "knots in the repeats (with the lab's trial-to-trial variation, whose bracket" in text
    assert "| rope1 | 1 | robot | critical | 2.5 (2-3), 2 of 2 seeds tied | - |" in text
    assert "Paper: All 7 ropes learned within 10 trials" in text
    assert "| 100 | 5 | none in 10 (2 seeds) | >10 |" in text
    assert "| A \\ B | 1 | 2 |" in text
    assert "| 1 |  | 3 |" in text and "| 2 | - |  |" in text
    assert "| r1-on-r2 |" not in text and "| k1e2-me5 |" not in text  # in the tables only


def test_the_papers_learner_settings_stand_beside(tmp_path):
    _write(tmp_path, "03-ropes", "learn", [_run("rope1", s, 2 + s, rope=1) for s in (0, 1)])
    theirs = [_run("rope1", s, None, rope=1, repeats=["knot"]) for s in (0, 1)]
    _write(tmp_path / "paper-settings", "03-ropes", "learn", theirs)
    text = paper_table(tmp_path, "flyknot paper")
    assert "| with the paper's learner settings: trials | knots in repeats |" in text
    row = "| rope1 | 1 | robot | critical | 2.5 (2-3), 2 of 2 seeds tied | - | "
    assert row + "none in 10 (2 seeds) | 2/2 (34-100 %) |" in text


def test_a_directory_without_runs_is_one_line(tmp_path, capsys):
    assert main(["paper", "--out", str(tmp_path), "--table-only"]) == 2
    assert "holds no paper scenario's summary.json" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [["--scenarios", "09-x"], ["--seeds", "x"]])
def test_bad_arguments_are_one_line(tmp_path, capsys, bad):
    assert main(["paper", "--out", str(tmp_path / "p"), *bad]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def _without_pictures(text: str) -> list[str]:
    """The table's lines: a knot's picture is linked from where each copy of the table lies."""
    return [line for line in text.splitlines() if "![" not in line]


@pytest.mark.slow
def test_one_scenario_over_two_seeds_then_resumed(egl, tmp_path, capsys):
    out = tmp_path / "p"
    argv = ["paper", "--seeds", "0-1", "--scenarios", "04-success-rate", "--out", str(out)]
    argv += ["--set", "max_runs=1", "--set", "max_trials=1", "--set", "settle_s=0.2"]
    argv += ["--set", "repeats=1", "--results", str(tmp_path / "results.md")]
    assert main(argv) == 0
    manifest = json.loads((out / "04-success-rate" / "manifest.json").read_text())
    assert manifest["commit"] == git_commit()
    ledger = out / "04-success-rate" / "runs" / "rope1-seed1" / "learning" / "ledger.jsonl"
    before = ledger.read_text()
    text = (tmp_path / "results.md").read_text()
    assert _without_pictures(text) == _without_pictures((out / "results.md").read_text())
    for where, table in ((tmp_path, text), (out, (out / "results.md").read_text())):
        for link in re.findall(r"!\[[^]]*\]\(([^)]+)\)", table):
            assert (where / link).is_file(), link
    assert "Why the learned commands' repeats of `04-success-rate` ended" in text
    assert "| rope 1 | 2 |" in text  # one repeat a seed, under its rope
    assert "img/results/04-success-rate-anatomy.png" in text
    assert (
        "| rope1 | 1 | fast-paced | launch |" in text and "(2 seeds)" in text
    ) or "seeds tied" in text
    assert main(argv) == 2  # the runs are there: --resume or another --out
    assert "use --resume" in capsys.readouterr().err
    assert main([*argv, "--resume"]) == 0
    assert ledger.read_text() == before
    resumed = json.loads((out / "04-success-rate" / "manifest.json").read_text())
    assert {k: v for k, v in resumed.items() if k != "resumed"} == manifest
    assert [r["commit"] for r in resumed["resumed"]] == [git_commit()]
    assert main([*argv, "--paper-settings", "--seeds", "0"]) == 0  # beside, in paper-settings/
    theirs = json.loads((out / "paper-settings" / "04-success-rate" / "summary.json").read_text())
    assert theirs["runs"][0]["gain"] == 1 and theirs["runs"][0]["weights"]["w_control"] == 0.5
    assert "with the paper's learner settings" in (out / "results.md").read_text()


def test_every_variant_stands_beside_under_its_label(tmp_path):
    _write(tmp_path, "03-ropes", "learn", [_run("rope1", s, 2 + s, rope=1) for s in (0, 1)])
    robot = [_run("rope1", s, 1, rope=1) for s in (0, 1)]
    _write(tmp_path / "robot-demo", "03-ropes", "learn", robot)
    _write(tmp_path / "oracle", "03-ropes", "learn", [_run("rope1", 0, 4, rope=1)])
    text = paper_table(tmp_path, "flyknot paper")
    head = (
        "| from the robot demonstration (a command searched in this lab, not the paper's "
        "protocol): trials | knots in repeats | the oracle learner (the same objective with "
        "the lab's own Jacobian, a measuring stick): trials | knots in repeats |"
    )
    assert head in text
    row = "| rope1 | 1 | robot | critical | 2.5 (2-3), 2 of 2 seeds tied | - | "
    assert row + "1 (1-1), 2 of 2 seeds tied | - | 4 (4), 1 of 1 seed tied | - |" in text
    assert "with the paper's learner settings" not in text.split("## ")[1]  # not run: no column


def test_a_variant_runs_with_its_options_into_its_directory(tmp_path, monkeypatch):
    import flyknot_app.reports.paper as paper

    seen = {}

    def fake_run(where, seeds, *, workers, resume, overrides, scenarios):
        seen.update(where=where, overrides=overrides, scenarios=scenarios)
        _write(where, "03-ropes", "learn", [_run("rope1", 0, 2, rope=1)])

    monkeypatch.setattr(paper, "run_paper", fake_run)
    _write(tmp_path, "03-ropes", "learn", [_run("rope1", 0, 5, rope=1)])
    argv = ["paper", "--out", str(tmp_path), "--variant", "robot-demo", "--seeds", "0"]
    assert main([*argv, "--scenarios", "03-ropes", "05-demos", "--set", "max_trials=3"]) == 0
    assert seen["where"] == tmp_path / "robot-demo"
    assert seen["overrides"] == {"max_trials": 3, "defaults": {"demo": "robot"}}
    assert seen["scenarios"] == ["03-ropes"]  # 05-demos names its own demonstrations


def test_an_unknown_variant_is_one_line(tmp_path, capsys):
    assert main(["paper", "--out", str(tmp_path), "--variant", "nope", "--table-only"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "flyknot: error: --variant: unknown variant 'nope' (valid choices: paper-settings, "
        "robot-demo, oracle, paper-velocity, no-follow-through)\n"
    )


def test_the_baselines_stand_beside_ilc_on_rope_1(tmp_path):
    ilc = [_run("rope1", 0, 2, rope=1), _run("rope1", 1, 4, rope=1), _run("rope1", 2, None, rope=1)]
    ilc.append(_run("rope2", 0, 3, rope=2))  # another rope: not in the comparison
    _write(tmp_path, "03-ropes", "learn", ilc)
    for name, tts in (("cma", [None, None, 9]), ("random", [None, None, None])):
        d = tmp_path / "baselines" / name
        d.mkdir(parents=True)
        runs = [
            {"name": name, "seed": s, "costs": [1.0] * (t or 10), "trials_to_success": t}
            for s, t in enumerate(tts)
        ]
        (d / "baseline.json").write_text(json.dumps({"rope": 1, "runs": runs}))
    text = paper_table(tmp_path, "flyknot paper")
    assert "## Baselines from the same start (rope 1)" in text
    assert "| ILC (`03-ropes`) | 2 of 3 | 4 | 1 |" in text  # 2, 4, 11 (no knot in 10)
    assert "| cma (`cma`) | 1 of 3 | 11 | 2.8 |" in text  # 11, 11, 9
    assert "| random (`random`) | 0 of 3 | 11 | 2.8 |" in text


def test_no_baselines_no_section(tmp_path):
    _write(tmp_path, "03-ropes", "learn", [_run("rope1", 0, 2, rope=1)])
    assert "Baselines" not in paper_table(tmp_path, "flyknot paper")


def test_the_results_show_each_scenarios_first_knot(tmp_path, capsys):
    out = tmp_path / "paper"
    _write(out, "03-ropes", "learn", [_run("rope1", 0, 2, rope=1)])
    _write(out, "02-objectives", "objectives", [_run("critical", 0, None, rope=1)])
    verdicts = out / "03-ropes" / "verdicts"
    verdicts.mkdir()
    (verdicts / "runs__rope1-seed0__learning__trial_0001_a0.knot.png").write_bytes(b"first")
    (verdicts / "runs__rope1-seed0__learning__trial_0000_a0.unknot.png").write_bytes(b"no")
    (verdicts / "runs__rope1-seed1__learning__trial_0003_a0.knot.png").write_bytes(b"later")
    docs = tmp_path / "docs"
    stale = docs / "img" / "results" / "05-demos.png"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"old")
    argv = ["paper", "--out", str(out), "--table-only", "--results", str(docs / "results.md")]
    assert main(argv) == 0
    text = (docs / "results.md").read_text()
    assert "The first knot of `03-ropes`: ![a knot of `03-ropes`](img/results/03-ropes.png)" in text
    assert "![a knot of `02-objectives`]" not in text  # no knot there
    assert (docs / "img" / "results" / "03-ropes.png").read_bytes() == b"first"
    assert not stale.exists()  # a picture of an earlier table goes
    own = (out / "results.md").read_text()
    assert "(03-ropes/verdicts/runs__rope1-seed0__learning__trial_0001_a0.knot.png)" in own


def test_a_variant_stands_beside_the_sensitivity_table(tmp_path):
    rm = {"stiffness": 100.0, "end_mass": 5.0}
    _write(tmp_path, "07-sensitivity", "sensitivity", [_run("k1e2-me5", 0, 2, rope_model=rm)])
    _write(
        tmp_path / "robot-demo",
        "07-sensitivity",
        "sensitivity",
        [_run("k1e2-me5", 0, 1, rope_model=rm)],
    )
    text = paper_table(tmp_path, "flyknot paper")
    assert (
        "| stiffness | end mass | trials until the first knot (ours) | paper | from the robot"
        in text
    )
    assert "| 100 | 5 | 2 (2), 1 of 1 seed tied | >10 | 1 (1), 1 of 1 seed tied |" in text


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_every_variant_loads_on_every_scenario_it_runs(variant):
    """Each variant's options lie over every paper scenario it does not skip: the scenarios'
    velocity weight stays but where a variant is the paper's; the follow-through term at a
    tenth of each of its weights with the damped step's noise band and common time stays but
    in the no-follow-through variant (without them, the follow-through weights back at the
    paper's) and the paper's settings (the paper's weights, the fixed-gain step)."""
    from flyknot_app.learner_settings import FOLLOW_WEIGHTS
    from flyknot_app.reports.paper import PAPER_SCENARIOS
    from flyknot_app.scenario import load_scenario, parse_overrides
    from learner.inverse_qp import InverseModelWeights

    v = VARIANTS[variant]
    paper = InverseModelWeights()
    for name in PAPER_SCENARIOS:
        if name in v.skips:
            continue
        scen = load_scenario(name, parse_overrides([], defaults=v.overrides))
        paper_vel = variant in ("paper-velocity", "paper-settings")
        follow = variant not in ("no-follow-through", "paper-settings")
        for run in scen.runs:
            u, damping = run.learner.update, run.learner.damping
            want = paper.w_crit_vel if paper_vel else 0.1
            assert (u.weights.w_crit_vel, u.weights.w_crit_pos) == (want, paper.w_crit_pos)
            share = 0.1 if follow else 1.0
            for w in FOLLOW_WEIGHTS:
                assert getattr(u.weights, w) == pytest.approx(share * getattr(paper, w))
            if variant == "paper-settings":
                assert u.follow_through and run.learner.step == "gain"
                continue
            assert u.follow_through is follow and damping.common_time is follow
            assert damping.noise == (0.3 if follow else 0.0)


def test_all_runs_every_experiment_each_variants_parts_then_the_baselines(tmp_path, monkeypatch):
    """``flyknot paper --all``: the paper scenarios, each variant's parts (their own ``--set``
    pairs under the user's, the variant's options under both), then the baselines from
    ``03-ropes``' demonstration with ILC's budget, then the table with every column; with
    ``--resume`` the baselines written are kept and every run continues."""
    import flyknot_app.baselines as baselines
    import flyknot_app.reports.paper as paper
    from flyknot_app.baselines import BaselineResult

    runs, searches = [], []

    def fake_run(where, seeds, *, workers, resume, overrides, scenarios, progress):
        runs.append((where.relative_to(tmp_path).as_posix(), scenarios, overrides, resume))
        for n in scenarios:
            (where / n).mkdir(parents=True, exist_ok=True)
            doc = ScenarioSummary(n, "learn", tuple(_run("rope1", s, 2, rope=1) for s in seeds))
            (where / n / "summary.json").write_text(json.dumps(doc.to_json()))
            (where / n / "manifest.json").write_text("{}")

    def fake_search(name, seeds, params, *, demo, progress):
        searches.append((name, list(seeds), params.budget, demo))
        res = [BaselineResult(name, s, costs=[1.0] * 11, knots=[False] * 11) for s in seeds]
        return res, {"demo": demo}

    monkeypatch.setattr(paper, "run_paper", fake_run)
    monkeypatch.setattr(baselines, "search_seeds", fake_search)
    argv = ["paper", "--all", "--out", str(tmp_path), "--seeds", "0,1"]
    assert main([*argv, "--set", "max_trials=3"]) == 0
    mine = {"max_trials": 3}
    robot = {"defaults": {"demo": "robot"}}
    assert runs[0] == (".", list(paper.PAPER_SCENARIOS), mine, False)
    assert runs[1:3] == [
        ("robot-demo", ["02-objectives", "03-ropes", "07-sensitivity"], {**mine, **robot}, False),
        ("robot-demo", ["01-tracking", "04-success-rate"], {"repeats": 8, **mine, **robot}, False),
    ]
    assert runs[3][:2] == ("oracle", ["03-ropes", "05-demos"])
    name, scenarios, overrides, _ = runs[4]
    assert (name, scenarios[0]) == ("no-follow-through", "02-objectives")
    assert overrides["defaults"]["follow_through"] is False
    assert overrides["defaults"]["weights"]["w_pc"] == pytest.approx(100.0)
    assert len(runs) == 5  # paper-settings and paper-velocity are run by hand only
    assert searches == [("cma", [0, 1], 10, "fast-paced"), ("random", [0, 1], 10, "fast-paced")]
    text = (tmp_path / "results.md").read_text()
    assert "by `flyknot paper --all --seeds 0,1 --out" in text
    assert "## Baselines from the same start (rope 1)" in text
    assert "the oracle learner (the same objective" in text.split("## `03-ropes`")[1]
    runs.clear()
    searches.clear()
    assert main([*argv, "--resume"]) == 0
    assert [r[3] for r in runs] == [True] * 5 and searches == []


def test_all_on_runs_without_resume_runs_nothing(tmp_path, capsys, monkeypatch):
    """An ``--out`` whose variant already holds runs: one line before anything runs; and
    ``--all`` with an option that picks part of it: one line."""
    import flyknot_app.reports.paper as paper

    monkeypatch.setattr(paper, "run_paper", lambda *a, **k: pytest.fail("ran"))
    (tmp_path / "oracle" / "05-demos").mkdir(parents=True)
    (tmp_path / "oracle" / "05-demos" / "manifest.json").write_text("{}")
    argv = ["paper", "--all", "--out", str(tmp_path)]
    assert main(argv) == 2
    where = tmp_path / "oracle"
    assert capsys.readouterr().err == (
        f"flyknot: error: --out: {str(where)!r} already holds paper runs; use --resume\n"
    )
    for extra, flag in (
        (["--variant", "oracle"], "--variant"),
        (["--table-only"], "--table-only"),
        (["--scenarios", "03-ropes"], "--scenarios"),
    ):
        assert main([*argv, *extra]) == 2
        assert capsys.readouterr().err == (
            f"flyknot: error: --all: runs every scenario and variant; not with {flag}\n"
        )

"""``flyknot results``: one dated table from run, baseline and trial directories."""

from __future__ import annotations

import json

import pytest

from flyknot_app.cli import main
from tests.test_judging import TRIALS, _record


def _summary(tmp_path, judge="verdict"):
    d = tmp_path / "04"
    d.mkdir()
    run = {
        "name": "rope1",
        "rope": 1,
        "costs": [0.5, 0.3],
        "trials_to_success": 2,
        "repeat_classes": ["knot", "wrapped_at_grip", "knot", "fault"],
        "judge": judge,
        "seed": 0,
    }
    none = {**run, "name": "rope4", "rope": 4, "trials_to_success": None, "repeat_classes": []}
    del none["seed"]
    doc = {"scenario": "04-success-rate", "kind": "learn", "runs": [run, none]}
    (d / "summary.json").write_text(json.dumps(doc))
    (d / "manifest.json").write_text(json.dumps({"overrides": {"repeats": 4}}))
    return d


def test_the_table_has_runs_and_trials(tmp_path, capsys):
    runs = _summary(tmp_path)
    trials = tmp_path / "robot-command"
    for name, (stem, knot) in TRIALS.items():
        _record(stem, knot).save(trials / name)
    out = tmp_path / "results.md"
    assert main(["results", str(runs), str(trials), "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# Results\n") and f"by `flyknot results {runs} {trials} --out" in text
    row = (
        "| `04-success-rate` | rope1 | 1 | 0 | `repeats=4` | 2 | 2/4 (15-85 %); fault 1, "
        "wrapped_at_grip 1 |"
    )
    assert row in text
    assert "| `04-success-rate` | rope4 | 4 | - | `repeats=4` | none in 2 | - |" in text
    row = "| trials | `robot-command` | - | - | - | - | 1/3 (6-79 %); unknot 1, wrapped_at_grip 1 |"
    assert row in text


def test_a_run_without_verdicts_is_refused(tmp_path, capsys):
    runs = _summary(tmp_path, judge=None)
    assert main(["results", str(runs)]) == 2
    err = capsys.readouterr().err
    assert "was run before trials carried verdicts" in err and err.count("\n") == 1


@pytest.mark.parametrize("missing", ["nowhere"])
def test_a_missing_directory_is_one_line(tmp_path, capsys, missing):
    assert main(["results", str(tmp_path / missing)]) == 2
    assert capsys.readouterr().err.startswith("flyknot: error: directory: ")

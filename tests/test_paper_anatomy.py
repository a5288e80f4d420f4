"""The failure anatomy by rope in ``docs/results.md``: each run's trials under its rope, the
learning trials or the repeats as the scenario asks, the ropes in order."""

from __future__ import annotations

import json

import pytest

from flyknot_app.anatomy.diagnosis import Diagnosis
from flyknot_app.anatomy.report import Anatomy
from flyknot_app.reports import paper_anatomy
from flyknot_app.reports.paper_anatomy import anatomy_by_rope, anatomy_figures, anatomy_section


def _d(group: str, label: str) -> Diagnosis:
    return Diagnosis(name="t", label=label, reason="", outcome=label, group=group)


@pytest.fixture
def scenario(tmp_path, monkeypatch):
    """A scenario directory of three runs (ropes 7, 1 and a user's rope) whose diagnoses the
    anatomy would give."""
    runs = [
        {"name": "rope7-seed0", "rope": 7},
        {"name": "rope1-seed0", "rope": 1},
        {"name": "mine-seed0", "rope": "my cord"},
    ]
    for name in ("03-ropes", "04-success-rate"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps({"runs": runs}))
    found = (
        _d("rope7-seed0", "not_through"),
        _d("rope7-seed0/repeats", "success"),
        _d("rope1-seed0", "not_through"),
        _d("rope1-seed0", "success"),
        _d("rope1-seed0/repeats", "shaken_loose"),
        _d("mine-seed0", "no_contact"),
        _d("stranger-seed0", "success"),  # no run of the summary: left out
    )
    monkeypatch.setattr(paper_anatomy, "explain_directory", lambda d: Anatomy(str(d), found))
    return tmp_path


def test_the_trials_go_under_their_ropes_in_order(scenario):
    learning = anatomy_by_rope(scenario / "03-ropes", "learning")
    assert learning.groups() == ("rope 1", "rope 7", "rope my cord")
    assert (
        learning.counts("rope 1")["success"] == 1 and learning.counts("rope 1")["not_through"] == 1
    )
    assert sum(learning.counts("rope 7").values()) == 1
    repeats = anatomy_by_rope(scenario / "04-success-rate", "repeats")
    assert repeats.groups() == ("rope 1", "rope 7")
    assert (
        repeats.counts("rope 1")["shaken_loose"] == 1 and repeats.counts("rope 7")["success"] == 1
    )
    assert anatomy_by_rope(scenario / "05-demos", "learning") is None  # no summary there


def test_the_section_lists_each_rope_and_links_its_figure(scenario, tmp_path):
    folder = tmp_path / "img" / "results"
    pictures = anatomy_figures(scenario, folder, "img/results")
    assert pictures == {
        "03-ropes-anatomy": "img/results/03-ropes-anatomy.png",
        "04-success-rate-anatomy": "img/results/04-success-rate-anatomy.png",
    }
    assert (folder / "03-ropes-anatomy.png").stat().st_size > 0
    lines = anatomy_section(scenario, "03-ropes", pictures)
    assert lines[0].startswith("Why the learning trials of `03-ropes` ended as they did, by rope")
    assert "| rope | trials | success | no_contact | not_through |" in lines
    assert "| rope 1 | 2 | 1 | 0 | 1 |" in lines and "| rope my cord | 1 | 0 | 1 | 0 |" in lines
    assert lines[-2] == "![the anatomy of `03-ropes` by rope](img/results/03-ropes-anatomy.png)"
    repeats = anatomy_section(scenario, "04-success-rate", None)
    assert repeats[0].startswith("Why the learned commands' repeats of `04-success-rate`")
    assert "| rope 1 | 1 | 0 | 1 |" in repeats and not any("![" in x for x in repeats)
    assert anatomy_section(scenario, "05-demos", pictures) == []  # not shown by rope

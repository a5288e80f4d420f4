"""``flyknot bench protocol``: what it measures, on a tiny case (no timing is asserted)."""

from __future__ import annotations

import json

import pytest

from flyknot.errors import ConfigError
from flyknot_app.bench.protocol import (
    PAPER_SCENARIOS,
    QUICK,
    QuickCase,
    bench_protocol,
    format_protocol,
)

TINY = (QuickCase("01-tracking", {"max_runs": 1, "repeats": 1, "settle_s": 0.3}),)


def test_the_protocol_is_every_paper_scenario_and_quick_is_a_subset_of_it():
    assert PAPER_SCENARIOS == (
        "01-tracking", "02-objectives", "03-ropes", "04-success-rate", "05-demos",
        "06-transfer", "07-sensitivity", "08-certainty",
    )  # fmt: skip
    assert {c.scenario for c in QUICK} <= set(PAPER_SCENARIOS)
    labels = [c.label for c in QUICK]  # each case's directory and row
    assert labels == ["01-tracking", "04-success-rate-rope4", "04-success-rate-rope5"]


@pytest.mark.slow
def test_quick_times_the_same_trials_four_ways(egl, capsys, tmp_path):
    res = bench_protocol(workers=1, quick=True, progress=False, cases=TINY, keep=tmp_path / "b")
    labs = ("now", "no_knot_set", "no_unknot_held", "by_scenario")
    for lab in labs:  # kept: the run directories of every lab
        assert (tmp_path / "b" / lab / "01-tracking" / "summary.json").is_file()
    assert capsys.readouterr().out == ""  # the runner's lines do not reach a JSON reader
    assert tuple(res["labs"]) == labs
    for rows in res["labs"].values():
        tracking, total = rows
        assert tracking["scenario"] == "01-tracking" and total["scenario"] == "total"
        assert tracking["trials"] == total["trials"] == 2  # the initial command + 1 repeat
        assert tracking["sim_s_per_trial"] > 0.3  # the command and the fixed 0.3 s settle
        assert 0 < tracking["run_s"] <= tracking["done_s"] <= total["wall_s"]
        assert total["run_s"] == tracking["run_s"]
    for lab in labs[1:]:
        assert res[f"{lab}_over_now"] == pytest.approx(
            res["labs"][lab][-1]["wall_s"] / res["labs"]["now"][-1]["wall_s"]
        )
    assert res["memory"]["main_mb"] > 50
    json.dumps(res)
    text = format_protocol(res)
    assert "no_knot_set / now, total wall time" in text and "01-tracking" in text
    assert "by_scenario / now, total wall time" in text
    assert "no_unknot_held / now, total wall time" in text


def test_workers_must_be_a_positive_integer_and_out_a_new_directory(tmp_path):
    with pytest.raises(ConfigError, match=r"^--workers: must be an integer >= 1, got 0"):
        bench_protocol(workers=0)
    with pytest.raises(ConfigError, match=r"^--out: '.*' exists already; give a new directory"):
        bench_protocol(workers=1, cases=TINY, keep=tmp_path)

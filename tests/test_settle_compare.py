"""``flyknot-tools settle-compare``: a trial played with and without the knot-set end."""

from __future__ import annotations

import json

import pytest

from flyknot.errors import ConfigError
from flyknot_tools.cli import main
from flyknot_tools.settle_compare import compare_settles, format_compared


def test_an_unknotted_trial_is_the_same_both_ways():
    # Rope 7 (the chain) makes no loop under the robot command: a rope free of knots on any
    # machine class (rope 1's untied seeds differ between classes: tests/recorded_on.py).
    (row,) = compare_settles("robot", range(10, 11), rope=7)
    assert row.trial == 10 and row.agree and not row.ended_early
    assert row.klass == {"lab": "unknot", "without": "unknot"}
    assert row.settle_s["lab"] == pytest.approx(row.settle_s["without"])
    assert "same verdict class in 1 of 1; ended by knot_set in 0" in format_compared([row])


def test_the_command_line_prints_json_and_names_bad_input(capsys):
    assert main(["settle-compare", "--trials", "10", "--rope", "7", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["trial"] == 10 and row["klass"]["lab"] == "unknot"
    with pytest.raises(ConfigError, match=r"^demo: unknown demonstration 'nope' \(valid choices: "):
        compare_settles("nope", range(1))
    with pytest.raises(ConfigError) as e:
        compare_settles("robot", range(1), rule="rest")
    assert str(e.value) == "rule: unknown rule 'rest' (valid choices: knot_set, unknot_held)"
    assert main(["settle-compare", "--trials", "x-y"]) == 2
    assert "--trials: must be A-B or A, got 'x-y'" in capsys.readouterr().err

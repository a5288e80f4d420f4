"""flyknot compare: several run directories side by side."""

from __future__ import annotations

import json

import pytest

from flyknot.errors import ConfigError
from flyknot_app import cli
from flyknot_app.compare import compare, load_runset


def _write(d, runs, name="summary.json"):
    d.mkdir(parents=True)
    (d / name).write_text(json.dumps({"runs": runs}))
    return d


def test_table_and_figures(tmp_path, capsys):
    a = _write(
        tmp_path / "ilc",
        [
            {"costs": [0.6, 0.3], "trials_to_success": 2, "repeats": ["trefoil", "unknot"]},
            {"costs": [0.5, None, 0.2], "trials_to_success": None, "repeats": ["trefoil"]},
        ],
    )
    b = _write(
        tmp_path / "cma",
        [{"costs": [0.9, 0.8, 0.7, 0.4], "trials_to_success": 4, "repeats": []}],
        "baseline.json",
    )
    old = _write(tmp_path / "old", [{"costs": [1.0], "first_success_trial": 0}])
    assert load_runset(old).trials_to_success == (1,)
    assert cli.main(["compare", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "| ilc | 1 of 2 | 2 (2-2) | 2/3 (21%-94%) |" in out
    assert "| cma | 1 of 1 | 4 (4-4) | - |" in out
    for f in ("compare.md", "compare_costs.png", "compare_trials.png", "compare_success.png"):
        assert (tmp_path / "out" / f).stat().st_size > 0


def test_a_directory_without_results_is_named(tmp_path):
    with pytest.raises(ConfigError, match=r"^RUN_DIR: '.*empty' holds neither summary.json"):
        compare([tmp_path / "empty"], tmp_path / "out")

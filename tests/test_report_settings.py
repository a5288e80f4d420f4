"""report.md says what the runs were run with; the cost figure's trials are whole numbers."""

from __future__ import annotations

import json

from flyknot_app.reports.report import plot_costs, settings_lines, write_report
from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary


def _run(name, knots):
    options = {"name": name, "label": name, "rope": 1, "demo": "robot", "objective": "critical"}
    return RunSummary(
        options,
        costs=[0.6, 0.4, 0.3],
        knots=knots,
        trials_to_success=(knots.index(True) + 1) if any(knots) else None,
        t_c=0.65,
    )


def test_report_lists_the_overrides_and_the_cell(tmp_path):
    manifest = {"overrides": {"max_trials": 3, "gain": 1}, "runs": [{"name": "a", "cell": "sim"}]}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    text = write_report(tmp_path, ScenarioSummary("s", "learn", (_run("a", [0, 0, 1]),)))
    assert "Overrides (`--set`): `gain=1`, `max_trials=3`. Cell: sim." in text.read_text()
    (tmp_path / "manifest.json").write_text(json.dumps({"overrides": {}, "runs": []}))
    assert settings_lines(tmp_path) == ["Overrides (`--set`): none. Cell: sim.", ""]
    assert settings_lines(tmp_path / "nowhere") == []


def test_cost_figure_has_integer_trials_and_a_knot_legend(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    seen = {}
    orig = plt.Figure.savefig

    def spy(fig, *a, **k):
        ax = fig.axes[0]
        seen["ticks"] = [t for t in ax.get_xticks() if 1 <= t <= 3]
        seen["labels"] = [t.get_text() for t in ax.get_legend().get_texts()]
        return orig(fig, *a, **k)

    monkeypatch.setattr(plt.Figure, "savefig", spy)
    plot_costs([_run("a", [False, True, True])], tmp_path / "c.png", "t")
    assert seen["ticks"] == [1.0, 2.0, 3.0]
    assert seen["labels"] == ["a", "first knot", "later knot"]


def test_run_help_lists_the_scenarios_and_the_set_fields(capsys):
    import pytest

    from flyknot_app import cli

    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    out = capsys.readouterr().out
    assert "03-ropes, 04-success-rate" in out and "learn-rope1, quick" in out
    for field in ("max_trials", "confirm", "rope_model.stiffness", "weights.w_control"):
        assert field in out

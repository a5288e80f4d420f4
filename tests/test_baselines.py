"""Black-box baselines through the gym env: bookkeeping, stopping, repeats, the command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot_app.baselines import (
    BaselineParams,
    BaselineResult,
    PPOParams,
    require_rl,
    run_baseline,
    search_seeds,
    write_results,
)


class QuadraticEnv:
    """Stands in for FlyknotEnv: reward -|knots - goal|^2; the knot ties within ``radius``."""

    def __init__(self, goal_offset: float = 0.15, radius: float = 0.25):
        self.knots = np.zeros((10, 8))
        self.goal = np.full((10, 8), goal_offset)
        self.radius = radius
        self.played = []

    def reset(self, *, seed=None):
        self.knots = np.zeros((10, 8))
        self.rewound = False
        return np.zeros(146), {}

    def restart_variation(self):
        self.rewound = True

    def play(self, knots):
        self.played.append(np.array(knots))
        d = float(np.linalg.norm(knots - self.goal))
        tied = d < self.radius
        info = {
            "cost": d**2,
            "fault": None,
            "knot": "trefoil" if tied else "unknot",
            "verdict": "knot" if tied else "unknot",
        }
        return np.zeros(146), -(d**2) + (100.0 if tied else 0.0), tied, False, info


@pytest.mark.parametrize("name", ["random", "cma"])
def test_a_search_stops_at_its_first_knot(name):
    env = QuadraticEnv(goal_offset=0.02)
    res = run_baseline(name, env, BaselineParams(budget=200, sigma=0.3, scale=0.1), seed=1)
    np.testing.assert_array_equal(env.played[0], np.zeros((10, 8)))  # the initial command
    assert env.rewound  # the search's first trial meets the lab's first variation again
    assert res.trials_to_success == len(res.knots) and res.knots[-1]
    assert not any(res.knots[:-1])


@pytest.mark.parametrize("name", ["random", "cma"])
def test_a_search_without_a_knot_uses_its_budget_and_repeats_its_best(name):
    env = QuadraticEnv(goal_offset=5.0, radius=0.01)
    res = run_baseline(name, env, BaselineParams(budget=12, repeats=3), seed=0)
    assert res.trials_to_success is None and len(res.knots) == 12
    assert res.repeats == ["unknot"] * 3 and res.success_rate == 0.0
    best = int(np.argmax(res.rewards))
    np.testing.assert_array_equal(env.played[-1], env.played[best])


def test_the_same_seed_searches_the_same_way():
    a, b = QuadraticEnv(5.0, 0.01), QuadraticEnv(5.0, 0.01)
    run_baseline("cma", a, BaselineParams(budget=8), seed=3)
    run_baseline("cma", b, BaselineParams(budget=8), seed=3)
    np.testing.assert_array_equal(np.array(a.played), np.array(b.played))


def test_errors_name_the_field():
    with pytest.raises(
        ConfigError,
        match=r"^baseline: unknown baseline 'sgd' \(valid choices: random, cma, ppo\)$",
    ):
        run_baseline("sgd", QuadraticEnv())
    with pytest.raises(ConfigError, match=r"^baseline: unknown baseline 'sgd'"):
        search_seeds("sgd", [0])  # before any lab is built
    with pytest.raises(ConfigError, match=r"^demo: "):
        search_seeds("cma", [0], demo="no-such-demo")
    with pytest.raises(ConfigError, match=r"^budget: must be an integer >= 1, got 0$"):
        BaselineParams(budget=0)
    with pytest.raises(ConfigError, match=r"^gamma: must lie in \(0, 1\], got 0$"):
        PPOParams(gamma=0)
    with pytest.raises(ConfigError, match=r"^episodes_per_update: must be an integer >= 1"):
        PPOParams(episodes_per_update=0)


def test_ppo_without_the_rl_extra_says_how_to_install_it(monkeypatch):
    import importlib.util

    # Whatever is installed here: torch missing, stable-baselines3 present (a stand-in spec).
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name: (
            None
            if name == "torch"
            else (real("json") if name == "stable_baselines3" else real(name))
        ),
    )
    with pytest.raises(ConfigError, match=r"^baseline: ppo needs the rl extra \(torch missing\)"):
        require_rl()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ConfigError, match=r"\(torch, stable_baselines3 missing\)"):
        require_rl()
    with pytest.raises(ConfigError, match=r"download.pytorch.org/whl/cpu"):
        run_baseline("ppo", QuadraticEnv())


def test_results_are_written(tmp_path):
    res = run_baseline("random", QuadraticEnv(0.02), BaselineParams(budget=50, repeats=2), 0)
    table = write_results(tmp_path, [res], BaselineParams(budget=50, repeats=2), 1).read_text()
    assert table.splitlines()[2].startswith(f"| random | 0 | {res.trials_to_success} | ")
    assert table.splitlines()[2].endswith(" | 2/2 (34%-100%) |")
    doc = json.loads((tmp_path / "baseline.json").read_text())
    assert doc["runs"][0]["success_rate"] == 1.0


def test_the_report_gives_mean_trials_and_the_success_after_the_budget(tmp_path):
    def result(seed, tts, n, repeats):
        return BaselineResult("cma", seed, [0.0] * n, [1.0] * n, [False] * n, tts, repeats)

    results = [
        result(0, 4, 4, ["knot"] * 3),
        result(1, None, 30, ["unknot", "fault", "knot"]),
        result(2, 11, 11, []),
    ]
    params = BaselineParams(budget=30, repeats=3)
    text = write_results(tmp_path, results, params, 1, {"note": "x"}).read_text()
    rows = text.splitlines()
    assert rows[3] == "| cma | 1 | >30 | 1 | 1/3 (6%-79%) |"
    assert rows[4] == "| cma | 2 | 11 | 1 | - |"
    # (4 + 31 + 11) / 3 = 15.33, a lower bound: seed 1 tied nothing in 30 trials.
    assert (
        "Knot within the budget of 30: 2 of 3 seeds; mean trials until the first knot: >=15.3."
        in text
    )
    assert "Success after the budget (repeats, pooled): 4/6 (30%-90%)." in text
    assert json.loads((tmp_path / "baseline.json").read_text())["settings"] == {"note": "x"}


def test_the_command_runs_a_tiny_search_on_the_lab(tmp_path, capsys):
    from flyknot_app import cli

    args = ["baseline", "random", "--budget", "2", "--seeds", "0-1", "--settle", "0.2"]
    assert cli.main([*args, "--demo", "robot", "--out", str(tmp_path), "--quiet"]) == 0
    doc = json.loads((tmp_path / "baseline.json").read_text())
    assert doc["settings"]["demo"] == "robot"
    assert [r["seed"] for r in doc["runs"]] == [0, 1]
    assert all(1 <= len(r["knots"]) <= 2 for r in doc["runs"])
    assert "| random | 1 |" in capsys.readouterr().out


def test_a_baseline_starts_from_the_main_job_s_demonstration_and_checks_it(tmp_path, capsys):
    from flyknot_app import cli

    parser = cli.build_parser()
    assert parser.parse_args(["baseline", "cma"]).demo == "fast-paced"
    out = tmp_path / "b"
    assert cli.main(["baseline", "cma", "--demo", "nosuch", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        "flyknot: error: demo: no demo file or name 'nosuch'"
    )
    assert not out.exists()

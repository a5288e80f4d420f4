"""Every scenario file runs end to end at tiny size (1 trial, short settle, few runs)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from flyknot.constants import SCENARIOS_DIR
from flyknot_app.reports.run_summary import ScenarioSummary
from flyknot_app.runner import guess_cache_name, initial_knots, run_scenario
from flyknot_app.scenario import load_scenario, parse_overrides
from flyknot_sim.scene import SceneParams, robot_base_pose

FILES = sorted(SCENARIOS_DIR.glob("*.toml"))
TINY = ["max_trials=1", "settle_s=0.2", "max_runs=2"]


def _tiny(path: Path):
    """The scenario at tiny size (its first runs, one trial, one repeat where it repeats)."""
    scen = load_scenario(str(path), parse_overrides(TINY))
    if any(r.repeats for r in scen.runs):
        scen = load_scenario(str(path), parse_overrides([*TINY, "repeats=1"]))
    return scen


@pytest.fixture(scope="session")
def guess_cache(tmp_path_factory):
    """Initial guesses of every (demonstration, window) the tiny scenarios and the tests below
    use, computed once for all smoke runs."""
    from learner.kinematics import RobotModel

    root = tmp_path_factory.mktemp("ig")
    robot = RobotModel.from_mjcf()
    z = float(robot_base_pose(SceneParams())[2])
    used = {(r.demo, r.window) for f in FILES for r in _tiny(f).runs}
    for demo, window in sorted(used):
        initial_knots(demo, root, robot, 0.005, z, window)
    return root / "initial_guess"


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_scenario_runs_at_tiny_size(egl, path: Path, tmp_path, guess_cache):
    overrides = parse_overrides(TINY)
    scen = _tiny(path)
    out = tmp_path / scen.name
    shutil.copytree(guess_cache, out / "initial_guess")
    summary = run_scenario(scen, out, overrides=overrides, progress=False)
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary.to_json()))
    assert ScenarioSummary.from_json(on_disk) == summary
    for run in on_disk["runs"]:
        for key in ("rope", "objective", "costs", "knots", "trials_to_success"):
            assert key in run
    for run in summary.runs:
        assert len(run.costs) == len(run.knots) == 1
        assert (out / "runs" / run.name / "final_knots.npy").is_file()
        # Every trial's failure-anatomy diagnosis, stored by the run's worker for the report.
        records = list((out / "runs" / run.name).rglob("*.npz"))
        records = [r for r in records if not r.name.endswith(".truth.npz")]
        stored = list((out / "runs" / run.name).rglob("*.diagnosis"))
        assert len(stored) == len(records) >= 1
        assert len(run.repeat_classes) == run.options["repeats"] <= 1
    assert (out / "report.md").read_text().startswith(f"# {scen.name}")
    assert (out / "costs.png").is_file()
    if scen.kind == "transfer":
        assert (out / "transfer_grid.png").is_file()


def test_resume_after_an_interrupted_run_repeats_nothing(egl, tmp_path, guess_cache):
    scen = load_scenario(
        "quick", parse_overrides(["max_trials=2", "settle_s=0.2", "stop_at_success=false"])
    )
    out = tmp_path / "q"
    shutil.copytree(guess_cache, out / "initial_guess")
    first = run_scenario(scen, out, progress=False)
    ledger = (out / "runs" / "rope1" / "learning" / "ledger.jsonl").read_text()
    again = run_scenario(scen, out, resume=True, progress=False)
    assert (out / "runs" / "rope1" / "learning" / "ledger.jsonl").read_text() == ledger
    assert again.runs[0].costs == first.runs[0].costs


def test_tracking_repeats_play_the_initial_command(egl, tmp_path, guess_cache):
    scen = load_scenario(
        "01-tracking", parse_overrides(["max_trials=0", "repeats=1", "settle_s=0.2", "max_runs=1"])
    )
    out = tmp_path / scen.name
    shutil.copytree(guess_cache, out / "initial_guess")
    run_scenario(scen, out, progress=False)
    spec = scen.runs[0]
    z = float(robot_base_pose(SceneParams())[2])
    cache = out / "initial_guess" / guess_cache_name(spec.demo, spec.window, z)
    with np.load(cache) as z:
        k0 = z["knots"]
    np.testing.assert_array_equal(np.load(out / "runs" / spec.name / "final_knots.npy"), k0)
    summary = json.loads((out / "summary.json").read_text())
    run = summary["runs"][0]
    assert len(run["costs"]) == 1 and len(run["repeat_classes"]) == 1 and run["repeats"] == 1
    assert summary["runs"][0]["seed"] == spec.seed  # flyknot compare names the run's seed
    assert summary["runs"][0]["judge"] == "verdict"
    assert (out / "success_rates.png").is_file()
    assert "Tracking alone (no learning)" in (out / "report.md").read_text()


def test_two_worker_processes_give_the_runs_of_one(egl, tmp_path, guess_cache):
    """Runs spread over a process pool (their options pickled to the workers, their
    summaries back) give what one process gives."""
    scen = load_scenario("04-success-rate", parse_overrides([*TINY, "repeats=0"]))
    results = []
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        shutil.copytree(guess_cache, out / "initial_guess")
        summary = run_scenario(scen, out, workers=workers, progress=False)
        results.append([(r.name, r.costs, r.repeat_classes) for r in summary.runs])
    assert results[0] == results[1] and len(results[0]) == 2

"""Seed sweeps on the command line and runs as Ray tasks (a local Ray with 2 CPUs)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from flyknot.errors import ConfigError
from flyknot_app.runner import run_scenario
from flyknot_app.scenario import expand_seeds, parse_scenario


def test_seeds_make_one_run_per_seed_and_keep_transfer_pairs():
    scen = parse_scenario(
        {"run": [{"name": "a", "rope": 1}, {"name": "b", "rope": 2, "start_from": "a"}]}, name="x"
    )
    out = expand_seeds(scen, [0, 3])
    assert [(r.name, r.seed, r.start_from) for r in out.runs] == [
        ("a-seed0", 0, None),
        ("b-seed0", 0, "a-seed0"),
        ("a-seed3", 3, None),
        ("b-seed3", 3, "a-seed3"),
    ]
    with pytest.raises(ConfigError, match=r"^--seeds: give at least one seed$"):
        expand_seeds(scen, [])


def test_an_unknown_executor_is_refused_before_anything_is_written(tmp_path):
    scen = parse_scenario({"run": [{"name": "a"}]}, name="x")
    with pytest.raises(ConfigError, match=r"^--executor: unknown executor 'dask'"):
        run_scenario(scen, tmp_path / "r", executor="dask")
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_a_tiny_sweep_runs_as_ray_tasks_and_resumes(egl, tmp_path):
    out = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "flyknot_app", "run", "quick", "--set", "max_trials=0"]
    cmd += ["--set", "settle_s=0.2", "--seeds", "0-1", "--executor", "ray", "--workers", "2"]
    subprocess.run([*cmd, "--out", str(out)], check=True, capture_output=True, timeout=600)
    summary = json.loads((out / "summary.json").read_text())
    assert [r["name"] for r in summary["runs"]] == ["rope1-seed0", "rope1-seed1"]
    assert all(len(r["costs"]) == 1 for r in summary["runs"])
    first = [r["costs"] for r in summary["runs"]]
    # Resumed: the finished runs are read back, not run again.
    subprocess.run(
        [*cmd, "--out", str(out), "--resume"], check=True, capture_output=True, timeout=600
    )
    again = json.loads((out / "summary.json").read_text())
    assert [r["costs"] for r in again["runs"]] == first


def test_the_tests_local_ray_listens_on_loopback_only():
    # The address Ray gives a local instance's node (its GCS, raylet and workers bind to it),
    # asked in a subprocess as the Ray sweep above runs: loopback, not the machine's address.
    code = "from ray._private.services import get_node_ip_address as a; print(a())"
    done = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True, timeout=120
    )
    assert done.stdout.strip() == "127.0.0.1"

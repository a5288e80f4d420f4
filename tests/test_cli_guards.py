"""The command line refuses what would silently lose or mix up work."""

from __future__ import annotations

import numpy as np

from flyknot_app.cli import main

Q0 = np.array([0.0, -0.3, 0.0, 0.8, 0.0, 1.1, 0.0])


def test_workers_zero_is_refused_before_the_run_directory_exists(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "quick", "--out", str(out), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert "--workers: must be an integer >= 1, got 0" in err
    assert not out.exists()


def test_resume_of_a_missing_run_is_refused(tmp_path, capsys):
    out = tmp_path / "nothing"
    assert main(["run", "quick", "--out", str(out), "--resume"]) == 2
    assert f"--resume: '{out}' holds no run to resume (no manifest.json there)" in (
        capsys.readouterr().err
    )
    assert not out.exists()


def test_trial_does_not_overwrite_without_force(tmp_path, capsys):
    cmd = tmp_path / "c.npy"
    np.save(cmd, np.tile(Q0, (10, 1)))
    out = tmp_path / "t"
    args = ["trial", "--rope", "1", "--command", str(cmd), "--out", str(out), "--settle", "0.1"]
    assert main(args) == 0
    first = (out / "trial.json").read_text()
    capsys.readouterr()
    assert main(args) == 2
    assert f"--out: '{out}' already holds a trial; use --force to replace it" in (
        capsys.readouterr().err
    )
    assert (out / "trial.json").read_text() == first
    assert main([*args, "--force"]) == 0

"""Kill -9 in the middle of a run, resume, and get exactly the uninterrupted run."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from flyknot_app.runner import initial_knots
from flyknot_app.scenario import load_scenario
from flyknot_sim.scene import SceneParams, robot_base_pose

ARGS = [
    "--set",
    "max_trials=4",
    "--set",
    "settle_s=0.2",
    "--set",
    "stop_at_success=false",
    "--set",
    "repeats=2",
]


def _run(out: Path, *extra: str, kill_in_save: int | None = None) -> subprocess.Popen:
    """``flyknot run quick`` in a child process; with ``kill_in_save = n`` the child kills
    itself (SIGKILL) in its n-th record file write, after the bytes are out and before the
    file is renamed into place: a kill while a record is being written."""
    argv = ["run", "quick", "--out", str(out), *ARGS, *extra]
    code = "import sys; from flyknot_app.cli import main; sys.exit(main(sys.argv[1:]))"
    if kill_in_save is not None:
        code = (
            "import os, signal, sys\n"
            "import flyknot.record as r\n"
            "write, calls = r.atomic_save_npz, [0]\n"
            "def dying(path, arrays):\n"
            "    calls[0] += 1\n"
            f"    if calls[0] == {kill_in_save}:\n"
            "        tmp = path.with_name(f'.{path.name}.tmp')\n"
            "        import numpy as np\n"
            "        with open(tmp, 'wb') as f:\n"
            "            np.savez_compressed(f, **arrays)\n"
            "        os.kill(os.getpid(), signal.SIGKILL)\n"
            "    write(path, arrays)\n"
            "r.atomic_save_npz = dying\n"
            "from flyknot_app.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n"
        )
    cmd = [sys.executable, "-c", code, *argv]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _ledger(out: Path) -> list[dict]:
    p = out / "runs" / "rope1" / "learning" / "ledger.jsonl"
    if not p.is_file():
        return []
    rows = [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    for r in rows:
        r.pop("wall_s")
    return rows


@pytest.fixture(scope="module")
def guess(tmp_path_factory):
    from learner.kinematics import RobotModel

    root = tmp_path_factory.mktemp("ig")
    spec = load_scenario("quick").runs[0]
    z = float(robot_base_pose(SceneParams())[2])
    initial_knots(spec.demo, root, RobotModel.from_mjcf(), 0.005, z, spec.window)
    return root / "initial_guess"


@pytest.fixture(scope="module")
def whole(egl, tmp_path_factory, guess):
    """The uninterrupted run."""
    out = tmp_path_factory.mktemp("whole") / "run"
    shutil.copytree(guess, out / "initial_guess")
    w = _run(out)
    assert w.wait(timeout=600) == 0, w.stderr.read().decode()
    return out


@pytest.mark.slow
def test_kill_and_resume_equals_the_uninterrupted_run(tmp_path, guess, whole):
    killed = tmp_path / "killed"
    shutil.copytree(guess, killed / "initial_guess")
    p = _run(killed)
    deadline = time.monotonic() + 300
    while len(_ledger(killed)) < 1:
        assert p.poll() is None, p.stderr.read().decode()
        assert time.monotonic() < deadline, "no trial finished in 300 s"
        time.sleep(0.01)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    assert not (killed / "summary.json").exists()
    assert 1 <= len(_ledger(killed)) < 4
    r = _run(killed, "--resume")
    assert r.wait(timeout=600) == 0, r.stderr.read().decode()
    _assert_same_run(killed, whole)


@pytest.mark.slow
def test_a_kill_while_a_record_is_written_resumes_to_the_same_run(tmp_path, guess, whole):
    """Killed inside the write of trial 1's truth file: the trial has no JSON, so the resumed
    run plays it again with the same variation and ends as the uninterrupted run."""
    killed = tmp_path / "killed"
    shutil.copytree(guess, killed / "initial_guess")
    p = _run(killed, kill_in_save=4)  # trial 0: .npz, .truth.npz; trial 1: .npz, .truth.npz
    assert p.wait(timeout=600) == -signal.SIGKILL, p.stderr.read().decode()
    learning = killed / "runs" / "rope1" / "learning"
    assert (learning / ".trial_0001_a0.truth.npz.tmp").is_file()
    assert not (learning / "trial_0001_a0.json").exists()
    # A ledger line cut short by the kill is not written either.
    with open(learning / "ledger.jsonl", "a") as f:
        f.write('{"trial": 1, "attempt"')
    r = _run(killed, "--resume")
    assert r.wait(timeout=600) == 0, r.stderr.read().decode()
    _assert_same_run(killed, whole)


def _assert_same_run(killed: Path, whole: Path) -> None:
    assert _ledger(killed) == _ledger(whole)
    a = json.loads((killed / "summary.json").read_text())["runs"][0]
    b = json.loads((whole / "summary.json").read_text())["runs"][0]
    for key in ("costs", "knots", "faults", "repeats", "trials_to_success"):
        assert a[key] == b[key], key
    files = sorted(f.relative_to(whole) for f in (whole / "runs").rglob("*.npz"))
    assert files == sorted(f.relative_to(killed) for f in (killed / "runs").rglob("*.npz"))
    for f in files:
        with np.load(whole / f) as x, np.load(killed / f) as y:
            assert sorted(x.files) == sorted(y.files), f
            for k in x.files:
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"{f}:{k}")
    for f in sorted((whole / "runs").rglob("trial_*.json")) + sorted(
        (whole / "runs").rglob("repeat_*.json")
    ):
        meta = json.loads(f.read_text())["metadata"]
        other = json.loads((killed / f.relative_to(whole)).read_text())["metadata"]
        assert meta["trial_index"] == other["trial_index"], f

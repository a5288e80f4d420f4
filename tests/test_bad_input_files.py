"""Bad command and demonstration files: one line naming the file and the problem, exit 2, and
nothing written (the command line run as a user runs it, in a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError
from flyknot_app.diagnose.model_check import load_knots
from flyknot_app.scenario import check_demo

FORMATS = (
    "(accepted formats: .csv t,q1..q7 joint targets; .npy (n, 7) float radians; "
    ".npz Bezier knots and T)"
)
SHIPPED = [
    "fast",
    "fast-paced",
    "inverse",
    "inverse-paced",
    "robot",
    "slow",
    "slow-paced",
    "swipe",
    "swipe-paced",
]
DEMOS = (
    "(valid choices: fast, fast-paced, inverse, inverse-paced, robot, slow, slow-paced, swipe, "
    "swipe-paced)"
)


def _flyknot(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "flyknot_app", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def _refused(out: Path, *args: str) -> list[str]:
    """The stderr lines of a command that must exit 2 and leave ``out`` unmade."""
    done = _flyknot(*args, "--out", str(out))
    assert done.returncode == 2, done.stderr
    assert not out.exists()
    return done.stderr.splitlines()


def _random_bytes(path: Path) -> Path:
    path.write_bytes(np.random.default_rng(0).bytes(3000))
    return path


def _pickled_array(path: Path) -> Path:
    objects = np.empty(3, dtype=object)
    objects[:] = [1.0, "a", None]
    np.save(path, objects, allow_pickle=True)
    return path


def test_a_corrupt_npy_command(tmp_path):
    cmd = _random_bytes(tmp_path / "command.npy")
    err = _refused(tmp_path / "out", "trial", "--rope", "1", "--command", str(cmd))
    assert err == [f"flyknot: error: command file {str(cmd)!r} is not a NumPy .npy file {FORMATS}"]


def test_a_pickled_npy_command(tmp_path):
    cmd = _pickled_array(tmp_path / "command.npy")
    err = _refused(tmp_path / "out", "trial", "--rope", "1", "--command", str(cmd))
    assert err == [
        f"flyknot: error: command file {str(cmd)!r} holds Python objects (a pickled array), "
        f"not numbers {FORMATS}"
    ]


@pytest.mark.parametrize("command", ["run", "paper"])
def test_an_unknown_demonstration_name(command, tmp_path):
    args = ["run", "learn-rope1"] if command == "run" else ["paper", "--scenarios", "03-ropes"]
    err = _refused(tmp_path / "out", *args, "--set", "demo=nosuchdemo")
    assert err == [f"flyknot: error: demo: no demo file or name 'nosuchdemo' {DEMOS}"]


def test_a_missing_demonstration_file(tmp_path):
    demo = tmp_path / "gone.npz"
    err = _refused(tmp_path / "out", "run", "learn-rope1", "--set", f"demo={demo}")
    assert err == [f"flyknot: error: demo: no demo file or name {str(demo)!r} {DEMOS}"]


@pytest.mark.parametrize("suffix", [".npz", ".csv", ".c3d"])
def test_a_corrupt_demonstration_file(suffix, tmp_path):
    demo = _random_bytes(tmp_path / f"demo{suffix}")
    err = _refused(tmp_path / "out", "run", "learn-rope1", "--set", f"demo={demo}")
    problem = {
        ".npz": "is not a demonstration file (.npz)",
        ".csv": "is not a text file (a CSV demonstration)",
        ".c3d": "is not a readable C3D file: File must be a valid c3d file: iostream error",
    }[suffix]
    assert err == [f"flyknot: error: demo: {str(demo)!r} {problem} {DEMOS}"]


def test_a_corrupt_demonstration_to_replay(tmp_path):
    demo = _random_bytes(tmp_path / "demo.npz")
    err = _refused(tmp_path / "out", "demo", "replay", str(demo))
    assert err == [f"flyknot: error: {str(demo)!r} is not a demonstration file (.npz)"]


# --- the readers behind those messages, on each kind of damage ---------------------------


def _saved_demo(path: Path, **change) -> Path:
    """The robot demonstration saved again with arrays ``change`` replaced."""
    with np.load(DEMOS_DIR / "robot.npz") as z:
        np.savez(path, **{**{k: z[k] for k in z.files}, **change})
    return path


def _meta(**fields) -> np.ndarray:
    return np.array(
        json.dumps({"format_version": 1, "t_c": 0.7, "rope": 1, "metadata": {}, **fields})
    )


def _cut_short(path: Path) -> Path:
    whole = (DEMOS_DIR / "robot.npz").read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    return path


def _flipped_byte(path: Path) -> Path:
    whole = bytearray((DEMOS_DIR / "robot.npz").read_bytes())
    whole[len(whole) // 2] ^= 0xFF
    path.write_bytes(bytes(whole))
    return path


DAMAGED_DEMOS = {
    "cut short": (_cut_short, " is not a demonstration file (.npz)"),
    "flipped byte": (_flipped_byte, " is not a readable demonstration file (.npz): "),
    "object array": (
        lambda p: _saved_demo(p, t=np.empty(2, dtype=object)),
        " is not a readable demonstration file (.npz): Object arrays cannot be loaded",
    ),
    "text times": (
        lambda p: _saved_demo(p, t=np.array(["a", "b"])),
        " is not a readable demonstration file (.npz): could not convert string to float",
    ),
    "meta not JSON": (
        lambda p: _saved_demo(p, meta=np.array("{")),
        " is not a readable demonstration file (.npz): Expecting property name",
    ),
    "meta a list": (lambda p: _saved_demo(p, meta=np.array("[1]")), ": meta must be a JSON object"),
    "meta without t_c": (
        lambda p: _saved_demo(p, meta=np.array('{"format_version": 1}')),
        ": meta t_c must be int or float, got None",
    ),
    "text t_c": (lambda p: _saved_demo(p, meta=_meta(t_c="x")), ": meta t_c must be int or float"),
    "short times": (
        lambda p: _saved_demo(p, t=np.arange(5.0)),
        ": Demonstration.hand_pos must have shape (5, 3)",
    ),
}


@pytest.mark.parametrize("damage", DAMAGED_DEMOS)
def test_every_damaged_demonstration_is_a_record_error_naming_the_file(damage, tmp_path):
    make, problem = DAMAGED_DEMOS[damage]
    path = make(tmp_path / "demo.npz")
    with pytest.raises(RecordError) as e:
        Demonstration.load(path)
    assert str(e.value).startswith(f"{str(path)!r}{problem}"), str(e.value)
    with pytest.raises(ConfigError) as e:
        check_demo(str(path))
    assert e.value.field == "demo" and e.value.choices == SHIPPED


def test_shipped_demonstrations_pass_the_check():
    for name in SHIPPED:
        assert check_demo(name) == DEMOS_DIR / f"{name}.npz"


def test_model_check_knots_are_read_safely(tmp_path):
    with np.load(DEMOS_DIR / "seeds" / "robot_command.npz") as z:
        knots = z["knots"]
    np.save(tmp_path / "final_knots.npy", knots)
    np.testing.assert_array_equal(load_knots(tmp_path / "final_knots.npy"), knots)
    np.testing.assert_array_equal(load_knots(DEMOS_DIR / "seeds" / "robot_command.npz"), knots)
    bad = {
        _random_bytes(tmp_path / "r.npy"): "is not a NumPy .npy file",
        _pickled_array(tmp_path / "p.npy"): "holds Python objects (a pickled array), not numbers",
        _random_bytes(tmp_path / "r.npz"): "is not a NumPy .npz archive",
    }
    for path, problem in bad.items():
        with pytest.raises(ConfigError) as e:
            load_knots(path)
        assert str(e.value) == f"--knots: command file {str(path)!r} {problem}"
    np.save(tmp_path / "s.npy", np.zeros((5, 3)))
    with pytest.raises(ConfigError, match=r"knots: must have shape \(10, 8\), got \(5, 3\)$"):
        load_knots(tmp_path / "s.npy")


def test_a_set_of_what_a_scenario_compares(tmp_path):
    """``flyknot run 05-demos --set demo=...`` would run one demonstration under four names."""
    err = _refused(tmp_path / "out", "run", "05-demos", "--set", "demo=slow-paced")
    assert len(err) == 1
    assert err[0].startswith("flyknot: error: --set demo: '05-demos' compares its runs by demo (")

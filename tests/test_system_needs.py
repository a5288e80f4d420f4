"""What the tests need from the system: ``.ci/system-packages`` installs it only where it can
(as root, or with sudo under CI=true), and a test that needs a missing piece is skipped naming
it, or failed under CI=true (``tests/system_needs.py``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests import system_needs
from tests.system_needs import chromium_missing, compiler_missing, egl_missing, require

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / ".ci" / "system-packages"


def _fake_bin(tmp_path: Path, uid: int, apt_status: int = 0) -> Path:
    """A PATH of fakes: ``id`` says ``uid``, ``apt-get`` and ``sudo`` write their command lines
    to ``calls`` (``apt-get`` exits with ``apt_status``); no ``cc``, so a C compiler is always
    missing."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(parents=True)
    log = tmp_path / "calls"
    fakes = {
        "id": f"echo {uid}\n",
        "apt-get": f'echo "apt-get $*" >> {log}\nexit {apt_status}\n',
        "sudo": f'echo "sudo $1" >> {log}\nexec "$@"\n',
    }
    for name, body in fakes.items():
        (bin_dir / name).write_text(f"#!/bin/bash\n{body}")
        (bin_dir / name).chmod(0o755)
    (bin_dir / "env").symlink_to("/usr/bin/env")
    return bin_dir


def _run(tmp_path: Path, uid: int, ci: str | None, apt_status: int = 0):
    env = {"PATH": str(_fake_bin(tmp_path, uid, apt_status))}
    if ci is not None:
        env["CI"] = ci
    done = subprocess.run(["/bin/bash", str(SCRIPT)], env=env, capture_output=True, text=True)
    log = tmp_path / "calls"
    calls = log.read_text().splitlines() if log.exists() else []
    return done, calls


def test_without_root_or_ci_nothing_is_installed_and_the_missing_packages_are_named(tmp_path):
    for ci in (None, "false"):
        done, calls = _run(tmp_path / str(ci), uid=1000, ci=ci)
        assert done.returncode == 0, done.stderr
        assert calls == []
        assert "not installing gcc libc6-dev" in done.stderr
        assert "neither root nor CI=true" in done.stderr


def test_as_root_the_missing_packages_are_installed_with_apt_get(tmp_path):
    done, calls = _run(tmp_path, uid=0, ci=None)
    assert done.returncode == 0, done.stderr
    assert calls[0] == "apt-get update -q"
    assert calls[1].startswith("apt-get install -y -q gcc libc6-dev")
    assert len(calls) == 2  # no sudo


def test_under_ci_without_root_they_are_installed_with_sudo(tmp_path):
    done, calls = _run(tmp_path, uid=1000, ci="true")
    assert done.returncode == 0, done.stderr
    assert calls[:2] == ["sudo apt-get", "apt-get update -q"]
    assert calls[2] == "sudo env"
    assert calls[3].startswith("apt-get install -y -q gcc libc6-dev")


def test_under_ci_a_failed_install_fails(tmp_path):
    done, calls = _run(tmp_path, uid=1000, ci="true", apt_status=100)
    assert done.returncode == 100
    assert calls == ["sudo apt-get", "apt-get update -q"]


def test_the_ci_run_installs_through_the_script():
    run = (ROOT / ".ci" / "run").read_text()
    assert run.index("bash .ci/system-packages") < run.index("pytest")
    script = SCRIPT.read_text()
    for package in ("chromium-driver", "libegl-mesa0", "gcc"):
        assert package in script


def test_a_missing_piece_skips_with_its_reason_outside_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    require(None)
    with pytest.raises(pytest.skip.Exception, match=r"^no thing; install it$"):
        require("no thing; install it")


def test_under_ci_a_missing_piece_fails(monkeypatch):
    monkeypatch.setenv("CI", "true")
    require(None)
    with pytest.raises(pytest.fail.Exception, match=r"^no thing; install it \(CI=true"):
        require("no thing; install it")


def test_chromium_missing_names_the_paths_and_the_packages(monkeypatch, tmp_path):
    monkeypatch.setattr(system_needs, "CHROMIUM", tmp_path / "chromium")
    monkeypatch.setattr(system_needs, "CHROMEDRIVER", tmp_path / "chromedriver")
    assert chromium_missing() == (
        f"no Chromium found at {tmp_path / 'chromium'} and {tmp_path / 'chromedriver'}; "
        "install Debian's chromium and chromium-driver"
    )
    for name in ("chromium", "chromedriver"):
        (tmp_path / name).write_text("")
    assert chromium_missing() is None


def test_egl_missing_says_why_and_what_to_install(monkeypatch):
    """Without an EGL vendor library (glvnd finds none), the probe's context fails."""
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setenv("__EGL_VENDOR_LIBRARY_FILENAMES", "/nonexistent/egl_vendor.json")
    reason = egl_missing.__wrapped__()
    assert reason is not None
    assert reason.startswith("no OpenGL context for MuJoCo's renders (")
    assert reason.endswith("); install Debian's libegl1, libgl1-mesa-dri and libegl-mesa0")


def test_compiler_missing_names_the_compiler_and_the_packages(monkeypatch):
    monkeypatch.setenv("CC", "no-such-cc")
    assert compiler_missing() == (
        "no C compiler 'no-such-cc' on the PATH (set CC to one); install Debian's gcc and libc6-dev"
    )
    monkeypatch.setenv("CC", sys.executable)  # any executable on the PATH will do
    assert compiler_missing() is None

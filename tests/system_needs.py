"""What some tests need from the system beyond the Python packages, and what they do without it.

The viewer's browser test drives Debian's Chromium through its chromedriver, renders (``flyknot
render``, the pictures of a run's knots) draw in an EGL OpenGL context (Mesa's without a GPU),
and the learner's compiled robot model needs a C compiler. ``.ci/run`` installs them where it
can (as root, or under ``CI=true``). A test that needs a missing one is skipped with a reason
naming what is missing and how to install it; under ``CI=true`` it fails instead, so CI runs
every test. The fixtures of ``tests/conftest.py`` (``chromium``, ``egl``, ``c_compiler``) apply
this.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import pytest

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
EGL_PACKAGES = "libegl1, libgl1-mesa-dri and libegl-mesa0"
ROOT = Path(__file__).resolve().parent.parent

_EGL_PROBE = """
from flyknot_app.viewer.render import _gl_context
context = _gl_context(16, 16)
context.make_current()
context.free()
"""


def on_ci() -> bool:
    """Whether the tests run under CI (``CI=true``), where nothing may be skipped for a
    missing system package."""
    return os.environ.get("CI", "").strip().lower() == "true"


def require(missing: str | None) -> None:
    """Nothing when ``missing`` is None; else skip the test with ``missing`` as the reason, or
    fail it under ``CI=true``."""
    if missing is None:
        return
    if on_ci():
        pytest.fail(f"{missing} (CI=true: every test must run)", pytrace=False)
    pytest.skip(missing)


def chromium_missing() -> str | None:
    """Why the browser test cannot run (no Chromium or chromedriver), or None."""
    absent = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.is_file()]
    if not absent:
        return None
    return (
        f"no Chromium found at {' and '.join(absent)}; "
        "install Debian's chromium and chromium-driver"
    )


@functools.cache
def egl_missing() -> str | None:
    """Why MuJoCo cannot render offscreen (no context of the backend ``MUJOCO_GL`` asks for,
    EGL by default), or None. Probed in a child process: a failed context leaves nothing
    behind in this one."""
    probe = subprocess.run(
        [sys.executable, "-c", _EGL_PROBE],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    if probe.returncode == 0:
        return None
    lines = probe.stderr.strip().splitlines() or [f"exit code {probe.returncode}"]
    return f"no OpenGL context for MuJoCo's renders ({lines[-1]}); install Debian's {EGL_PACKAGES}"


def compiler_missing() -> str | None:
    """Why the robot model cannot be compiled (no C compiler, ``$CC`` or ``cc``), or None."""
    from learner.native import NativeUnavailableError, _compiler

    try:
        _compiler()
    except NativeUnavailableError as exc:
        return f"{exc}; install Debian's gcc and libc6-dev"
    return None

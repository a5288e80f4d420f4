"""Test-suite settings: hypothesis examples are derandomized so CI runs are repeatable, a
local Ray started by a test (or by a subprocess it runs) listens on loopback only, and the
fixtures of what some tests need from the system (Chromium, EGL, a C compiler)."""

import os

import pytest
from hypothesis import settings

from flyknot_hw.xarm_sdk import prepare_sdk_log_dir
from tests.system_needs import chromium_missing, compiler_missing, egl_missing, require

# Ray takes this machine's network address for a local instance on Linux unless told it is
# not a cluster node; the tests reach only loopback (tests/test_sweeps.py checks it).
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

# The hardware tests import the xArm SDK while collecting, in every xdist worker at once.
prepare_sdk_log_dir()

settings.register_profile("flyknot", derandomize=True, deadline=None)
settings.load_profile("flyknot")


@pytest.fixture(scope="session")
def chromium() -> None:
    """Debian's Chromium and chromedriver (the viewer's browser test): skipped without them,
    failed under CI=true (tests/system_needs.py)."""
    require(chromium_missing())


@pytest.fixture(scope="session")
def egl() -> None:
    """An offscreen OpenGL context for MuJoCo's renders: skipped without one, failed under
    CI=true (tests/system_needs.py)."""
    require(egl_missing())


@pytest.fixture(scope="session")
def c_compiler() -> None:
    """A C compiler for the learner's compiled robot model: skipped without one, failed under
    CI=true (tests/system_needs.py)."""
    require(compiler_missing())

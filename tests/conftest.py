"""Test-suite settings: hypothesis examples are derandomized so CI runs are repeatable, and a
local Ray started by a test (or by a subprocess it runs) listens on loopback only."""

import os

from hypothesis import settings

# Ray takes this machine's network address for a local instance on Linux unless told it is
# not a cluster node; the tests reach only loopback (tests/test_sweeps.py checks it).
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

settings.register_profile("flyknot", derandomize=True, deadline=None)
settings.load_profile("flyknot")

"""Progress bars show on a terminal and stay out of logs (flyknot.progress)."""

from __future__ import annotations

import subprocess
import sys

from flyknot.progress import bar_disable


def test_bar_disable():
    assert bar_disable(False) is True
    assert bar_disable(True) is None  # tqdm: shown on a terminal only


def test_no_bar_codes_in_a_log():
    out = subprocess.run(
        [sys.executable, "-m", "flyknot_app", "bench", "sim", "--ropes", "6"],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    assert "\r" not in out.stderr and "\x1b" not in out.stderr
    assert all(lab in out.stdout for lab in ("before", "elastic", "pyramidal", "now"))
    assert "now / pyramidal" in out.stdout

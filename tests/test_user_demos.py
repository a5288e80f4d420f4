"""A user's own demonstration file as a run's start: ``demo = PATH`` to a .npz, .csv or .c3d."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.demo_formats import read_demonstration, save_demo_c3d, save_demo_csv
from flyknot.errors import ConfigError, RecordError
from flyknot_app.scenario import check_demo


@pytest.fixture(scope="module")
def shipped():
    return Demonstration.load(DEMOS_DIR / "fast-paced.npz")


def test_every_format_reads_the_same_demonstration(shipped, tmp_path):
    save_demo_csv(shipped, tmp_path / "d.csv")
    save_demo_c3d(shipped, tmp_path / "d.c3d")
    shipped.save(tmp_path / "d.npz")
    for name, atol in (("d.npz", 0.0), ("d.csv", 1e-12), ("d.c3d", 1e-4)):
        demo = read_demonstration(tmp_path / name)
        assert demo.t_c == pytest.approx(shipped.t_c, abs=1e-6), name
        np.testing.assert_allclose(demo.hand_pos, shipped.hand_pos, rtol=0, atol=atol)
        np.testing.assert_allclose(demo.markers, shipped.markers, rtol=0, atol=atol)
        assert check_demo(str(tmp_path / name)) == tmp_path / name


def test_a_demonstration_of_another_kind_is_refused(tmp_path):
    bad = tmp_path / "demo.json"
    bad.write_text("{}")
    with pytest.raises(RecordError) as e:
        read_demonstration(bad)
    assert (
        str(e.value) == f"{str(bad)!r}: a demonstration is a .npz, .csv or .c3d file, not '.json'"
    )
    with pytest.raises(ConfigError) as e:
        check_demo(str(bad))
    assert e.value.field == "demo"


@pytest.mark.slow
def test_a_run_learns_from_a_csv_demonstration(shipped, tmp_path):
    """`flyknot run learn-rope1 --set demo=FILE.csv`: the initial guess and two trials."""
    save_demo_csv(shipped, tmp_path / "mine.csv")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "flyknot_app", "run", "learn-rope1", "--set",
         f"demo={tmp_path / 'mine.csv'}", "--set", "max_trials=2", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "runs" / "rope1" / "result.json").read_text())
    assert result["demo"] == str(tmp_path / "mine.csv") and len(result["costs"]) == 2
    assert result["t_c"] == pytest.approx(0.794, abs=0.01)
    assert result["costs"][1] < result["costs"][0]

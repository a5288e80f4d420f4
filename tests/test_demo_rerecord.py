"""Recording a demonstration's stored motion again: the shipped files are what it makes."""

from __future__ import annotations

from dataclasses import replace

import pytest

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError
from flyknot_tools.cli import main as tools_main
from flyknot_tools.demo_rerecord import rerecord
from tests.recorded_on import assert_recorded_again, same_class


@pytest.mark.parametrize("name", ["fast", "robot"])
def test_a_shipped_demo_is_its_stored_motion_recorded_in_todays_lab(name):
    demo = Demonstration.load(DEMOS_DIR / f"{name}.npz")
    again = rerecord(demo, check_repeats=0)
    assert again.kind == ("robot" if name == "robot" else "hand")
    assert_recorded_again(again.demo, demo)
    # what the settle's length sets differs on another machine class (tests/recorded_on.py)
    drop = {"check"} | (set() if same_class() else {"settle_fraction"})
    kept = {k: v for k, v in demo.metadata.items() if k not in drop}
    assert {k: again.demo.metadata[k] for k in kept} == kept  # the search's record is kept


def test_a_demo_without_a_motion_is_refused(capsys, tmp_path):
    demo = Demonstration.load(DEMOS_DIR / "fast.npz")
    bare = replace(demo, metadata={"generator": "elsewhere"})
    with pytest.raises(ConfigError) as e:
        rerecord(bare)
    assert str(e.value) == (
        "demo: stores no motion to record again (valid: a hand motion or a robot command)"
    )
    path = tmp_path / "bare.npz"
    bare.save(path)
    assert tools_main(["demo", "rerecord", str(path), "--check", "0"]) == 2
    assert "stores no motion" in capsys.readouterr().err
    assert tools_main(["demo", "rerecord", str(tmp_path / "none.npz")]) == 2

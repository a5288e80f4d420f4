"""``flyknot trial`` reports the rope's shape at the end of the trial: the turning angles
between consecutive segments of the simulator's centreline in its last frame."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from flyknot_app.cli import main
from flyknot_app.trial_cli import rest_shape

Q0 = np.array([0.0, -0.3, 0.0, 0.8, 0.0, 1.1, 0.0])


def _polyline(headings_deg: list[float]) -> np.ndarray:
    """A planar polyline of unit segments with these headings [deg]."""
    steps = [[math.cos(math.radians(h)), math.sin(math.radians(h)), 0.0] for h in headings_deg]
    return np.cumsum(np.vstack([np.zeros(3), steps]), axis=0)


def test_rest_shape_is_the_last_frames_turning_angles_past_the_held_joint():
    # the held end's joint turns 90 deg (left out), then a zig-zag of 10 deg and one 30 deg
    line = _polyline([0, 90, 100, 90, 100, 90, 120])
    rec = SimpleNamespace(truth={"centreline": np.stack([np.zeros_like(line), line])})
    shape = rest_shape(rec)
    assert shape["rest_median_turn_deg"] == pytest.approx(10.0)
    assert shape["rest_max_turn_deg"] == pytest.approx(30.0)
    assert rest_shape(SimpleNamespace(truth={})) == {}


def test_the_trial_command_prints_the_rest_shape(tmp_path, capsys):
    cmd = tmp_path / "c.npy"
    np.save(cmd, np.tile(Q0, (10, 1)))  # the arm holds still: the rope hangs straight
    args = ["trial", "--rope", "6", "--command", str(cmd), "--out", str(tmp_path / "t")]
    assert main([*args, "--settle", "0.5", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert 0.0 <= summary["rest_median_turn_deg"] < 1.0
    assert summary["rest_median_turn_deg"] <= summary["rest_max_turn_deg"]


def test_the_trial_command_plays_a_changed_variation(tmp_path, capsys):
    """Without any variation two plays of a command are the same; the lab's own differ."""
    cmd = tmp_path / "c.npy"
    np.save(cmd, np.linspace(Q0, Q0 + 0.3, 60))
    base = ["trial", "--rope", "1", "--command", str(cmd), "--settle", "0.2", "--repeats", "2"]
    still = ["rest_start=false", "servo_gain_rel=0", "start_delay_max_s=0"]
    assert main([*base, "--out", str(tmp_path / "own"), "--json"]) == 0
    opts = [a for v in still for a in ("--variation", v)]
    assert main([*base, *opts, "--out", str(tmp_path / "none"), "--json"]) == 0
    capsys.readouterr()

    def tips(folder):
        return [np.load(tmp_path / folder / f"trial_{i:03d}.npz")["fingertip_pos"] for i in (0, 1)]

    a, b = tips("none")
    assert np.array_equal(a, b)
    meta = json.loads((tmp_path / "none" / "trial_000.json").read_text())["metadata"]
    assert meta["variation"]["servo_gain_rel"] == 0 and meta["variation"]["rest_start"] is False
    a, b = tips("own")
    assert not np.array_equal(a, b)


@pytest.mark.parametrize(
    ("pair", "message"),
    [
        (
            "gains=0.1",
            "--variation.gains: not a field of the variation (valid choices: sway_deg, "
            "servo_gain_rel, start_delay_max_s, rest_start, rest_scale)",
        ),
        ("rest_scale=1.5", "--variation.rest_scale: must be a number in [0, 1], got 1.5"),
        ("rest_scale", "--variation: expected FIELD=VALUE, got 'rest_scale'"),
    ],
)
def test_a_bad_variation_is_one_line_and_writes_nothing(tmp_path, capsys, pair, message):
    cmd = tmp_path / "c.npy"
    np.save(cmd, np.tile(Q0, (10, 1)))
    out = tmp_path / "t"
    args = ["trial", "--command", str(cmd), "--out", str(out), "--variation", pair]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(message) and "\n" not in err
    assert not out.exists()

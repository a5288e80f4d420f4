"""Which part of the lab's variation decides a command's knot
(flyknot_app.diagnose.variation_split)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot_app.diagnose.variation_split import (
    Play,
    alone,
    format_split,
    path_spread,
    split_variation,
)
from flyknot_sim.lab_params import LabParams, VariationParams


def _fake_play(lab_params) -> Play:
    """Ties unless the start delay is on and the seed is odd (a knife edge in timing); the
    fingertip moves off the nominal path by the servo spread (1e-3 s) [m] at its last tick."""
    v = lab_params.variation
    klass = "unknot" if v.start_delay_max_s > 0.0 and lab_params.seed % 2 else "knot"
    tip = np.zeros((5, 3))
    tip[-1, 2] = 1e-3 * v.servo_gain_rel * (1 + lab_params.seed % 2)
    return Play(klass, tip)


def test_each_component_alone_and_the_split_it_makes():
    v = VariationParams()
    only = alone(v, "servo_gain_rel")
    assert only == VariationParams(0.0, v.servo_gain_rel, 0.0, False)
    scaled = VariationParams(rest_scale=0.25)
    assert alone(scaled, "rest_start") == VariationParams(0.0, 0.0, 0.0, True, 0.25)
    split = split_variation(LabParams(), _fake_play, 4, seeds=[1, 2, 3, 4])
    assert list(split.classes) == [
        "none",
        "rest_start",
        "servo_gain_rel",
        "start_delay_max_s",
        "all",
    ]
    assert split.classes["none"] == ("knot",)  # one play: without variation every play is one
    assert split.knots("rest_start") == 4 and split.knots("servo_gain_rel") == 4
    assert split.classes["start_delay_max_s"] == ("unknot", "knot", "unknot", "knot")
    assert split.knots("all") == 2
    # the servo spread moves the last tick by 0.03 or 0.06 mm (odd seeds)
    assert split.spread["servo_gain_rel"] == pytest.approx((6e-5, 3e-5, 6e-5, 3e-5))
    assert split.median_spread("rest_start") == 0.0
    assert format_split(split).splitlines() == [
        "no variation: 1 of 1 tied",
        "rest_start alone: 4 of 4 tied; fingertip path spread 0 mm (median)",
        "servo_gain_rel alone: 4 of 4 tied; fingertip path spread 0.045 mm (median)",
        "start_delay_max_s alone: 2 of 4 tied (misses: unknot); fingertip path spread 0 mm "
        "(median)",
        "all: 2 of 4 tied (misses: unknot); fingertip path spread 0.045 mm (median)",
    ]
    doc = json.loads(json.dumps(split.to_json()))
    assert doc["knots"]["all"] == 2
    assert doc["median_spread_mm"]["all"] == pytest.approx(0.045)


def test_path_spread_is_the_largest_distance_over_the_common_ticks():
    nominal = np.zeros((4, 3))
    tip = np.array([[0.0, 0, 0], [0.003, 0.004, 0], [0, 0, 0.001], [0, 0, 0], [9, 9, 9]])
    assert path_spread(tip, nominal) == pytest.approx(0.005)  # the 5th tick is past nominal


def test_a_component_the_lab_does_not_vary_is_left_out():
    lab = LabParams(variation=VariationParams(sway_deg=2.0, servo_gain_rel=0.0))
    split = split_variation(lab, _fake_play, 2)
    assert "sway_deg" in split.classes and "servo_gain_rel" not in split.classes
    assert split.seeds == (1000, 1001)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: alone(VariationParams(), "wind"), "component: unknown variation component 'wind'"),
        (lambda: split_variation(LabParams(), _fake_play, 0), "--plays: must be an integer >= 1"),
        (lambda: split_variation(LabParams(), _fake_play, 2, seeds=[1]), "seeds: must be 2 seeds"),
    ],
)
def test_bad_arguments_name_the_field(call, message):
    with pytest.raises(ConfigError) as e:
        call()
    assert str(e.value).startswith(message)


def _run_dir(tmp_path, cell="sim", tts=2):
    run = tmp_path / "run"
    (run / "learning").mkdir(parents=True)
    for k in range(3):
        np.save(run / "learning" / f"knots_{k:04d}.npy", np.full((10, 8), float(k)))
    result = {
        "demo": "fast-paced", "follow_through_s": 0.25, "path_frac": 0.0, "cell": cell,
        "rope": 1, "seed": 0, "costs": [3.0, 0.5, 0.9], "trials_to_success": tts, "T": 1.0,
    }  # fmt: skip
    (run / "result.json").write_text(json.dumps(result))
    return run


def test_cli_plays_the_first_knots_command(tmp_path, capsys, monkeypatch):
    import flyknot_app.diagnose.variation_split as vs
    from flyknot_app.cli import main

    seen = []

    def fake_lab_play(knots, T):
        seen.append((float(knots[0, 0]), T))
        return _fake_play

    monkeypatch.setattr(vs, "lab_play", fake_lab_play)
    run = _run_dir(tmp_path)
    assert main(["diagnose", "variation", str(run), "--plays", "2"]) == 0
    assert seen == [(1.0, 1.0)]  # trial 2's command: knots_0001
    out = capsys.readouterr().out
    assert out.startswith("trial 2's command, 2 plays per setting:\nno variation: 1 of 1 tied")
    assert json.loads((run / "variation.json").read_text())["trial"] == 2
    run = _run_dir(tmp_path / "b", tts=None)
    assert main(["diagnose", "variation", str(run), "--plays", "1", "--json"]) == 0
    assert seen[-1] == (1.0, 1.0)  # no knot: the lowest cost, trial 2


def test_cli_refuses_a_real_cell_and_a_bad_trial(tmp_path, capsys):
    from flyknot_app.cli import main

    assert main(["diagnose", "variation", str(_run_dir(tmp_path, cell="xarm"))]) == 2
    err = capsys.readouterr().err
    assert err == (
        "flyknot: error: RUN_DIR: only a simulated lab can switch its variation off; this run's "
        "cell is 'xarm' (valid choices: sim)\n"
    )
    assert main(["diagnose", "variation", str(_run_dir(tmp_path / "b")), "--trial", "9"]) == 2
    assert "--trial: must be 1..3 (the run's trials), got 9" in capsys.readouterr().err


def test_cli_plays_a_floors_command(tmp_path, capsys, monkeypatch):
    import flyknot_app.diagnose.variation_split as vs
    from flyknot_app.cli import main

    seen = []
    monkeypatch.setattr(vs, "lab_play", lambda knots, T: seen.append(T) or _fake_play)
    floor = tmp_path / "floor.json"
    floor.write_text(json.dumps({"knots": np.zeros((10, 8)).tolist(), "T": 1.044, "rope": 1}))
    out = tmp_path / "split.json"
    assert (
        main(["diagnose", "variation", "--floor", str(floor), "--plays", "2", "--out", str(out)])
        == 0
    )
    assert seen == [1.044] and json.loads(out.read_text())["knots"]["all"] == 1
    assert capsys.readouterr().out.startswith("the floor's command, 2 plays per setting:\n")
    floor.write_text("{}")
    assert main(["diagnose", "variation", "--floor", str(floor)]) == 2
    assert "is not a result of `flyknot diagnose floor`" in capsys.readouterr().err
    assert main(["diagnose", "variation"]) == 2
    assert "give a run directory or --floor, not both or neither" in capsys.readouterr().err


def test_cli_splits_a_changed_variation(tmp_path, capsys, monkeypatch):
    import flyknot_app.diagnose.variation_split as vs
    from flyknot_app.cli import main

    seen = []

    def play(lab_params):
        seen.append(lab_params.variation)
        return _fake_play(lab_params)

    monkeypatch.setattr(vs, "lab_play", lambda knots, T: play)
    run = _run_dir(tmp_path)
    args = ["diagnose", "variation", str(run), "--plays", "1", "--json"]
    assert (
        main([*args, "--variation", "servo_gain_rel=0.003", "--variation", "rest_scale=0.1"]) == 0
    )
    assert seen[-1] == VariationParams(servo_gain_rel=0.003, rest_scale=0.1)  # "all"
    assert json.loads(capsys.readouterr().out)["variation"] == {
        "servo_gain_rel": 0.003,
        "rest_scale": 0.1,
    }
    assert main([*args, "--variation", "rest_scale=-1"]) == 2
    assert capsys.readouterr().err == (
        "flyknot: error: --variation.rest_scale: must be a number in [0, 1], got -1\n"
    )

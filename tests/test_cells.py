"""The cell registry and a scenario's ``[cell]`` table."""

from __future__ import annotations

import pytest

from flyknot.errors import ConfigError
from flyknot.record import Cell
from flyknot_app.cells import CELLS, SimCellSpec, cell_spec, open_cell
from flyknot_app.scenario import parse_scenario


def test_the_sim_cell_opens_from_its_spec():
    lab = open_cell("sim", cell_spec("sim", {"rope": 3, "seed": 5}))
    assert isinstance(lab, Cell)
    assert lab.params.seed == 5 and lab.rope_params.id == 3
    assert lab.trial_index == 0


def test_unknown_kind_and_field_list_the_valid_ones():
    with pytest.raises(
        ConfigError, match=r"^cell\.kind: unknown cell kind 'robot' \(valid choices: sim, xarm\)$"
    ):
        cell_spec("robot", {})
    with pytest.raises(
        ConfigError,
        match=r"^cell\.ip: not a field of a 'sim' cell "
        r"\(valid choices: rope, seed, settle_s, ropes, knot_set, unknot_held, variation\)$",
    ):
        cell_spec("sim", {"ip": "10.0.0.1"})
    with pytest.raises(ConfigError, match=r"^seed: must be an integer >= 0, got -1$"):
        SimCellSpec(seed=-1)
    with pytest.raises(ConfigError, match=r"^cell: a 'sim' cell needs a SimCellSpec"):
        open_cell("sim", {"rope": 1})
    assert sorted(CELLS) == ["sim", "xarm"]


def test_a_scenarios_cell_table_sets_the_kind_and_the_cells_defaults():
    scen = parse_scenario(
        {
            "cell": {"kind": "sim", "rope": 3, "seed": 2},
            "run": [{"name": "a"}, {"name": "b", "rope": 4}],
        },
        name="x",
    )
    assert [(r.cell, r.rope, r.seed) for r in scen.runs] == [("sim", 3, 2), ("sim", 4, 2)]
    assert scen.runs[1].cell_spec() == SimCellSpec(rope=4, seed=2)
    with pytest.raises(ConfigError, match=r"^cell\.kind: unknown cell kind 'robot'"):
        parse_scenario({"cell": {"kind": "robot"}, "run": [{"name": "a"}]}, name="x")
    with pytest.raises(
        ConfigError,
        match=r"^cell\.gain: not a field of a 'sim' cell "
        r"\(valid choices: rope, seed, settle_s, knot_set, unknot_held, variation\)$",
    ):
        parse_scenario({"cell": {"gain": 0.5}, "run": [{"name": "a"}]}, name="x")
    with pytest.raises(ConfigError, match=r"^run\[0\]\.cell: unknown field"):
        parse_scenario({"run": [{"name": "a", "cell": "sim"}]}, name="x")


def test_the_variation_is_a_cell_field_and_a_set_key():
    from flyknot_app.cells import sim_lab_params
    from flyknot_app.scenario import parse_overrides
    from flyknot_sim.lab_params import VariationParams

    doc = {"cell": {"variation": {"rest_scale": 0.5}}, "run": [{"name": "a"}]}
    spec = parse_scenario(doc, name="x").runs[0].cell_spec()
    assert sim_lab_params(spec).variation == VariationParams(rest_scale=0.5)
    over = parse_overrides(["cell.variation.servo_gain_rel=0.003"])
    spec = parse_scenario(doc, name="x", overrides=over).runs[0].cell_spec()
    assert sim_lab_params(spec).variation == VariationParams(servo_gain_rel=0.003, rest_scale=0.5)
    assert sim_lab_params(SimCellSpec()).variation == VariationParams()


@pytest.mark.parametrize(
    ("variation", "message"),
    [
        (
            {"gains": 0.1},
            r"^cell\.variation\.gains: not a field of the variation \(valid choices: sway_deg, "
            r"servo_gain_rel, start_delay_max_s, rest_start, rest_scale\)$",
        ),
        (
            {"servo_gain_rel": -0.01},
            r"^cell\.variation\.servo_gain_rel: must be a finite number >= 0, got -0\.01$",
        ),
        ({"rest_scale": 2}, r"^cell\.variation\.rest_scale: must be a number in \[0, 1\], got 2$"),
        ("low", r"^cell\.variation: must be a table of variation fields, got 'low'$"),
    ],
)
def test_a_bad_variation_names_the_field(variation, message):
    with pytest.raises(ConfigError, match=message):
        SimCellSpec(variation=variation)


def test_set_cell_keys_refuse_a_runs_own_field():
    from flyknot_app.scenario import parse_overrides

    with pytest.raises(
        ConfigError, match=r"^--set key: set 'seed' as --set seed=VALUE, not 'cell\.seed'$"
    ):
        parse_overrides(["cell.seed=3"])
    with pytest.raises(ConfigError, match=r"^--set key: expected cell\.FIELD"):
        parse_overrides(["cell..x=3"])


def test_the_runner_closes_the_cell_however_the_run_ends(monkeypatch, tmp_path):
    from flyknot_app import runner

    closed = []

    class Closing:
        base_pose = None

        def close(self):
            closed.append(True)

    monkeypatch.setattr(runner, "open_cell", lambda kind, spec: Closing())

    def boom(lab, *a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "_execute_on", boom)
    spec = parse_scenario({"run": [{"name": "a"}]}, name="x").runs[0]
    with pytest.raises(KeyboardInterrupt):
        runner.execute_run(spec, tmp_path, None, resume=False, progress=False)
    assert closed == [True]


def test_the_sim_cells_early_end_options_reach_the_labs_settle():
    settle = open_cell("sim", SimCellSpec()).params.settle
    assert (settle.knot_set_s, settle.unknot_held_s) == (2.0, 3.0)
    settle = open_cell("sim", SimCellSpec(knot_set=False)).params.settle
    assert (settle.knot_set_s, settle.unknot_held_s) == (None, 3.0)
    settle = open_cell("sim", SimCellSpec(unknot_held=False)).params.settle
    assert (settle.knot_set_s, settle.unknot_held_s) == (2.0, None)
    with pytest.raises(ConfigError, match=r"^cell.knot_set: must be true or false, got 'no'"):
        SimCellSpec(knot_set="no")
    with pytest.raises(ConfigError, match=r"^cell.unknot_held: must be true or false, got 1"):
        SimCellSpec(unknot_held=1)


@pytest.mark.slow
def test_a_run_plays_the_variation_set_on_its_cell(tmp_path, capsys):
    """``flyknot run ... --set cell.variation.FIELD=V`` reaches the lab: its records say so."""
    import json

    from flyknot_app.cli import main

    out = tmp_path / "run"
    sets = ["--set", "cell.variation.rest_scale=0", "--set", "cell.variation.servo_gain_rel=0"]
    assert main(["run", "quick", "--out", str(out), *sets]) == 0
    capsys.readouterr()
    record = json.loads((out / "runs/rope1/learning/trial_0000_a0.json").read_text())
    variation = record["metadata"]["variation"]
    assert variation["rest_scale"] == 0 and variation["servo_gain_rel"] == 0
    assert variation["start_delay_max_s"] == 0.004  # the lab's own where nothing was set
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["overrides"]["cell"] == {"variation": {"rest_scale": 0, "servo_gain_rel": 0}}

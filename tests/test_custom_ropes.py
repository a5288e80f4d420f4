"""Custom ropes: a user's ropes file, named wherever a rope id is accepted."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from flyknot.constants import ASSETS_DIR
from flyknot.errors import ConfigError
from flyknot.record import TrialRecord
from flyknot_app.cli import main
from flyknot_app.scenario import RunSpec, load_scenario, parse_rope_arg, parse_scenario
from flyknot_sim.aero import AeroParams, rope_drag_forces
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab
from flyknot_sim.rope_custom import (
    CUSTOM_KEYS,
    load_custom_ropes,
    parse_custom_ropes,
    resolve_rope,
    rope_record,
)
from flyknot_sim.rope_table import get_rope, load_rope_table

ROPES = """
[[rope]]
name = "my cord"
material = "cotton"
diameter = 0.006
density = 0.02
length = 1.1
end_weight = 0.01
cd = 1.5
damping = 0.02

[[rope]]
name = "heavy chain"
material = "steel"
diameter = 0.045
density = 0.8
length = 1.2
end_weight = 0
timestep = 0.002
"""

PAPER_NAMES = (
    "'#10 sash spot cord', '#14 spot cord', 'soft braided', 'shoe lace', 'thick twisted', "
    "'3/8\" chain', '3/8\" surgical tubing'"
)


@pytest.fixture
def ropes_file(tmp_path):
    p = tmp_path / "my_ropes.toml"
    p.write_text(ROPES)
    return p


def _one(**entry):
    base = {
        "name": "my cord",
        "material": "cotton",
        "diameter": 0.006,
        "density": 0.02,
        "length": 1.1,
        "end_weight": 0.01,
    }
    return {"rope": [{**base, **entry}]}


# --- the file format -------------------------------------------------------------------------
def test_parse_custom_file_defaults_and_overrides(ropes_file):
    ropes = load_custom_ropes(ropes_file)
    assert list(ropes) == ["my cord", "heavy chain"]
    cord = ropes["my cord"]
    assert (cord.id, cord.name, cord.material, cord.custom) == (
        "my cord",
        "my cord",
        "cotton",
        True,
    )
    assert (cord.diameter, cord.density, cord.length, cord.end_mass) == (0.006, 0.02, 1.1, 0.01)
    # cotton's E and G of rope 1 (9 mm, 40 g/m) scaled so that EI grows with the linear density,
    # as the paper's table does: EI / tex the same as rope 1's
    assert cord.bend_modulus == pytest.approx(7.0e4 * (0.02 / 0.04) * (9 / 6) ** 4)
    assert cord.shear_modulus == pytest.approx(2.33e4 * (0.02 / 0.04) * (9 / 6) ** 4)
    rope1 = get_rope(1)
    assert cord.bending_stiffness / cord.density == pytest.approx(
        rope1.bending_stiffness / rope1.density
    )
    assert cord.bend_hysteresis == 54.0  # the lab's cotton: the frictional couple
    assert cord.friction == 0.5  # the material's
    assert cord.damping == 0.02 and cord.cd == 1.5  # the overrides
    assert (cord.segments, cord.timestep) == (30, 0.001)  # the defaults
    chain = ropes["heavy chain"]
    assert (chain.bend_modulus, chain.shear_modulus, chain.damping, chain.friction) == (
        0.0,
        0.0,
        0.0,
        0.57,
    )
    assert chain.cd is None and chain.timestep == 0.002 and chain.end_mass == 0.0
    # 30 segments of 40 mm would not exceed the 45 mm diameter: capped at 26 (46 mm)
    assert chain.segments == 26 and chain.segment_length > chain.diameter
    assert isinstance(chain.length, float) and isinstance(chain.end_mass, float)


def test_shipped_example_parses():
    ropes = load_custom_ropes(ASSETS_DIR / "ropes_example.toml")
    assert "climbing cord" in ropes
    assert all(p.custom and p.segment_length > p.diameter for p in ropes.values())


def test_paper_ropes_unchanged_and_named():
    table = load_rope_table()
    assert sorted(table) == [1, 2, 3, 4, 5, 6, 7]
    for rid, p in table.items():
        assert p.cd is None and not p.custom and "cd" not in p.to_dict()
        assert resolve_rope(rid) == p
        assert resolve_rope(str(rid)) == p
        assert resolve_rope(p.name) == p
    assert resolve_rope("shoe lace") == get_rope(4)
    assert parse_rope_arg("4") == 4 and parse_rope_arg("my cord") == "my cord"
    assert LabParams(rope="shoe lace").rope == 4  # a paper rope's name becomes its id
    assert rope_record(get_rope(4)) == {
        "rope": 4,
        "rope_name": "shoe lace",
        "rope_diameter_m": 0.007,
    }


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        (
            _one(material="nylon"),
            "rope[0].material: unknown value 'nylon' (valid choices: cotton, steel, latex)",
        ),
        (_one(diameter=-0.01), "rope[0].diameter: must be a finite number > 0, got -0.01"),
        (
            {"rope": [{k: v for k, v in _one()["rope"][0].items() if k != "name"}]},
            "rope[0]: missing key(s) name",
        ),
        (
            {"rope": _one()["rope"] * 2},
            "rope[1].name: duplicate rope name 'my cord'",
        ),
        (
            _one(colour="red"),
            "rope[0].colour: unknown key (valid choices: " + ", ".join(CUSTOM_KEYS) + ")",
        ),
        (_one(end_weight=-1), "rope[0].end_weight: must be a finite number >= 0, got -1"),
        (_one(cd=0), "rope[0].cd: must be a finite number > 0, got 0"),
        (
            _one(lock_angle=-1),
            "rope[0].lock_angle: must lie in [0, 180) deg (at 180 a segment folds back onto "
            "the last), got -1",
        ),
        (
            _one(lock_angle="steep"),
            "rope[0].lock_angle: must lie in [0, 180) deg (at 180 a segment folds back onto "
            "the last), got 'steep'",
        ),
        (
            _one(stretch_modulus=-5e5),
            "rope[0].stretch_modulus: must be a finite number >= 0, got -500000.0",
        ),
        (
            _one(stretch_modulus="rubbery"),
            "rope[0].stretch_modulus: must be a finite number >= 0, got 'rubbery'",
        ),
        (_one(segments=2.5), "rope[0].segments: must be an integer, got 2.5"),
        (
            _one(segments=200),
            "rope[0].segments: segment length 0.0055 m must exceed the diameter 0.006 m "
            "(elements sharing no vertex would touch at rest); use at most 183 segments",
        ),
        (
            _one(timestep=0.01),
            "rope[0].timestep: must lie in (0, 0.004] s (the robot's command tick), got 0.01",
        ),
        (
            _one(length=0.8),
            "rope[0].length: must exceed 1 m (the 11 markers sit every 0.1 m from the held "
            "end, the last one at the free end), got 0.8",
        ),
        (
            _one(name="shoe lace"),
            "rope[0].name: 'shoe lace' is the paper's rope 4; give your rope another name",
        ),
        (
            _one(name="8"),
            "rope[0].name: must not be a number (1..7 are the paper's rope ids), got '8'",
        ),
        ({"rope": []}, "rope: the ropes file needs at least one [[rope]] table"),
        ({"ropes": []}, "ropes: unknown top-level key of a ropes file (valid choices: rope)"),
    ],
)
def test_bad_ropes_have_exact_messages(doc, message):
    with pytest.raises(ConfigError) as e:
        parse_custom_ropes(doc)
    assert str(e.value) == message


def test_unknown_rope_name_lists_ids_and_names(ropes_file):
    with pytest.raises(ConfigError) as e:
        resolve_rope("nope", ropes_file)
    assert str(e.value) == (
        f"rope: unknown rope name 'nope' (valid choices: 1, 2, 3, 4, 5, 6, 7, {PAPER_NAMES}, "
        "'my cord', 'heavy chain')"
    )
    with pytest.raises(ConfigError) as e:
        resolve_rope("my cord")
    assert str(e.value) == (
        "rope: unknown rope name 'my cord', and no ropes file was given (valid choices: "
        f"1, 2, 3, 4, 5, 6, 7, {PAPER_NAMES})"
    )
    with pytest.raises(ConfigError) as e:
        LabParams(rope=9)
    assert str(e.value) == "rope: unknown rope id 9 (valid choices: 1, 2, 3, 4, 5, 6, 7)"
    with pytest.raises(ConfigError, match=r"^ropes: no ropes file '.*missing.toml'$"):
        LabParams(rope="my cord", ropes=str(ropes_file.parent / "missing.toml"))


def test_bad_toml_and_file_changes_are_seen(tmp_path):
    p = tmp_path / "r.toml"
    p.write_text("[[rope]\nname = ")
    with pytest.raises(ConfigError, match=r"^ropes: .*r\.toml: not valid TOML: "):
        load_custom_ropes(p)
    p.write_text(ROPES)
    assert load_custom_ropes(p)["my cord"].cd == 1.5
    p.write_text(ROPES.replace("cd = 1.5", "cd = 2.5"))
    assert load_custom_ropes(p)["my cord"].cd == 2.5


# --- the labs ----------------------------------------------------------------------------------
def test_sim_trial_with_a_custom_rope(ropes_file, tmp_path):
    params = LabParams(rope="my cord", ropes=str(ropes_file), settle_s=0.1)
    lab = SimLab(params)
    assert lab.rope_params == load_custom_ropes(ropes_file)["my cord"]
    assert lab.rope.n_vert == 31
    # the cd override reaches the drag
    assert params.aero.cd is None and lab.plant.drag.params.cd == 1.5
    rec = lab.run(swing_command(duration=0.3, amplitude=np.full(7, 0.1)))
    assert rec.fault is None and rec.knot is not None
    meta = rec.metadata
    assert meta["rope"] == "my cord" and meta["rope_name"] == "my cord"
    assert meta["rope_params"]["diameter"] == 0.006 and meta["rope_params"]["cd"] == 1.5
    assert meta["ropes_file"] == str(ropes_file.resolve())
    rec.save(tmp_path / "trial")
    back = TrialRecord.load(tmp_path / "trial")
    assert back.metadata["rope_params"] == meta["rope_params"]


def test_cd_changes_the_drag_force(ropes_file):
    p = load_custom_ropes(ropes_file)["my cord"]
    x = np.column_stack([np.zeros(5), np.zeros(5), -np.linspace(0, 0.2, 5)])
    v = np.tile([2.0, 0.0, 0.0], (5, 1))  # across the rope
    f_curve = rope_drag_forces(x, v, p.diameter, 0.0, AeroParams())
    f_rope = rope_drag_forces(x, v, p.diameter, 0.0, AeroParams(cd=p.cd))
    f_double = rope_drag_forces(x, v, p.diameter, 0.0, AeroParams(cd=2 * p.cd))
    assert not np.allclose(f_curve, f_rope)
    np.testing.assert_allclose(f_double, 2 * f_rope)


def test_hand_lab_takes_a_custom_rope_and_its_cd(ropes_file):
    from flyknot_sim.hand import HandLab
    from flyknot_sim.hand_params import HandParams

    hand = HandParams(rope="heavy chain", ropes=str(ropes_file))
    assert hand.rope_params.segments == 26
    lab = HandLab(replace(hand, rope="my cord"))
    assert lab._drag.params.cd == 1.5 and lab.rope.n_vert == 31
    assert HandLab(HandParams(rope=1))._drag.params.cd is None


# --- command line and scenarios ---------------------------------------------------------------
def test_cli_trial_with_ropes_file(ropes_file, tmp_path, capsys):
    cmd = tmp_path / "c.csv"
    swing_command(duration=0.2, amplitude=np.full(7, 0.05)).save(cmd)
    out = tmp_path / "o"
    argv = ["trial", "--ropes", str(ropes_file), "--rope", "my cord", "--command", str(cmd)]
    assert main([*argv, "--out", str(out), "--settle", "0.1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rope"] == "my cord" and summary["fault"] is None
    meta = TrialRecord.load(out / "trial").metadata
    assert meta["rope"] == "my cord" and meta["rope_params"]["cd"] == 1.5
    # errors: one line, exit 2
    assert main(["trial", "--rope", "nope", "--ropes", str(ropes_file), "--command", str(cmd),
                 "--out", str(tmp_path / "o2")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.startswith("flyknot: error: rope: unknown rope name 'nope' (valid choices: 1, 2")
    assert err.endswith("'my cord', 'heavy chain')\n") and err.count("\n") == 1


@pytest.mark.parametrize(
    ("value", "valid"),
    [
        ("-1.0e5", "must be a finite number >= 0, got -100000.0"),
        ('"stiff"', "must be a finite number >= 0, got 'stiff'"),
        ("2.0e6", "2e+06 Pa makes an edge's spring faster than MuJoCo's soft constraint"),
    ],
)
def test_cli_a_bad_stretch_modulus_is_one_line_and_exit_2(tmp_path, capsys, value, valid):
    bad = tmp_path / "tubes.toml"
    bad.write_text(
        '[[rope]]\nname = "tube"\nmaterial = "latex"\ndiameter = 0.009\ndensity = 0.026\n'
        f"length = 1.1\nend_weight = 0.018\nstretch_modulus = {value}\n"
    )
    cmd = tmp_path / "c.csv"
    swing_command(duration=0.2, amplitude=np.full(7, 0.05)).save(cmd)
    argv = ["trial", "--ropes", str(bad), "--rope", "tube", "--command", str(cmd)]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"flyknot: error: rope[0].stretch_modulus: {valid}")
    assert err.count("\n") == 1 and not (tmp_path / "o").exists()


def test_scenario_with_a_ropes_file(ropes_file, tmp_path, monkeypatch):
    scen_path = tmp_path / "mine.toml"
    scen_path.write_text(
        'ropes = "my_ropes.toml"\n'
        "[defaults]\nmax_trials = 2\n"
        '[[run]]\nname = "cord"\nrope = "my cord"\n'
        '[[run]]\nname = "lace"\nrope = "shoe lace"\n'
    )
    monkeypatch.chdir(tmp_path.parent)  # the file is found beside the scenario, not in cwd
    scen = load_scenario(str(scen_path))
    cord, lace = scen.runs
    assert (cord.rope, cord.ropes) == ("my cord", str(ropes_file.resolve()))
    assert lace.rope == 4  # a paper rope's name becomes its id
    lab = LabParams(rope=cord.rope, ropes=cord.ropes)
    assert lab.rope_params.cd == 1.5
    from flyknot_app.runner import _ropes_manifest

    used = _ropes_manifest(scen)["ropes"]
    assert list(used) == [cord.ropes] and used[cord.ropes]["my cord"]["cd"] == 1.5
    from flyknot_app.cli import build_parser

    args = build_parser().parse_args(["run", str(scen_path), "--ropes", "x.toml"])
    assert args.ropes == "x.toml"
    # grid values name ropes too; run names stay directory names
    doc = {"ropes": str(ropes_file), "grid": {"rope": [1, "my cord", "heavy chain"]}}
    scen = parse_scenario(doc, name="g")
    assert [r.name for r in scen.runs] == ["rope1", "ropemy_cord", "ropeheavy_chain"]
    assert [r.rope for r in scen.runs] == [1, "my cord", "heavy chain"]
    # --ropes replaces the scenario's file; relative to the working directory
    other = tmp_path / "other.toml"
    other.write_text(ROPES.replace("my cord", "your cord"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"^rope: unknown rope name 'my cord' \(valid"):
        load_scenario(str(scen_path), ropes="other.toml")
    # errors
    with pytest.raises(ConfigError) as e:
        parse_scenario({"ropes": "nowhere.toml", "run": [{"name": "a"}]}, name="x")
    assert str(e.value) == "ropes: no ropes file 'nowhere.toml'"
    with pytest.raises(ConfigError) as e:
        parse_scenario({"run": [{"name": "a", "ropes": "x.toml"}]}, name="x")
    assert str(e.value).startswith("run[0].ropes: unknown field (valid choices: name, rope,")
    with pytest.raises(ConfigError, match=r"^rope: unknown rope name 'my cord', and no ropes"):
        RunSpec(name="a", rope="my cord")


def test_gym_env_accepts_a_rope_name(ropes_file):
    pytest.importorskip("gymnasium")
    from flyknot_app.gym.env import FlyknotEnv

    env = FlyknotEnv(rope="my cord", ropes=str(ropes_file), settle_s=0.1)
    assert env._lab.rope_params.name == "my cord" and env._lab.plant.drag.params.cd == 1.5


def test_demo_replay_on_a_custom_rope(ropes_file, tmp_path, capsys):
    from flyknot.constants import DEMOS_DIR

    out = tmp_path / "replays"
    argv = ["demo", "replay", str(DEMOS_DIR / "fast.npz"), "--ropes", str(ropes_file)]
    argv += ["--rope", "my cord", "--nominal", "--settle", "0.2", "--out", str(out), "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["repeats"] == 1 and result["outcomes"][0] is not None
    with np.load(out / "replay_000.npz") as z:
        meta = json.loads(str(z["meta"]))
        assert z["centreline"].shape[1:] == (31, 3)
    assert meta["rope"] == "my cord" and meta["metadata"]["rope_params"]["cd"] == 1.5
    # making a demonstration needs one of the paper's ropes (Demonstration.rope is an id)
    from flyknot.demo import Demonstration
    from flyknot_sim.hand_params import HandParams
    from flyknot_sim.hand_replay import motion_from_demo
    from flyknot_tools.hand_demos.synthesis import make_demonstration

    motion = motion_from_demo(Demonstration.load(DEMOS_DIR / "fast.npz"))
    with pytest.raises(ConfigError, match=r"^rope: a demonstration records one of the paper"):
        make_demonstration(
            motion, variant="fast", seed=0, hand=HandParams(rope="my cord", ropes=str(ropes_file))
        )

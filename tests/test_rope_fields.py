"""The rope fields, declared once (flyknot_sim.rope_fields): the ropes table, a user's ropes
file, ``rope-validate --set`` and their messages all read the declaration."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
import tomllib
from dataclasses import MISSING, fields, replace
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flyknot.constants import ROPE_TABLE
from flyknot.errors import ConfigError
from flyknot_sim.rope_custom import CUSTOM_KEYS, CUSTOM_OPTIONAL, CUSTOM_REQUIRED
from flyknot_sim.rope_custom import parse_custom_ropes as parse_file
from flyknot_sim.rope_fields import (
    FIELD,
    REQUIRED,
    ROPE_FIELDS,
    SETTABLE,
    ByMaterial,
    Range,
    RopeField,
    rope_dataclass,
)
from flyknot_sim.rope_table import RopeParams, get_rope, parse_rope_table
from flyknot_tools.rope_validate.suite import model_with

ROOT = Path(__file__).resolve().parents[1]
MATERIALS = tomllib.loads(ROPE_TABLE.read_text())["materials"]
"""The lab's materials."""
RANGED = [f for f in ROPE_FIELDS if isinstance(f.valid, Range)]


def _table(**entry):
    """A ropes table of the lab's materials and rope 1 (all its fields given), changed."""
    rope = {**get_rope(1).to_dict(), **entry}
    return {"materials": {m: dict(v) for m, v in MATERIALS.items()}, "rope": [rope]}


def _file(**entry):
    """A ropes file of one rope with only the required keys, changed."""
    base = {"name": "my cord", "material": "cotton", "diameter": 0.006, "density": 0.02}
    return {"rope": [{**base, "length": 1.1, "end_weight": 0.01, **entry}]}


def _set(name, text):
    """Rope 1 with ``--set name=text``."""
    return model_with(get_rope(1), {name: text}).params


# --- every door reads every field ------------------------------------------------------------
def test_the_declaration_is_the_ropes_fields():
    assert tuple(f.name for f in fields(RopeParams)) == tuple(f.name for f in ROPE_FIELDS)
    for f in fields(RopeParams):
        default = FIELD[f.name].default
        assert f.default is MISSING if default is REQUIRED else f.default == default
    # a ropes file has every field but the id (a custom rope's id is its name)
    file_names = {f.name for f in ROPE_FIELDS if f.file_key in CUSTOM_KEYS}
    assert file_names == {f.name for f in ROPE_FIELDS} - {"id"}
    assert len(CUSTOM_KEYS) == len(set(CUSTOM_KEYS)) == len(ROPE_FIELDS) - 1
    assert CUSTOM_REQUIRED == ("name", "material", "diameter", "density", "end_weight", "length")
    by_material = {f.name for f in ROPE_FIELDS if f.by_material is not ByMaterial.NO}
    assert by_material <= set(CUSTOM_OPTIONAL)
    assert tuple(f.name for f in ROPE_FIELDS if f.name not in ("id", "name")) == SETTABLE
    for f in ROPE_FIELDS:  # the docstring lists every field with its unit
        assert f"{f.name}{f' [{f.unit}]' if f.unit else ''}: " in RopeParams.__doc__


@pytest.mark.parametrize("f", ROPE_FIELDS, ids=lambda f: f.name)
def test_every_field_is_read_by_the_table_the_file_and_set(f):
    """A field's example (a valid value, not its default) reaches the rope through each door;
    a field that one of them left out would keep its default and fail here."""
    (rope,) = parse_rope_table(_table(**{f.name: f.example})).values()
    assert getattr(rope, f.name) == f.example
    if f.by_material is not ByMaterial.NO:  # from the material's table too
        doc = _table()
        doc["rope"][0].pop(f.name, None)  # rope 1 leaves out a field at its default
        doc["materials"]["cotton"][f.name] = f.example
        assert getattr(parse_rope_table(doc)[1], f.name) == f.example
    if f.in_file:
        (rope,) = parse_file(_file(**{f.file_key: f.example})).values()
        assert getattr(rope, f.name) == f.example
    else:
        with pytest.raises(ConfigError, match=rf"^rope\[0\]\.{f.name}: unknown key"):
            parse_file(_file(**{f.name: f.example}))
    if f.settable:
        assert getattr(_set(f.name, str(f.example)), f.name) == f.example
    else:
        with pytest.raises(ConfigError, match=rf"^--set: unknown field '{f.name}'"):
            _set(f.name, str(f.example))


def test_a_field_left_out_takes_its_default():
    doc = _table()
    for f in ROPE_FIELDS:
        if f.default is not REQUIRED:
            doc["rope"][0].pop(f.name, None)
    doc["materials"]["cotton"].pop("bend_hysteresis")
    rope = parse_rope_table(doc)[1]
    assert (rope.cd, rope.condim, rope.torsional_friction, rope.bend_hysteresis) == (
        None,
        3,
        None,
        0.0,
    )
    (mine,) = parse_file(_file(material="latex")).values()
    assert (mine.segments, mine.timestep, mine.bend_hysteresis) == (30, 0.001, 0.0)
    assert (mine.bend_modulus, mine.damping) == (7.6e5, 0.0015)  # latex's, not scaled


# --- messages: the field and its valid values -------------------------------------------------
@pytest.mark.parametrize(
    ("door", "name", "value", "message"),
    [
        ("table", "bend_hysteresis", -3, "bend_hysteresis: must be a finite number >= 0, got -3"),
        ("table", "condim", 6, "condim: unknown value 6 (valid choices: 3, 4)"),
        ("file", "friction", 0, "rope[0].friction: must be a finite number > 0, got 0"),
        (
            "file",
            "timestep",
            -1,
            "rope[0].timestep: must lie in (0, 0.004] s (the robot's command tick), got -1",
        ),
        ("file", "end_weight", "heavy", "rope[0].end_weight: must be a finite number >= 0, got "
         "'heavy'"),
        ("set", "bend_hysteresis", "-3", "bend_hysteresis: must be a finite number >= 0, got -3.0"),
        ("set", "segments", "2.5", "segments: must be an integer, got 2.5"),
        ("set", "segments", "1", "segments: must be >= 2, got 1"),
        ("set", "condim", "5", "condim: unknown value 5 (valid choices: 3, 4)"),
        ("set", "material", "wool", "material: unknown value 'wool' (valid choices: cotton, "
         "steel, latex)"),
        ("set", "cd", "inf", "cd: must be a finite number > 0, got inf"),
        ("set", "diameter", "thick", "diameter: must be a number, got 'thick'"),
    ],
)  # fmt: skip
def test_out_of_range_messages(door, name, value, message):
    with pytest.raises(ConfigError) as e:
        if door == "table":
            parse_rope_table(_table(**{name: value}))
        elif door == "file":
            parse_file(_file(**{name: value}))
        else:
            _set(name, value)
    assert str(e.value) == message


def _outside(f: RopeField):
    r = f.valid
    if r.integer:
        return st.integers(max_value=math.ceil(r.low) - (1 if r.low_in else 0))
    return (st.floats(max_value=r.low) | st.sampled_from([math.inf, -math.inf, math.nan])).filter(
        lambda v: not r.contains(v)
    )


@given(st.sampled_from(RANGED).flatmap(lambda f: st.tuples(st.just(f), _outside(f))))
def test_a_value_out_of_range_is_refused_alike_by_every_door(field_value):
    """Whichever door a value out of a field's range comes in by, the message names the
    field (as that door does) and its range, and quotes the value."""
    f, v = field_value
    bound = f.valid.text().removeprefix("an integer ")
    with pytest.raises(ConfigError) as e:
        replace(get_rope(1), **{f.name: v})
    own = e.value
    assert own.field == f.name and bound in own.problem and f"got {v!r}" in own.problem
    with pytest.raises(ConfigError) as e:
        parse_rope_table(_table(**{f.name: v}))
    assert str(e.value) == str(own)
    if f.settable:
        with pytest.raises(ConfigError) as e:
            _set(f.name, repr(v))
        assert str(e.value) == str(own)
    if f.in_file:
        with pytest.raises(ConfigError) as e:
            parse_file(_file(**{f.file_key: v}))
        assert e.value.field == f"rope[0].{f.file_key}"
        assert f"got {v!r}" in e.value.problem
        assert (f.file_valid or f.valid).text(f.unit).removeprefix("an integer ") in (
            e.value.problem
        )


# --- the declaration checks itself ------------------------------------------------------------
def test_a_bad_declaration_is_refused():
    with pytest.raises(ConfigError) as e:
        RopeField("stiffness", float, "Pa", Range(0.0), "E.", example=0.0, default=0.0)
    assert str(e.value) == "rope field stiffness: needs an example other than its default 0.0"
    with pytest.raises(ConfigError) as e:
        RopeField("stiffness", float, "Pa", Range(0.0), "E.", example=1.0, default=-1.0)
    assert str(e.value) == "rope field stiffness default: must be a finite number > 0, got -1.0"
    with pytest.raises(ConfigError) as e:
        Range(1.0, 0.5)
    assert str(e.value) == "range: needs a finite low < high, got 1.0, 0.5"
    with pytest.raises(ConfigError) as e:

        @rope_dataclass
        class Own:
            x: float = 0.0

    assert str(e.value) == "Own: declares its fields in flyknot_sim/rope_fields.py"


def test_describe_names_unit_range_and_default():
    assert FIELD["timestep"].describe() == (
        "timestep [s]: Largest simulation step this rope was validated at. (> 0; (0, 0.004] s "
        "in a ropes file; default 0.001 in a ropes file)"
    )
    assert FIELD["bend_hysteresis"].describe().endswith("(>= 0; default the material's, else 0.0)")
    assert FIELD["end_mass"].describe().endswith("(>= 0; 'end_weight' in a ropes file)")


# --- adding a field ----------------------------------------------------------------------------
ADD_A_FIELD = """
import flyknot_sim.rope_fields as rf

new = rf.RopeField("twist_damping", float, "s", rf.NONNEGATIVE, "Damping time of twist.",
                   example=0.5, default=0.0, by_material=rf.ByMaterial.VALUE)
rf.ROPE_FIELDS += (new,)
rf.FIELD = {f.name: f for f in rf.ROPE_FIELDS}
rf.SETTABLE += (new.name,)

import tomllib
from flyknot.constants import ROPE_TABLE
from flyknot.errors import ConfigError
from flyknot_sim.rope_custom import parse_custom_ropes
from flyknot_sim.rope_table import get_rope, parse_rope_table
from flyknot_tools.rope_validate.suite import model_with

assert get_rope(1).twist_damping == 0.0 and "twist_damping" not in get_rope(1).to_dict()
doc = tomllib.loads(ROPE_TABLE.read_text())
doc["materials"]["cotton"]["twist_damping"] = 0.25
assert parse_rope_table(doc)[1].twist_damping == 0.25
rope = {"name": "c", "material": "cotton", "diameter": 0.006, "density": 0.02, "length": 1.1,
        "end_weight": 0.01}
assert parse_custom_ropes({"rope": [rope]})["c"].twist_damping == 0.0
assert parse_custom_ropes({"rope": [{**rope, "twist_damping": 2}]})["c"].twist_damping == 2.0
assert model_with(get_rope(1), {"twist_damping": "0.5"}).params.twist_damping == 0.5
try:
    model_with(get_rope(1), {"twist_damping": "-1"})
except ConfigError as e:
    print(e)
"""


def test_adding_a_field_is_one_declaration():
    """A new field with a default, declared and nothing else: the table (its materials too),
    a ropes file and --set take it, checked by its range; the paper ropes' records without
    it read as before."""
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(ADD_A_FIELD)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout == "twist_damping: must be a finite number >= 0, got -1.0\n"

"""Options read from and written to mappings by their dataclass fields (flyknot.options),
and a run's summary (flyknot_app.reports.run_summary) read back as it was written."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot.options import (
    INLINE,
    NOT_AN_OPTION,
    from_mapping,
    nested_options,
    option_keys,
    option_names,
    to_mapping,
)
from flyknot_app.reports.run_summary import OPTION_KEYS, RunSummary, ScenarioSummary
from flyknot_app.scenario import RunSpec
from learner.ilc_params import ILCParams
from learner.inverse_qp import InverseModelWeights
from learner.update import UpdateSettings


@dataclass(frozen=True)
class Inner:
    """A nested table."""

    a: float = 1.0
    b: int = 2


@dataclass(frozen=True)
class Side:
    """Options that sit beside the outer class's."""

    c: str = "x"
    inner: Inner = field(default_factory=Inner)


@dataclass(frozen=True)
class Outer:
    """An outer class with every kind of field."""

    n: int = 0
    side: Side = field(default_factory=Side, metadata=INLINE)
    hidden: str = field(default="program", metadata=NOT_AN_OPTION)

    def __post_init__(self) -> None:
        if self.n < 0:
            raise ConfigError("n", f"must be >= 0, got {self.n!r}")


def test_names_keys_and_nesting():
    assert option_names(Outer) == ("n", "c", "inner")
    assert option_keys(Outer) == ("n", "c", "inner.a", "inner.b")
    assert nested_options(Outer, "inner") is Inner and nested_options(Outer, "c") is None
    with pytest.raises(ConfigError) as e:
        nested_options(Outer, "hidden")
    assert str(e.value) == "hidden: unknown field (valid choices: n, c, inner)"


def test_from_mapping_builds_nested_and_inline_fields():
    got = from_mapping(Outer, {"n": 3, "c": "y", "inner": {"b": 5}})
    assert got == Outer(3, Side("y", Inner(1.0, 5)))
    over = from_mapping(Outer, {"inner": {"a": 9.0}}, base=got)
    assert over == Outer(3, Side("y", Inner(9.0, 5)))  # what the mapping leaves out stays
    assert from_mapping(Outer, {}, given={"hidden": "set"}).hidden == "set"


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"m": 1}, "run[1].m: unknown field (valid choices: n, c, inner)"),
        ({"hidden": "x"}, "run[1].hidden: unknown field (valid choices: n, c, inner)"),
        ({"inner": {"z": 1}}, "run[1].inner.z: unknown field (valid choices: a, b)"),
        ({"inner": 3}, "run[1].inner: must be a table of options, got 3"),
        ({"n": -1}, "n: must be >= 0, got -1"),
    ],
)
def test_bad_mappings_name_the_field(values, message):
    with pytest.raises(ConfigError) as e:
        from_mapping(Outer, values, where="run[1]")
    assert str(e.value) == message


def test_adding_an_option_is_one_field():
    """A field added to a nested class is an option everywhere, with no other change."""

    @dataclass(frozen=True)
    class Side2(Side):
        d: float = 0.5

    @dataclass(frozen=True)
    class Outer2(Outer):
        side: Side2 = field(default_factory=Side2, metadata=INLINE)

    assert "d" in option_names(Outer2)
    assert from_mapping(Outer2, {"d": 0.25}).side.d == 0.25
    assert to_mapping(Outer2())["d"] == 0.5


_loop = st.fixed_dictionaries(
    {},
    optional={
        "max_trials": st.integers(0, 30),
        "stop_at_success": st.booleans(),
        "tracking_retries": st.integers(0, 4),
        "gain": st.floats(0.01, 1.0),
        "safeguard": st.booleans(),
        "average": st.integers(1, 5),
        "objective": st.sampled_from(["critical", "equal"]),
        "backend": st.sampled_from(["clarabel", "osqp"]),
        "trust_region": st.none() | st.floats(0.01, 1.0),
        "margin": st.floats(0.0, 1.0),
        "weights": st.fixed_dictionaries({}, optional={"w_control": st.floats(0.1, 10.0)}),
        "rope_model": st.fixed_dictionaries({}, optional={"stiffness": st.floats(1.0, 1e5)}),
        "fit": st.fixed_dictionaries({}, optional={"degree": st.sampled_from([1, 2])}),
    },
)


@settings(max_examples=60, deadline=None)
@given(_loop)
def test_learner_options_round_trip(values):
    params = from_mapping(ILCParams, values)
    back = from_mapping(ILCParams, json.loads(json.dumps(to_mapping(params))))
    assert to_mapping(back) == to_mapping(params)
    for key, value in values.items():
        if not isinstance(value, dict):
            got = getattr(params, key) if hasattr(params, key) else getattr(params.update, key)
            assert got == value


def test_the_update_settings_are_the_loops_options_but_the_limits():
    loop = [f.name for f in fields(ILCParams) if f.name != "update"]
    update = [f.name for f in fields(UpdateSettings) if f.name != "limits"]
    assert option_names(ILCParams) == (*loop, *update)
    params = from_mapping(ILCParams, {"objective": "equal", "weights": {"w_control": 5.0}})
    assert params.update == UpdateSettings(objective="equal", weights=InverseModelWeights(5.0))


def test_a_summary_reads_back_what_it_wrote():
    spec = from_mapping(RunSpec, {"name": "r", "rope": 3, "seed": 2, "gain": 0.5, "repeats": 2})
    summary = RunSummary(
        spec.to_json(),
        costs=[0.5, None],
        knots=[False, True],
        faults=[None, None],
        verdicts=[{"klass": "unknot"}, {"klass": "knot"}],
        trials_to_success=2,
        stopped_because="success",
        attempts=2,
        repeat_classes=["knot", "fault"],
        judge="verdict",
        T=1.2,
        t_c=0.65,
    )
    doc = json.loads(json.dumps(ScenarioSummary("s", "learn", (summary,)).to_json()))
    assert doc["runs"][0]["repeats"] == 2 and doc["runs"][0]["repeat_success_rate"] == 0.5
    back = ScenarioSummary.from_json(doc).runs[0]
    assert back.to_json() == summary.to_json()
    assert (back.name, back.rope, back.seed, back.learner.gain) == ("r", 3, 2, 0.5)


def test_no_outcome_field_shadows_a_run_option():
    own = {f.name for f in fields(RunSummary)} - {"options"}
    assert not own & set(OPTION_KEYS)


def test_runs_and_summaries_travel_to_worker_processes():
    """A run's options go to a worker process and its summary comes back (pickled)."""
    import pickle

    from flyknot.options import ReadOnlyMap
    from flyknot_app.scenario import load_scenario

    spec = load_scenario("04-success-rate").runs[0]
    assert pickle.loads(pickle.dumps(spec)) == spec
    summary = RunSummary(spec.to_json(), costs=[0.5], initial_guess={"cost": 1.0}, T=1.0)
    back = pickle.loads(pickle.dumps(summary))
    assert back == summary and back.to_json() == summary.to_json()
    frozen = ReadOnlyMap({"a": 1})
    assert pickle.loads(pickle.dumps(frozen)) == {"a": 1}
    with pytest.raises(AttributeError):
        frozen._data = {}
    with pytest.raises(TypeError):
        frozen["a"] = 2  # type: ignore[index]

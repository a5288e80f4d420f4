"""Tests of flyknot_tools/robot_demo.py (robot demonstrations) and
``flyknot-tools demo robot|record``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError
from flyknot_tools import cli as tools_cli
from flyknot_tools.robot_demo import (
    CommandSearchConfig,
    CommandSpace,
    command_score,
    free_from_knots,
    knots_from_free,
    record_demonstration,
    search_command,
)
from flyknot_tools.robot_rate import RateSearchConfig, rate_search
from tests.knot_curves import verdict
from tests.recorded_on import assert_recorded_again

ROBOT_DEMO = DEMOS_DIR / "robot.npz"


@given(st.integers(0, 10_000))
@settings(max_examples=20)
def test_free_knots_round_trip_and_rest(seed: int):
    rng = np.random.default_rng(seed)
    free, base = rng.normal(size=(7, 6)), rng.normal(size=(3, 8))
    k = knots_from_free(free, base)
    np.testing.assert_array_equal(free_from_knots(k), free)
    np.testing.assert_array_equal(k[:7, 1], k[:7, 0])  # zero start velocity
    np.testing.assert_array_equal(k[:7, 6], k[:7, 7])  # zero end velocity
    np.testing.assert_array_equal(k[7:], base)


def test_bad_shapes_and_config_messages():
    with pytest.raises(ConfigError) as e:
        free_from_knots(np.zeros((7, 8)))
    assert str(e.value) == "knots: must have shape (10, 8), got (7, 8)"
    with pytest.raises(ConfigError) as e:
        CommandSpace(duration=(1.0, 0.5))
    assert str(e.value) == "duration: need 0.1 <= lo < hi <= 5 s, got (1.0, 0.5)"
    with pytest.raises(ConfigError) as e:
        CommandSpace(knot_scale=0.0)
    assert str(e.value) == "knot_scale: must be a finite number > 0, got 0.0"
    # Both searches move a command the same way: one space, one default.
    assert CommandSearchConfig().space == RateSearchConfig().space == CommandSpace()
    with pytest.raises(ConfigError, match="evaluations: must be an integer >= 1, got 0"):
        CommandSearchConfig(evaluations=0)
    with pytest.raises(ConfigError) as e:
        CommandSearchConfig(target_rate=0)
    assert str(e.value) == "target_rate: must lie in (0, 1], got 0"
    with pytest.raises(ConfigError, match="local_evaluations: must be an integer >= 0, got -1"):
        CommandSearchConfig(local_evaluations=-1)


@pytest.fixture(scope="module")
def shipped():
    demo = Demonstration.load(ROBOT_DEMO)
    return demo, np.array(demo.metadata["command_knots"]), float(demo.metadata["command_T"])


def test_shipped_robot_demo_is_its_commands_nominal_trial(shipped):
    from flyknot_sim.lab import LabParams, VariationParams

    demo, knots, T = shipped
    # Recorded in the lab's defaults without variation.
    made_in = LabParams(variation=VariationParams.none())
    again = record_demonstration(knots, T, rope=demo.rope, lab_params=made_in)
    assert_recorded_again(again, demo)
    assert demo.metadata["knot"] == "trefoil"
    assert 0.3 < demo.t_c < T  # the rope touches itself during the motion
    # the stored command's base rows are the lab's base: the demonstration's frame
    from flyknot_sim.lab import SimLab

    base = SimLab(made_in).base_pose[:3]
    np.testing.assert_array_equal(knots[7:], np.repeat(base[:, None], 8, axis=1))
    np.testing.assert_array_equal(np.asarray(again.metadata["command_knots"]), knots)


def test_score_of_a_tie_and_of_a_fault(shipped):
    from flyknot_sim.lab import LabParams, SimLab, VariationParams
    from learner.bezier import BezierCommand

    _, knots, T = shipped
    lab = SimLab(LabParams(rope=1, variation=VariationParams.none()))
    rec = lab.run(BezierCommand(knots, T).joint_command())
    # The shipped demonstration's nominal trial ties a knot in the hanging rope: a hit.
    assert rec.knot == "trefoil" and rec.verdict.klass == "knot"
    assert command_score(rec, T) >= 100.0
    wrapped = dataclasses.replace(rec, verdict=verdict("wrapped_at_grip"))
    assert command_score(wrapped, T) == pytest.approx(command_score(rec, T) - 100.0)
    faulted = dataclasses.replace(rec, fault="joint 2 velocity exceeds limit")
    assert command_score(faulted, T) == pytest.approx(-17.0)  # -20 + 3 for the contact
    with pytest.raises(ConfigError, match="record: needs the simulator's truth"):
        command_score(dataclasses.replace(rec, truth={}), T)


def test_search_spends_its_budget_and_keeps_the_best(shipped):
    _, knots, T = shipped
    config = CommandSearchConfig(evaluations=4, local_evaluations=3, confirm=2, check=2)
    res = search_command(knots, T, config, seed=3)
    assert res.evaluations <= 4 + 3 and res.simulated <= res.evaluations
    assert len(res.history) == res.evaluations
    assert 0 <= res.confirm_knots <= 2 and 0 <= res.check_knots <= 2
    if res.first_hit is None:  # no knot: no local phase, nothing confirmed
        assert res.evaluations == 4 and res.confirmed_candidates == 0
    assert np.all(np.diff(res.history) >= 0) and res.history[-1] >= res.score
    assert res.tied == (res.score >= 100.0)
    assert res.first_hit is None or res.first_hit <= res.evaluations


def test_cli_record_round_trip_and_errors(shipped, tmp_path, capsys):
    _, knots, T = shipped
    cmd = tmp_path / "cmd.npz"
    np.savez(cmd, knots=knots, T=T)
    out = tmp_path / "demo.npz"
    assert tools_cli.main(["demo", "record", "--command", str(cmd), "--out", str(out)]) == 0
    assert Demonstration.load(out).metadata["knot"] == "trefoil"
    capsys.readouterr()
    assert (
        tools_cli.main(["demo", "record", "--command", str(tmp_path / "no.npz"), "--out", str(out)])
        == 2
    )
    assert capsys.readouterr().err == (
        f"flyknot-tools: error: --command: no command file {str(tmp_path / 'no.npz')!r}\n"
    )
    bad = tmp_path / "bad.npz"
    np.savez(bad, q=np.zeros(3))
    assert tools_cli.main(["demo", "record", "--command", str(bad), "--out", str(out)]) == 2
    assert "needs arrays 'knots' and 'T'" in capsys.readouterr().err


def test_cli_robot_reports_a_search_without_a_knot(shipped, tmp_path, capsys):
    _, knots, T = shipped
    start = tmp_path / "start.npz"
    np.savez(start, knots=knots, T=T)
    args = ["demo", "robot", "--start", str(start), "--evaluations", "1", "--local-evaluations"]
    args += ["0", "--seed", "1", "--quiet", "--out", str(tmp_path / "d.npz")]
    assert tools_cli.main(args) == 2  # seed 1's single candidate does not tie (measured)
    assert capsys.readouterr().err == (
        "flyknot-tools: error: robot demo search failed with status 'no knot': no command tied the "
        "knot in 1 evaluations; try another --seed or more --evaluations\n"
    )
    assert not (tmp_path / "d.npz").exists()


def test_rate_search_config_messages():
    with pytest.raises(ConfigError) as e:
        RateSearchConfig(generations=2, trials=8, seed_base=40)
    assert str(e.value) == "seed_base: the search's seeds 40..55 overlap the check's 10..49"
    with pytest.raises(ConfigError) as e:
        RateSearchConfig(check_seeds=(5, 5))
    assert str(e.value) == "check_seeds: need 0 <= lo < hi, got (5, 5)"
    with pytest.raises(ConfigError, match="popsize: must be an integer >= 2, got 1"):
        RateSearchConfig(popsize=1)


def test_rate_search_simulates_no_candidate_outside_the_limits_and_keeps_the_start(shipped):
    _, knots, T = shipped
    # Steps of 50 normalised units (6 rad on a knot) put every candidate outside the limits.
    config = RateSearchConfig(generations=2, popsize=3, trials=1, sigma=50.0, check_seeds=(10, 11))
    res = rate_search(knots, T, config)
    assert res.simulated == 0 and res.history.shape == (2, 3)
    assert np.all(res.history[:, 0] <= -30.0) and np.all(res.history[:, 1:] == 0.0)
    np.testing.assert_array_equal(res.knots, knots)
    assert res.T == T and res.ties == res.start_ties and res.n_check == 1
    assert res.summary(timing=False) == {
        "T": round(T, 4),
        "start_ties": res.start_ties,
        "ties": res.start_ties,
        "n_check": 1,
        "generations": 2,
        "simulated": 0,
    }


def test_cli_robot_rate_names_a_missing_start(tmp_path, capsys):
    args = ["demo", "robot-rate", "--start", str(tmp_path / "no.npz"), "--out", "x.npz"]
    assert tools_cli.main(args) == 2
    assert capsys.readouterr().err == (
        f"flyknot-tools: error: --start: no command file {str(tmp_path / 'no.npz')!r}\n"
    )

"""The lab-study tool (``flyknot-tools lab-study``): its table, counts and errors."""

from __future__ import annotations

import pytest

from flyknot.errors import ConfigError
from flyknot_tools.lab_study import CANDIDATES, _settle_kind, _summary, run_study, table_markdown


def _trial(label: str, settle: str, sim: float = 2.0, wall: float = 1.0) -> dict:
    return {"label": label, "settle": settle, "sim_s": sim, "wall_s": wall}


def test_summary_counts_ties_failures_and_how_each_was_judged():
    trials = [
        _trial("success", "rest", 10.0, 5.0),
        _trial("shaken_loose", "cap", 15.0, 6.0),
        _trial("not_through", "contact_free", 3.0, 1.0),
        _trial("success", "knot_set", 12.0, 6.0),
    ]
    s = _summary(trials)
    assert s["n"] == 4 and s["ties"] == 2
    assert s["failures"] == {"not_through": 1, "shaken_loose": 1}
    assert s["settle"] == {"rest": 1, "contact_free": 1, "knot_set": 1, "cap": 1}
    assert s["sim_s_per_trial"] == pytest.approx(40.0 / 4)
    assert s["wall_per_sim_s"] == pytest.approx(18.0 / 40.0)


def test_settle_kind_reads_the_records_settle_metadata():
    assert _settle_kind({"settled": True, "contact_free": False}) == "rest"
    assert _settle_kind({"settled": False, "contact_free": True}) == "contact_free"
    assert _settle_kind({"settled": False, "contact_free": False}) == "cap"
    assert _settle_kind({"settled": False, "contact_free": False, "knot_set": True}) == "knot_set"
    assert _settle_kind(None) == "cap"


def test_table_has_one_line_per_row_with_the_numbers():
    a = _summary([_trial("success", "rest"), _trial("slipped_out", "cap")])
    h = _summary([_trial("success", "cap")])
    md = table_markdown([{"candidate": "condim 4", "sway_deg": 1.0, "robot": a, "hand": h}])
    lines = md.strip().splitlines()
    assert len(lines) == 3
    assert lines[2] == (
        "| condim 4 | +1 deg sway | 1/2 | 1 slipped_out | 1/1 | - | 1/0/0/1; 0/0/0/1 | 2.0; 2.0 "
        "| 0.50; 0.50 |"
    )


def test_unknown_candidate_lists_the_valid_ones():
    with pytest.raises(ConfigError) as e:
        run_study(["drag off"], [0.0], n=1)
    assert str(e.value).startswith("candidate: unknown candidate 'drag off'")
    for name in CANDIDATES:
        assert name in str(e.value)
    with pytest.raises(ConfigError, match="sway_deg"):
        run_study(["lab"], [-1.0], n=1)


def test_one_robot_trial_of_a_row_is_diagnosed_in_the_rows_lab():
    from flyknot_app.anatomy.diagnosis import LABELS
    from flyknot_tools.lab_study import _labs, _robot_trials

    arm, hand = _labs(CANDIDATES["C_D 1.2"], 1, 1.0)
    assert arm.rope_params.cd == 1.2 and hand.rope_params.cd == 1.2
    assert arm.variation.sway_deg == 1.0 and hand.variation.sway_deg == 1.0
    assert arm.settings.impratio == 10.0 and arm.rope_params.bend_hysteresis == 54.0
    lab, lab_hand = _labs(CANDIDATES["elastic table"], 1, 0)
    assert lab.rope_params.frictional_couple == 0.0 and lab.settings.impratio == 1.0
    assert lab_hand.settings.impratio == 1.0 and lab_hand.rope_params.bend_modulus == 1e6
    (row,) = _robot_trials(arm, 1)  # the shipped demonstration's command
    assert row["label"] in LABELS and row["settle"] in ("rest", "contact_free", "cap")
    assert row["sim_s"] > 1.0 and row["wall_s"] > 0


def test_variation_rows_turn_off_every_part_but_one_in_both_labs():
    from flyknot_sim.hand_params import HandVariation
    from flyknot_sim.lab import VariationParams
    from flyknot_tools.lab_study import _labs

    arm, hand = _labs(CANDIDATES["no variation"], 1, 0.0)
    assert arm.variation == VariationParams.none() and hand.variation == HandVariation.none()
    arm, hand = _labs(CANDIDATES["start delay alone"], 1, 2.0)
    assert arm.variation == VariationParams(2.0, 0.0, 0.004, False)
    assert hand.variation == HandVariation(2.0, 0.0, 0.004, False, tempo_rel=0.0)
    arm, hand = _labs(CANDIDATES["servo gains alone"], 1, 0.0)
    assert (arm.variation.servo_gain_rel, hand.variation.servo_gain_rel) == (0.03, 0.03)
    assert not arm.variation.rest_start and hand.variation.tempo_rel == 0.0
    arm, hand = _labs(CANDIDATES["rest start alone"], 1, 0.0)
    assert arm.variation == VariationParams(0.0, 0.0, 0.0, True)
    assert hand.variation == HandVariation(0.0, 0.0, 0.0, True, tempo_rel=0.0)


def test_a_missing_robot_demo_is_named(tmp_path):
    with pytest.raises(ConfigError) as e:
        run_study(["lab"], [0.0], n=1, robot_demo=tmp_path / "none.npz")
    assert str(e.value) == f"robot_demo: no file {str(tmp_path / 'none.npz')!r}"


def test_the_robot_rows_play_the_given_demonstration(tmp_path):
    from flyknot.errors import RecordError
    from flyknot_tools.lab_study import _labs, _robot_trials

    arm, _ = _labs(CANDIDATES["no variation"], 1, 0.0)
    bad = tmp_path / "robot.npz"
    bad.write_text("not a demonstration")
    with pytest.raises(RecordError, match="is not a demonstration file"):
        _robot_trials(arm, 1, bad)


def test_a_demonstration_not_played_is_a_dash_in_the_table():
    a = _summary([_trial("success", "rest")])
    md = table_markdown([{"candidate": "lab", "sway_deg": 0.0, "robot": a, "hand": None}])
    assert md.strip().splitlines()[2] == (
        "| lab | settled | 1/1 | - | - | - | 1/0/0/0; - | 2.0; - | 0.50; - |"
    )


def test_an_unknown_demonstration_kind_lists_the_valid_ones():
    with pytest.raises(ConfigError) as e:
        run_study(["lab"], [0.0], n=1, demos=("robot", "swipe"))
    assert str(e.value) == (
        "demos: unknown demonstration kind 'swipe' (valid choices: robot, hand)"
    )


def test_the_robot_alone_is_played_without_swipe(monkeypatch):
    import flyknot_tools.lab_study as ls

    played = []

    def fake_measure(job):
        played.append(job[2])
        return {"candidate": job[0], "sway_deg": job[1], "demo": job[2],
                "trials": [_trial("success", "rest")]}  # fmt: skip

    class SerialPool:
        def __init__(self, max_workers):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def map(self, fn, jobs):
            return map(fn, jobs)

    monkeypatch.setattr(ls, "_measure", fake_measure)
    monkeypatch.setattr(ls, "ProcessPoolExecutor", SerialPool)
    (row,) = run_study(["lab"], [0.0], n=1, demos=("robot",))
    assert played == ["robot"] and row["hand"] is None and row["robot"]["ties"] == 1

"""Knot judgment behind one interface: the cell's verdict, the markers, an operator."""

from __future__ import annotations

import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot.judge import (
    CellVerdict,
    KnotJudge,
    MarkerJudge,
    OperatorJudge,
    final_polyline,
    get_judge,
    judge_params_for,
)
from flyknot.record import TrialRecord
from flyknot_app.anatomy.trials import judge_params_of
from tests.knot_curves import trefoil_arc, verdict

DOWN = [0.0, 1.0, 0.0, 0.0]  # fingertip z axis (out of the tube) pointing down: x by 180 deg


def _hanging_knot() -> np.ndarray:
    """Fingertip (1.6 m above the floor) then 11 markers of a loose overhand knot 0.35 m below
    the fingertip."""
    arc = trefoil_arc(0.04, 9) + np.array([0.0, 0.0, -0.35])
    line = np.vstack([[0.0, 0.0, 0.0], [0.0, -0.12, -0.15], arc, arc[-1] + [0.0, 0.0, -0.15]])
    return line + np.array([0.0, 0.0, 1.6])


def _lowered(height: float) -> np.ndarray:
    """:func:`_hanging_knot` with its tail's last marker turned level with the one before it,
    lowered until the lowest marker is ``height`` [m] above the floor."""
    line = _hanging_knot()
    line[-1] = line[-2] + np.array([0.15, 0.0, 0.0])
    return line - np.array([0.0, 0.0, line[1:, 2].min() - height])


def _record(line: np.ndarray, m: int = 5, **kw) -> TrialRecord:
    n = 10
    markers = np.tile(line[1:][None], (m, 1, 1))
    fields = dict(
        t_joint=np.arange(n) / 250.0,
        q_cmd=np.zeros((n, 7)),
        q_meas=np.zeros((n, 7)),
        t_marker=np.arange(m) / 200.0,
        markers=markers,
        fingertip_pos=np.tile(line[0], (n, 1)),
        fingertip_quat=np.tile(DOWN, (n, 1)),
        base_pose=np.array([0, 0, 1.0, 1, 0, 0, 0]),
        knot="unknot",
    )
    fields.update(kw)
    return TrialRecord(**fields)


def test_every_judge_is_a_knot_judge():
    for j in (CellVerdict(), MarkerJudge(), OperatorJudge(lambda r, s: "knot")):
        assert isinstance(j, KnotJudge)


def test_cell_verdict_is_the_records():
    v = verdict("knot")
    assert CellVerdict()(_record(_hanging_knot(), knot="trefoil", verdict=v)) == v
    assert CellVerdict()(_record(_hanging_knot(), knot=None)) is None
    assert MarkerJudge()(_record(_hanging_knot(), fault="C31 collision")) is None


def test_marker_judge_sees_a_knot_in_the_hanging_rope_and_a_straight_rope():
    v = MarkerJudge()(_record(_hanging_knot()))
    assert v.klass == "knot" and v.success and v.source == "markers"
    assert v.votes == {"trefoil": 31} and v.core_from_held_m > 0.3
    straight = np.stack([np.zeros(12), np.zeros(12), 1.6 - 0.1 * np.arange(12)], 1)
    s = MarkerJudge()(_record(straight))
    assert s.klass == "unknot" and not s.success
    # The same knot lowered until its lowest marker is 3 mm up: its core lies on the floor.
    low = MarkerJudge()(_record(_lowered(0.003)))
    assert low.klass == "on_floor" and not low.success


def test_marker_judge_reads_the_tube_axis_from_the_fingertip():
    # The tube pointing up (into the rope) puts the rope round the tube: never a success.
    up = MarkerJudge()(_record(_hanging_knot(), fingertip_quat=np.tile([1.0, 0, 0, 0], (10, 1))))
    assert not up.success


def test_marker_judge_uses_the_last_fully_tracked_frame():
    rec_line = _hanging_knot()
    rec = _record(rec_line)
    markers = np.array(rec.markers)
    markers[-2:, 4] = np.nan  # the last two frames lost marker 4
    markers[:2] = 0.0  # early frames: a degenerate rope
    rec = _record(rec_line, markers=markers)
    line, axis = final_polyline(rec)
    np.testing.assert_allclose(line, rec_line)
    np.testing.assert_allclose(axis, [0.0, 0.0, -1.0], atol=1e-12)
    gone = _record(rec_line, markers=np.full_like(markers, np.nan))
    assert final_polyline(gone) is None
    assert MarkerJudge()(gone) is None


def test_operator_is_shown_the_suggestion_and_answers():
    seen = []
    answers = iter(["knot", "wrapped", "floor", "none", None])

    def ask(record, suggestion):
        seen.append(suggestion.klass)
        return next(answers)

    judge = OperatorJudge(ask)
    got = [judge(_record(_hanging_knot())) for _ in range(5)]
    assert [None if v is None else v.klass for v in got] == [
        "knot",
        "wrapped_at_grip",
        "on_floor",
        "unknot",
        None,
    ]
    assert got[0].success and not got[1].success and got[0].source == "operator"
    assert not got[2].success
    assert seen == ["knot"] * 5
    assert OperatorJudge(lambda r, s: None, suggest=None)(_record(_hanging_knot())) is None


def test_an_operator_answer_outside_the_choices_names_them():
    with pytest.raises(
        ConfigError,
        match=r"^answer: unknown value 'yes' \(valid choices: knot, wrapped, floor, none\)$",
    ):
        OperatorJudge(lambda r, s: "yes", suggest=None)(_record(_hanging_knot()))


def test_unknown_judge_lists_the_valid_names():
    assert isinstance(get_judge("markers"), MarkerJudge)
    with pytest.raises(
        ConfigError, match=r"^judge: unknown knot judge 'eyes' \(valid choices: cell, markers\)$"
    ):
        get_judge("eyes")


def test_the_floor_is_measured_by_the_records_rope():
    assert judge_params_for({"rope_diameter_m": 0.012}).rope_radius_m == 0.006
    assert judge_params_for({"rope": 2}).rope_radius_m == 0.0
    # A knot whose core's lowest marker is 1.5 cm up: clear of the floor for a 9 mm rope,
    # touching it for the 25 mm rope 5.
    low = _lowered(0.015)
    thin = MarkerJudge()(_record(low, metadata={"rope_diameter_m": 0.009}))
    thick = MarkerJudge()(_record(low, metadata={"rope_diameter_m": 0.025}))
    assert (thin.klass, thick.klass) == ("knot", "on_floor")


def test_an_old_record_finds_its_ropes_diameter():
    assert judge_params_of({"rope": 2}).rope_radius_m == pytest.approx(0.006)
    assert judge_params_of({"rope": "shoe lace"}).rope_radius_m == pytest.approx(0.0035)
    assert judge_params_of({"rope_params": {"diameter": 0.02}}).rope_radius_m == 0.01
    assert judge_params_of({"rope": "my cord"}).rope_radius_m == 0.0  # its file unknown
    assert judge_params_of({}).rope_radius_m == 0.0

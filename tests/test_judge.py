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
)
from flyknot.record import TrialRecord


def _trefoil(n: int = 12) -> np.ndarray:
    """An open trefoil (a torus knot of type (2, 3), cut open), (n, 3) [m]."""
    t = np.linspace(0.15, 2 * np.pi - 0.15, n)
    return 0.1 * np.stack(
        [np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)], 1
    )


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
        fingertip_quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        base_pose=np.array([0, 0, 1.0, 1, 0, 0, 0]),
        knot="unknot",
    )
    fields.update(kw)
    return TrialRecord(**fields)


def test_every_judge_is_a_knot_judge():
    for j in (CellVerdict(), MarkerJudge(), OperatorJudge(lambda r, s: True)):
        assert isinstance(j, KnotJudge)


def test_cell_verdict_is_the_records():
    assert CellVerdict()(_record(_trefoil(), knot="trefoil")) == "trefoil"
    assert CellVerdict()(_record(_trefoil(), knot=None)) is None
    assert MarkerJudge()(_record(_trefoil(), fault="C31 collision")) is None


def test_marker_judge_sees_a_trefoil_and_a_straight_rope():
    assert MarkerJudge()(_record(_trefoil())) == "trefoil"
    straight = np.stack([np.zeros(12), np.zeros(12), -0.1 * np.arange(12)], 1)
    assert MarkerJudge()(_record(straight)) == "unknot"


def test_marker_judge_uses_the_last_fully_tracked_frame():
    rec_line = _trefoil()
    rec = _record(rec_line)
    markers = np.array(rec.markers)
    markers[-2:, 4] = np.nan  # the last two frames lost marker 4
    markers[:2] = 0.0  # early frames: a degenerate rope
    rec = _record(rec_line, markers=markers)
    line = final_polyline(rec)
    np.testing.assert_allclose(line, rec_line)
    gone = _record(rec_line, markers=np.full_like(markers, np.nan))
    assert final_polyline(gone) is None
    assert MarkerJudge()(gone) is None


def test_operator_is_shown_the_suggestion_and_answers():
    seen = []

    def ask(record, suggestion):
        seen.append(suggestion)
        return len(seen) == 1

    judge = OperatorJudge(ask)
    assert judge(_record(_trefoil())) == "trefoil"
    assert judge(_record(_trefoil())) == "unknot"
    assert seen == ["trefoil", "trefoil"]
    assert OperatorJudge(lambda r, s: None, suggest=None)(_record(_trefoil())) is None


def test_unknown_judge_lists_the_valid_names():
    assert isinstance(get_judge("markers"), MarkerJudge)
    with pytest.raises(
        ConfigError, match=r"^judge: unknown knot judge 'eyes' \(valid choices: cell, markers\)$"
    ):
        get_judge("eyes")

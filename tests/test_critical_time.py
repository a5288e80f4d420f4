"""Critical time from markers alone (learner.critical_time)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import RecordError
from learner.critical_time import (
    detect_critical_time,
    first_self_approach,
    first_tracking_loss,
    polyline_self_distance,
)


def test_distance_of_parallel_and_crossing_segments():
    # Segment 0 and segment 2 of a U: parallel at 0.05 m.
    u = np.array([[0, 0, 0], [1, 0, 0], [1, 0.05, 0], [0, 0.05, 0]], dtype=float)
    assert polyline_self_distance(u) == pytest.approx(0.05)
    # A Z folded over itself: segment 2 crosses segment 0.
    z = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]], dtype=float)
    assert polyline_self_distance(z) == pytest.approx(0.0, abs=1e-12)


@given(st.lists(st.floats(-1, 1), min_size=15, max_size=15))
@settings(max_examples=80, deadline=None)
def test_distance_matches_dense_sampling(coords):
    p = np.asarray(coords).reshape(5, 3)
    d = polyline_self_distance(p)
    s = np.linspace(0, 1, 201)[:, None]
    best = np.inf
    for i in range(4):
        a = p[i] + s * (p[i + 1] - p[i])
        for j in range(i + 2, 4):
            b = p[j] + s * (p[j + 1] - p[j])
            best = min(best, np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))
    assert d <= best + 1e-9
    assert d >= best - 0.02  # the grid's resolution on segments up to 3.5 m long


def test_cues_on_constructed_tracks():
    t = np.arange(5) * 0.1
    hand = np.zeros((5, 3))
    markers = np.zeros((5, 11, 3))
    markers[:, :, 2] = -0.1 * np.arange(1, 12)  # hanging straight
    assert first_self_approach(t, hand, markers, 0.009) is None
    assert first_tracking_loss(t, markers) is None
    markers[3, 10] = markers[3, 2] + [0.005, 0, 0]  # the end touches the rope at t = 0.3
    assert first_self_approach(t, hand, markers, 0.009) == pytest.approx(0.3)
    markers[4, 5] = np.nan
    assert first_tracking_loss(t, markers) == pytest.approx(0.4)


@pytest.mark.parametrize("name", ["fast", "slow", "swipe", "inverse", "robot"])
def test_shipped_demonstrations_within_25_ms(name):
    demo = Demonstration.load(DEMOS_DIR / f"{name}.npz")
    found = detect_critical_time(demo, 0.009)
    assert found.t_c == pytest.approx(demo.t_c, abs=0.025)


def test_bad_points_name_the_problem():
    with pytest.raises(RecordError) as e:
        polyline_self_distance(np.zeros((3, 3)))
    assert str(e.value) == "points must have shape (..., k, 3) with k >= 4, got (3, 3)"

"""Where the knot is decided: the separation of tying and untying trials over time."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot_app.diagnose.decided import (
    class_separation,
    decided_time,
    separation,
    velocity_weight,
)


def test_class_separation_by_hand():
    knot = np.array([[0.0, 0.0], [2.0, 0.0]])  # mean (1, 0), squared deviations 1 + 1
    other = np.array([[1.0, 3.0], [1.0, 5.0]])  # mean (1, 4), squared deviations 1 + 1
    d, s = class_separation(knot, other)
    assert d == pytest.approx(4.0)
    assert s == pytest.approx(np.sqrt(4.0 / 2.0))
    with pytest.raises(ConfigError) as e:
        class_separation(knot[:1], other)
    assert str(e.value) == "trials: each class needs at least two trials"


@settings(max_examples=30, deadline=None)
@given(st.floats(0.2, 0.8), st.integers(0, 2**31 - 1))
def test_classes_parting_at_a_known_time_are_decided_there(t_part, seed):
    """Trials scattered by 1 mm; from t_part the tying ones move 5 cm away: decided at the
    first sample at or after t_part."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, 101)
    tied = np.array([True] * 6 + [False] * 5)
    states = 0.001 * rng.standard_normal((tied.size, t.size, 33))
    states[tied] += 0.05 * (t >= t_part)[None, :, None]
    sep = separation(t, states, tied)
    assert sep.t_decided == pytest.approx(t[np.argmax(t >= t_part)])
    assert sep.n_knot == 6 and sep.n_other == 5


def test_lost_samples_and_undecided():
    t = np.array([0.0, 0.1, 0.2])
    tied = np.array([True, True, False, False])
    states = np.zeros((4, 3, 3))
    states[:, :, 0] = [[0, 0, 0], [0.01, 0.01, 0.01], [0.0, 0.0, 0.0], [0.01, 0.01, 0.01]]
    states[2, 2] = np.nan  # one untying trial lost at 0.2 s: that class has one trial left
    sep = separation(t, states, tied)
    assert np.isnan(sep.ratio[2]) and sep.ratio[0] == 0.0
    assert sep.t_decided is None
    assert decided_time(t, np.array([0.5, 2.0, 0.5]), 1.0) is None  # falls back below
    assert decided_time(t, np.array([2.0, 0.5, 3.0]), 1.0) == 0.2
    assert decided_time(t, np.array([1.5, np.nan, 2.0]), 1.0) == 0.0
    with pytest.raises(ConfigError, match="need shape"):
        separation(t, states[:, :2], tied)


def _synthetic(tied: bool, offset: float, rng: np.random.Generator, contact: float | None = None):
    """A record whose markers move 5 cm apart from 0.5 s on when it tied (first self-contact
    at ``contact`` [s], or unknown)."""
    from flyknot.record import TrialRecord
    from flyknot.verdict import Verdict

    n, m = 5, 201
    t_marker = np.arange(m) / 200.0
    markers = offset + 0.001 * rng.standard_normal((m, 11, 3))
    if tied:
        markers[t_marker >= 0.5] += 0.05
    klass, knot = ("knot", "trefoil") if tied else ("unknot", "unknot")
    return TrialRecord(
        t_joint=np.arange(n) / 250.0,
        q_cmd=np.zeros((n, 7)),
        q_meas=np.zeros((n, 7)),
        t_marker=t_marker,
        markers=markers,
        fingertip_pos=np.zeros((n, 3)),
        fingertip_quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        base_pose=np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]),
        knot=knot,
        verdict=Verdict(klass=klass, knot=knot),
        metadata={"cell": "sim", "rope": 1},
        first_contact_time=contact,
    )


def test_cli_decided(tmp_path, capsys):
    from flyknot_app.cli import main

    rng = np.random.default_rng(0)
    for i in range(8):
        _synthetic(i % 2 == 0, 0.0, rng).save(tmp_path / "trials" / f"trial_{i:03d}")
    assert main(["diagnose", "decided", str(tmp_path / "trials"), "--end", "1.0"]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[0] == "4 trials tied, 4 did not (markers)"
    assert text.splitlines()[1] == "decided at 0.500 s (separation >= 1 from then on)"
    for i in (3, 5, 7):  # one untying trial left
        for p in (tmp_path / "trials").glob(f"trial_{i:03d}*"):
            p.unlink()
    assert main(["diagnose", "decided", str(tmp_path / "trials")]) == 2
    assert capsys.readouterr().err.strip() == (
        "flyknot: error: DIR: needs at least two trials that tied and two that did not, got 4 and 1"
    )


def test_velocity_weight_is_position_weight_times_lead_squared():
    assert velocity_weight(0.063, 25.0) == pytest.approx(0.099225)
    assert velocity_weight(np.sqrt(0.00375 / 25.0), 25.0) == pytest.approx(0.00375)  # the paper's
    with pytest.raises(ConfigError, match=r"^lead_s: "):
        velocity_weight(0.0, 25.0)


def test_cli_decided_names_the_lead_after_the_first_contact(tmp_path, capsys):
    """Trials that touch themselves at 0.44-0.46 s (median 0.45) and part at 0.5 s: decided 50
    ms after the first contact, the velocity weight 25 x 0.05^2; without contacts no such line."""
    from flyknot_app.cli import main

    rng = np.random.default_rng(0)
    for i in range(8):
        rec = _synthetic(i % 2 == 0, 0.0, rng, contact=0.44 + 0.01 * (i % 3))
        rec.save(tmp_path / "trials" / f"trial_{i:03d}")
    assert main(["diagnose", "decided", str(tmp_path / "trials"), "--end", "1.0"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        "50 ms after the median first self-contact (0.450 s): velocities weighed as that much "
        "position, --set weights.w_crit_vel=0.0625 (the paper's 0.00375 is 12 ms)"
    )
    assert main(["diagnose", "decided", str(tmp_path / "trials"), "--end", "1.0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["t_contact"], out["lead_s"], out["w_crit_vel"]) == (0.45, 0.05, 0.0625)

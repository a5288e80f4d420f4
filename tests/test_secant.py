"""The secant Jacobian: the model's M(t_c) corrected by Broyden updates from measured trials."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from learner.ilc import ILCParams, learn
from learner.jacobians import SecantCorrection
from learner.kinematics import RobotModel
from learner.update import UpdateSettings
from tests.test_confirm import DisturbedCell, _spy
from tests.test_ilc import ROPE, model_problem


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_secant_condition_holds_after_each_update(seed):
    """After learning from trial k+1, (M_model + C) maps the last step onto the measured
    change of the error, and leaves directions orthogonal to the step as they were."""
    rng = np.random.default_rng(seed)
    sec = SecantCorrection()
    M_model = rng.normal(size=(66, 80))
    k0, e0 = rng.normal(size=(10, 8)), rng.normal(size=66)
    M0 = sec.corrected(k0, M_model, e0)
    np.testing.assert_array_equal(M0, M_model)  # nothing learned from one trial
    k1, e1 = k0 + 0.01 * rng.normal(size=(10, 8)), rng.normal(size=66)
    M1 = sec.corrected(k1, M_model, e1)
    dk = (k1 - k0).ravel()
    np.testing.assert_allclose(M1 @ dk, e1 - e0, atol=1e-9)
    ortho = rng.normal(size=80)
    ortho -= (ortho @ dk) / (dk @ dk) * dk
    np.testing.assert_allclose(M1 @ ortho, M_model @ ortho, atol=1e-9)
    # without learning, the same trial again changes nothing
    np.testing.assert_array_equal(sec.corrected(k1, M_model, e1 + 1.0, learn=False), M1)


def test_secant_options_are_checked():
    with pytest.raises(ConfigError) as e:
        ILCParams(average=2, update=UpdateSettings(jacobian="secant"))
    assert str(e.value) == "jacobian: 'secant' learns from every play: it takes no average > 1"
    with pytest.raises(ConfigError) as e:
        UpdateSettings(jacobian="secant", objective="equal")
    assert str(e.value) == "jacobian: 'secant' is for the critical objective only"


@pytest.fixture(scope="module")
def arm():
    return RobotModel.from_mjcf()


@pytest.fixture(scope="module")
def setup(arm):
    return model_problem(arm)


def _secant_run(arm, target, start, monkeypatch, run_dir, trials, resume=False, cell=None):
    cell = cell or DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    params = ILCParams(
        max_trials=trials, rope_model=ROPE, step="damped", update=UpdateSettings(jacobian="secant")
    )
    return cell, learn(cell, target, start, arm, params, run_dir=run_dir, resume=resume)


def test_secant_run_resumed_is_the_uninterrupted_run(arm, setup, monkeypatch, tmp_path):
    target, start = setup
    whole, res = _secant_run(arm, target, start, monkeypatch, tmp_path / "whole", 5)
    part, _ = _secant_run(arm, target, start, monkeypatch, tmp_path / "part", 3)
    part, again = _secant_run(
        arm, target, start, monkeypatch, tmp_path / "part", 5, resume=True, cell=part
    )
    assert [s.action for s in again.trials] == [s.action for s in res.trials]
    for a, b in zip(part.played, whole.played, strict=True):
        np.testing.assert_array_equal(a, b)
    # and the correction mattered: the model alone plays another fourth command
    plain, _ = _damped_plain(arm, target, start, monkeypatch, tmp_path / "plain")
    assert not np.array_equal(plain.played[3], whole.played[3])


def _damped_plain(arm, target, start, monkeypatch, run_dir):
    cell = DisturbedCell(arm, target, bad=2)
    _spy(cell, monkeypatch)
    params = ILCParams(max_trials=5, rope_model=ROPE, step="damped")
    return cell, learn(cell, target, start, arm, params, run_dir=run_dir)

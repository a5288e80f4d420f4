"""Robot base pose in the mocap frame from fingertip positions (flyknot_hw.mocap.calibration)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from flyknot.errors import ConfigError
from flyknot.geometry import quat_to_matrix
from flyknot_hw.mocap.calibration import apply_pose, calibrate_base, rigid_fit

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


def _pose(quat, t) -> np.ndarray:
    q = np.asarray(quat, dtype=float)
    return np.concatenate([np.asarray(t, dtype=float), q / np.linalg.norm(q)])


def _same_pose(a: np.ndarray, b: np.ndarray, tol: float) -> None:
    np.testing.assert_allclose(a[:3], b[:3], atol=tol)
    np.testing.assert_allclose(quat_to_matrix(a[3:]), quat_to_matrix(b[3:]), atol=tol)


def _workspace_points(rng: np.random.Generator, k: int) -> np.ndarray:
    """Fingertip positions an xArm 7 reaches: a box in front of the base [m]."""
    return rng.uniform([0.2, -0.4, 0.1], [0.7, 0.4, 0.8], size=(k, 3))


def test_recovers_a_known_pose_exactly():
    rng = np.random.default_rng(0)
    truth = _pose([0.9, 0.1, -0.2, 0.3], [1.5, -0.4, 0.9])
    a = _workspace_points(rng, 8)
    pose, res = calibrate_base(a, apply_pose(truth, a))
    _same_pose(pose, truth, 1e-10)
    assert pose[3] >= 0 and abs(np.linalg.norm(pose[3:]) - 1) < 1e-12
    assert res.rms_m < 1e-10 and res.max_m < 1e-10 and res.n_poses == 8
    assert res.per_pose.shape == (8,)


@settings(max_examples=60)
@given(
    quat=arrays(float, 4, elements=finite),
    t=arrays(float, 3, elements=st.floats(-3, 3)),
    pts=arrays(float, st.tuples(st.integers(3, 12), st.just(3)), elements=finite),
)
def test_random_rigid_transforms_are_recovered(quat, t, pts):
    assume(np.linalg.norm(quat) > 0.1)
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    assume(sv[1] / np.sqrt(len(pts)) > 0.05)  # well away from collinear
    truth = _pose(quat, t)
    pose, res = calibrate_base(pts, apply_pose(truth, pts))
    _same_pose(pose, truth, 1e-8)
    assert res.rms_m < 1e-9


@settings(max_examples=30)
@given(seed=st.integers(0, 10_000))
def test_noise_gives_a_residual_of_the_noise_level(seed):
    rng = np.random.default_rng(seed)
    truth = _pose(rng.normal(size=4), rng.uniform(-2, 2, 3))
    a = _workspace_points(rng, 20)
    noise = 0.001
    b = apply_pose(truth, a) + rng.normal(0, noise, a.shape)
    pose, res = calibrate_base(a, b)
    # Residual of a 6-parameter fit to 60 coordinates: sqrt(3 (1 - 6/60)) sigma ~ 1.6 mm.
    assert 0.5 * noise < res.rms_m < 2.5 * noise
    assert np.linalg.norm(pose[:3] - truth[:3]) < 3 * noise


def test_robust_refinement_discounts_a_misread_pose():
    rng = np.random.default_rng(3)
    truth = _pose([1.0, 0.0, 0.0, 0.4], [0.3, 0.2, 1.0])
    a = _workspace_points(rng, 10)
    b = apply_pose(truth, a) + rng.normal(0, 0.0005, a.shape)
    b[4] += [0.05, 0.0, 0.0]  # the marker of pose 4 was misread by 5 cm
    plain, _ = calibrate_base(a, b)
    robust, res_robust = calibrate_base(a, b, robust_m=0.002)
    err_plain = np.linalg.norm(plain[:3] - truth[:3])
    err_robust = np.linalg.norm(robust[:3] - truth[:3])
    assert err_robust < 0.002 < err_plain
    assert int(np.argmax(res_robust.per_pose)) == 4 and res_robust.max_m > 0.045


def test_rigid_fit_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 3))
    b = a * np.array([1.0, 1.0, -1.0])  # a mirror image: no rotation maps a onto it
    R, _ = rigid_fit(a, b)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize(
    ("a", "b", "field", "text"),
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "fk_points", "at least 3"),
        (
            np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0.0]]),
            np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0.0]]),
            "fk_points",
            "collinear",
        ),
        (np.zeros((4, 3)), np.zeros((5, 3)), "mocap_points", "shape"),
        (np.zeros((4, 2)), np.zeros((4, 2)), "fk_points", "(k, 3)"),
        (np.full((4, 3), np.nan), np.zeros((4, 3)), "fk_points", "finite"),
    ],
)
def test_bad_inputs_name_the_field(a, b, field, text):
    with pytest.raises(ConfigError) as e:
        calibrate_base(a, b)
    assert e.value.field == field and text in str(e.value)


def test_collinear_mocap_points_are_refused_too():
    a = _workspace_points(np.random.default_rng(2), 5)
    b = np.outer(np.arange(5.0), [0.1, 0.0, 0.0])
    with pytest.raises(ConfigError, match="collinear") as e:
        calibrate_base(a, b)
    assert e.value.field == "mocap_points"


def test_bad_robust_scale_and_pose_are_refused():
    a = _workspace_points(np.random.default_rng(4), 5)
    with pytest.raises(ConfigError, match="robust_m"):
        calibrate_base(a, a, robust_m=0.0)
    with pytest.raises(ConfigError, match="base_pose"):
        apply_pose(np.zeros(6), a)

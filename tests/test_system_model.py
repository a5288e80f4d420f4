"""System model: grid, critical step, hanging-state sensitivity, rollouts and M = dx/dkappa."""

from __future__ import annotations

import numpy as np
import pytest

from flyknot.constants import XARM7_XML
from flyknot.errors import ConfigError
from learner.bezier import BezierCommand, bernstein_basis
from learner.critical_state import critical_state_from_record
from learner.kinematics import RobotModel
from learner.rope_model import RopeModelParams
from learner.rope_sensitivity import hanging_sensitivity
from learner.system_model import (
    critical_step,
    initial_state,
    input_jacobian,
    linearise,
    model_record,
    model_times,
    resample_joints,
    rollout_from_joints,
    simulate_command,
    tip_inputs,
)

HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
TILTED = HOME + np.array([0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0])  # tube ~30 deg off vertical
PAPER = RopeModelParams()
SOFT = RopeModelParams(stiffness=10.0, damping=0.5)
FD_EPS = 1e-6  # [rad, m]
FD_TOL = 1e-12  # [m] Newton tolerance of the finite-difference rollouts


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_mjcf(XARM7_XML)


def _knots(q0: np.ndarray, amplitude: float, seed: int, base=(0.1, 0.0, 1.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, 8)
    k = np.zeros((10, 8))
    k[:7] = q0[:, None] + amplitude * np.sin(np.pi * s)[None] * rng.uniform(-1, 1, (7, 1))
    k[7:] = np.asarray(base)[:, None]
    return k


# ------------------------------------------------------------------------ grid, critical step


def test_model_times():
    t = model_times(0.8, 0.005)
    assert t.shape == (161,)
    assert t[-1] == pytest.approx(0.8, abs=1e-15)
    np.testing.assert_allclose(np.diff(t), 0.005, atol=1e-15)
    t = model_times(0.8012, 0.005)  # not a multiple: stop at the last step before T
    assert t.shape == (161,) and t[-1] == pytest.approx(0.8)
    with pytest.raises(ConfigError, match=r"^T: must be a finite number > 0, got 0.0$"):
        model_times(0.0)
    with pytest.raises(ConfigError, match=r"^dt: must be a finite number > 0, got -1.0$"):
        model_times(1.0, -1.0)


def test_critical_step_rounds_half_up_and_checks_range():
    assert critical_step(0.625, 0.25, 1.0) == 3  # 2.5 -> 3
    assert critical_step(0.6, 0.25, 1.0) == 2  # 2.4 -> 2
    assert critical_step(0.0, 0.25, 1.0) == 0
    assert critical_step(1.15, 0.25, 1.2) == 4  # 4.6 -> 5, capped at the last step K = 4
    assert critical_step(0.45, 0.005, 0.8) == 90
    with pytest.raises(ConfigError, match=r"^t_c: must lie in \[0, T\) = \[0, 1\) s, got 1.0$"):
        critical_step(1.0, 0.25, 1.0)
    with pytest.raises(ConfigError, match=r"^t_c: must lie in \[0, T\) = \[0, 1\) s, got -0.1$"):
        critical_step(-0.1, 0.25, 1.0)


# ------------------------------------------------------------------- hanging-state sensitivity


@pytest.mark.parametrize("params", [PAPER, SOFT], ids=["paper", "soft"])
def test_hanging_sensitivity_matches_finite_differences(params):
    rng = np.random.default_rng(4)
    tip = np.array([0.3, 0.1, 1.3])
    d = rng.normal(size=3)
    d[2] = -abs(d[2]) - 0.5
    d /= np.linalg.norm(d)
    p, v = initial_state(tip, d, params)
    assert np.all(v == 0.0)
    S = hanging_sensitivity(p, tip, d, params)
    assert S.shape == (33, 6)
    # Translation invariance: every point moves with the tip.
    np.testing.assert_allclose(S[:, :3], np.tile(np.eye(3), (11, 1)), atol=1e-9)
    # Tilting the tube (tangent directions; hanging_state normalises d_tip).
    t1 = np.cross(d, [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    for tv in (t1, np.cross(d, t1)):
        plus, _ = initial_state(tip, (d + 1e-5 * tv) / np.linalg.norm(d + 1e-5 * tv), params)
        minus, _ = initial_state(tip, (d - 1e-5 * tv) / np.linalg.norm(d - 1e-5 * tv), params)
        fd = (plus - minus).ravel() / 2e-5
        assert np.linalg.norm(fd) > 0.1  # the rope really responds
        # The soft rope's hanging state converges only to ~1e-6 relative (slow pseudo-time).
        assert np.linalg.norm(S[:, 3:] @ tv - fd) <= 1e-5 * np.linalg.norm(fd)


def test_straight_hanging_rope_shifts_with_the_tip():
    """For d_tip = -z the rope hangs straight; a tip shift moves every point by the same."""
    tip, d = np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.0, -1.0])
    p, _ = initial_state(tip, d, PAPER)
    np.testing.assert_allclose(p[:, 2], 1.5 - 0.1 * np.arange(1, 12), atol=1e-12)
    S = hanging_sensitivity(p, tip, d, PAPER)
    np.testing.assert_allclose(S[:, :3], np.tile(np.eye(3), (11, 1)), atol=1e-9)


# ---------------------------------------------------------------------------- rollouts


def test_tip_inputs_are_fk_plus_base(robot):
    q = np.stack([HOME, TILTED])
    base = np.array([0.1, -0.2, 1.0])
    p, d, R = tip_inputs(robot, q, base)
    for i in range(2):
        p_fk, R_fk = robot.fk(q[i])
        np.testing.assert_allclose(p[i], np.asarray(p_fk).ravel() + base, atol=1e-14)
        np.testing.assert_allclose(d[i], np.asarray(R_fk)[:, 2], atol=1e-14)
        np.testing.assert_allclose(R[i], np.asarray(R_fk), atol=1e-14)


def test_rollout_from_measured_joints_equals_the_command_rollout(robot):
    """Joints measured at 250 Hz, resampled to the 200 Hz grid, give the same rope motion."""
    cmd = BezierCommand(_knots(HOME, 0.3, 2), 0.4)
    ref = simulate_command(cmd.knots, cmd.T, robot, PAPER)
    jc = cmd.joint_command()
    t_meas = cmd.sample_times()
    rollouts = {}
    for method, q_tol, x_tol in (("cubic", 1e-6, 1e-5), ("linear", 2e-4, 2e-3)):
        ro = rollout_from_joints(
            t_meas, jc.q, cmd.base_offset, robot, PAPER, cmd.T, interpolation=method
        )
        assert ro.t.shape == (81,) and ro.q.shape == (81, 7) and ro.x.shape == (81, 66)
        np.testing.assert_allclose(ro.q, ref.q, atol=q_tol)
        np.testing.assert_allclose(ro.base, np.tile(cmd.base_offset, (81, 1)))
        np.testing.assert_allclose(ro.x[:, :33], ref.x[:, :33], atol=x_tol)
        rollouts[method] = ro
    short = rollout_from_joints(t_meas, jc.q, cmd.base_offset, robot, PAPER, cmd.T, n_steps=10)
    assert short.n_steps == 10
    np.testing.assert_allclose(short.x, rollouts["cubic"].x[:11], atol=1e-12)


def test_resample_linear_bound():
    """Piecewise-linear resampling error <= h^2 max|q''| / 8."""
    t_src = np.arange(0, 1.0 + 1e-9, 0.004)
    q = np.sin(7.0 * t_src)[:, None] * np.ones(7)
    t = np.arange(0, 1.0 + 1e-9, 0.005)
    lin = resample_joints(t_src, q, t, "linear")
    assert np.max(np.abs(lin[:, 0] - np.sin(7.0 * t))) <= 0.004**2 * 49.0 / 8.0 + 1e-15
    cub = resample_joints(t_src, q, t, "cubic")
    assert np.max(np.abs(cub[:, 0] - np.sin(7.0 * t))) < 1e-7


def test_rollout_input_errors(robot):
    t = np.arange(0, 0.3, 0.004)
    q = np.tile(HOME, (t.size, 1))
    with pytest.raises(
        ConfigError, match=r"^q_meas_t: must cover the model grid \[0.0000, 0.4000\] s, got"
    ):
        rollout_from_joints(t, q, np.zeros(3), robot, PAPER, 0.4)
    with pytest.raises(
        ConfigError, match=r"^interpolation: unknown value 'spline' \(valid choices: cubic, linear"
    ):
        rollout_from_joints(t, q, np.zeros(3), robot, PAPER, 0.2, interpolation="spline")
    with pytest.raises(ConfigError, match=r"^base_offset: must be finite with shape \(3,\)"):
        rollout_from_joints(t, q, np.zeros(2), robot, PAPER, 0.2)
    with pytest.raises(ConfigError, match=r"^n_steps: must be an integer in \[1, 40\], got 41$"):
        rollout_from_joints(t, q, np.zeros(3), robot, PAPER, 0.2, n_steps=41)
    with pytest.raises(ConfigError, match=r"^q_meas: must have shape \(75, 7\), got \(75, 6\)$"):
        rollout_from_joints(t, q[:, :6], np.zeros(3), robot, PAPER, 0.2)
    with pytest.raises(ConfigError, match=r"^rope_params: must be a RopeModelParams, got dict$"):
        rollout_from_joints(t, q, np.zeros(3), robot, {}, 0.2)


# ---------------------------------------------------------------------------- linearisation


def _fd_columns(knots, T, robot, params, steps, columns):
    """Central differences of the whole chain: knots -> Bezier -> FK -> hanging -> rollout."""
    out = np.empty((len(steps), 66, len(columns)))
    for a, c in enumerate(columns):
        e = np.zeros(80)
        e[c] = FD_EPS
        e = e.reshape(10, 8)
        xp = simulate_command(knots + e, T, robot, params, newton_tol=FD_TOL).x[steps]
        xm = simulate_command(knots - e, T, robot, params, newton_tol=FD_TOL).x[steps]
        out[:, :, a] = (xp - xm) / (2.0 * FD_EPS)
    return out


def test_linearise_matches_finite_differences_of_the_whole_chain(robot):
    """M = dx/dkappa (all 80 columns) against central differences, paper rope, tilted tube."""
    T = 0.2
    knots = _knots(TILTED, 0.3, 1)
    ro = simulate_command(knots, T, robot, PAPER, newton_tol=FD_TOL)
    steps = [0, 10, 25, ro.n_steps]
    M = linearise(ro, T, steps)
    fd = _fd_columns(knots, T, robot, PAPER, steps, range(80))
    assert M.shape == fd.shape == (4, 66, 80)
    assert np.linalg.norm(fd) > 10.0
    assert np.linalg.norm(M - fd) <= 1e-4 * np.linalg.norm(fd)
    for block in (slice(0, 33), slice(33, 66)):  # positions, velocities
        assert np.linalg.norm(M[:, block] - fd[:, block]) <= 1e-4 * np.linalg.norm(fd[:, block])
    # Step 0 (the hanging state moves with the start pose) and the base columns on their own.
    assert np.linalg.norm(M[0] - fd[0]) <= 1e-4 * np.linalg.norm(fd[0])
    assert np.linalg.norm(M[..., 56:] - fd[..., 56:]) <= 1e-4 * np.linalg.norm(fd[..., 56:])


def test_linearise_soft_rope_selected_columns(robot):
    T = 0.15
    knots = _knots(TILTED, 0.4, 3, base=(0.0, 0.2, 0.9))
    ro = simulate_command(knots, T, robot, SOFT, newton_tol=FD_TOL)
    cols = [3, 17, 30, 44, 55, 57, 66, 79]
    M = linearise(ro, T, [ro.n_steps])
    fd = _fd_columns(knots, T, robot, SOFT, [ro.n_steps], cols)
    assert np.linalg.norm(M[..., cols] - fd) <= 1e-4 * np.linalg.norm(fd)


def test_input_jacobian_structure(robot):
    knots = _knots(HOME, 0.3, 5)
    ro = simulate_command(knots, 0.2, robot, PAPER, n_steps=8)
    dU = input_jacobian(ro, 0.2)
    basis = bernstein_basis(ro.t, 0.2)
    jac = robot.tip_jacobians(ro.q, np.zeros_like(ro.q))
    np.testing.assert_allclose(dU[:, 0:3, 3 * 8 + 2], jac.dp_dq[:, :, 3] * basis[:, 2:3])
    np.testing.assert_allclose(dU[:, 3:6, 5 * 8 + 4], jac.dd_dq[:, :, 5] * basis[:, 4:5])
    for c in range(3):  # base rows: identity on p_tip, nothing on d_tip
        np.testing.assert_allclose(dU[:, c, 56 + 8 * c : 64 + 8 * c], basis)
        assert np.all(dU[:, 3:, 56 + 8 * c : 64 + 8 * c] == 0.0)


def test_linearise_steps_and_errors(robot):
    ro = simulate_command(_knots(HOME, 0.3, 6), 0.2, robot, PAPER, n_steps=12)
    full = linearise(ro, 0.2, range(13))
    np.testing.assert_allclose(linearise(ro, 0.2, [12, 4]), full[[12, 4]], atol=1e-12)
    with pytest.raises(ConfigError, match=r"^steps: must be integers in \[0, 12\], got 13$"):
        linearise(ro, 0.2, [13])
    with pytest.raises(ConfigError, match=r"^rollout: must be a ModelRollout, got list$"):
        linearise([], 0.2, [1])


# ------------------------------------------------------------------ the model as the real system


def test_model_record_markers_are_the_model_state(robot):
    cmd = BezierCommand(_knots(HOME, 0.3, 7, base=(0.1, -0.1, 1.0)), 0.4)
    rec = model_record(cmd, robot, PAPER)
    ro = simulate_command(cmd.knots, cmd.T, robot, PAPER)
    assert rec.t_marker.shape == (81,) and rec.t_joint.shape == (101,)
    np.testing.assert_allclose(rec.markers + cmd.base_offset, ro.traj.p, atol=1e-12)
    x = critical_state_from_record(rec, 0.2, cmd.base_offset)
    # The local quadratic fit over +-25 ms smooths this fast motion by up to ~0.3 mm.
    np.testing.assert_allclose(x[:33], ro.x[40, :33], atol=1e-3)
    np.testing.assert_allclose(rec.q_meas, cmd.joint_command().q)

"""Tests of the initial guess (learner/initial_guess*.py): kernels, the NLP's assembly and
derivatives, and solves.

The solves are small (T = 0.3-0.6 s); each takes a few seconds on two cores.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from flyknot.constants import XARM7_XML, Z_MIN_TIP
from flyknot.errors import ConfigError, SolverError
from flyknot.limits import JointLimits, command_derivatives
from learner.bezier import BezierCommand, bernstein_basis, sample_command
from learner.initial_guess import IPOPT_SUCCESS, initial_guess, require_success
from learner.initial_guess_params import (
    COST_TERMS,
    HOME_Q,
    N_X,
    POSITION_MARGIN,
    InitialGuessParams,
    cost_samples,
    hand_velocity,
    knots_from_x,
    limit_sample_times,
    rotation_error_sq,
    rotation_log,
    x_from_knots,
)
from learner.initial_guess_problem import build_problem

pytestmark = pytest.mark.skipif(not XARM7_XML.is_file(), reason=f"{XARM7_XML} is absent")

FD_STEP = 1e-6
FD_RTOL = 1e-5  # |J - J_fd| <= FD_RTOL * max(1, max|J|)
AD_RTOL = 1e-9  # structured vs CasADi's own derivatives, relative to max(1, max|.|)
FLIP = np.diag([1.0, -1.0, -1.0])  # the xArm fingertip at home points down: R_tip = Rx(pi)


@pytest.fixture(scope="module")
def robot():
    from learner.kinematics import RobotModel

    return RobotModel.from_mjcf()


def _knots_true() -> tuple[np.ndarray, np.ndarray]:
    """A smooth reachable command (tied end knots, so it starts and ends at rest) and its base."""
    amp = np.array([0.3, -0.2, 0.25, 0.3, -0.3, 0.25, 0.4])
    s = np.array([0.0, 0.0, 0.2, 0.5, 0.8, 1.0, 1.0, 1.0])
    knots = np.zeros((10, 8))
    knots[:7] = HOME_Q[:, None] + 0.1 + amp[:, None] * s[None]
    b = np.array([0.05, -0.1, 1.0])
    knots[7:] = b[:, None]
    return knots, b


def _demo_from_knots(robot, knots, T, rate=200.0):
    t = np.linspace(0.0, T, round(T * rate) + 1)
    q = sample_command(knots, T, t, 0)[:, :7]
    qd = sample_command(knots, T, t, 1)[:, :7]
    tip = robot.tip_states(q, qd)
    return t, tip.p + knots[7:, 0], tip.R


def _fast_demo(T=0.3, rev=1.0, radius=0.25, z0=0.9):
    """A hand circling at radius * 2 pi rev / T (5.2 m/s) while spinning twice as fast about the
    rope axis, starting at z0 = 0.9 m, below z_min."""
    t = np.linspace(0.0, T, round(T * 200) + 1)
    w = 2 * np.pi * rev / T
    p = np.c_[0.45 + 0 * t, radius * np.sin(w * t), z0 + radius * (1 - np.cos(w * t))]
    R = Rotation.from_rotvec(np.c_[0 * t, 0 * t, 2 * w * t]).as_matrix() @ FLIP
    return t, p, R


@pytest.fixture(scope="module")
def small_problem(robot):
    """A tiny problem (T = 0.2 s, 11 demo samples) and a point x away from the seed."""
    T = 0.2
    t = np.linspace(0.0, T, 11)
    p = np.c_[0.3 * t, 0.1 * t, 1.5 + 0 * t]
    R = Rotation.from_rotvec(np.c_[t, -t, 0.5 * t]).as_matrix() @ FLIP
    problem = build_problem(t, p, R, T, robot)
    x = problem.x0 + 0.1 * np.random.default_rng(0).standard_normal(N_X)
    return problem, x, (t, p, R)


# --------------------------------------------------------------------------------------------
# parameters and inputs
# --------------------------------------------------------------------------------------------


def test_default_params_are_the_papers():
    p = InitialGuessParams()
    assert (p.w_j, p.w_p, p.w_r, p.w_v, p.z_min) == (5e-7, 10.0, 0.2, 0.5, Z_MIN_TIP)
    assert p.z_min == 1.2
    assert p.limits == JointLimits()
    assert p.torque_limits is True
    assert 0 < p.limit_margin < 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"w_p": -1.0}, "w_p: must be a finite number >= 0, got -1.0"),
        ({"w_j": float("nan")}, "w_j: must be a finite number >= 0, got nan"),
        ({"w_r": float("inf")}, "w_r: must be a finite number >= 0, got inf"),
        ({"w_v": "0.5"}, "w_v: must be a finite number >= 0, got '0.5'"),
        ({"z_min": float("inf")}, "z_min: must be a finite number [m], got inf"),
        ({"sample_rate_hz": 0.0}, "sample_rate_hz: must be a finite number > 0, got 0.0"),
        ({"max_iter": 0}, "max_iter: must be an integer >= 1, got 0"),
        ({"max_iter": 2.5}, "max_iter: must be an integer >= 1, got 2.5"),
        ({"max_iter": True}, "max_iter: must be an integer >= 1, got True"),
        ({"limit_margin": 1.0}, "limit_margin: must be < 1, got 1.0"),
        ({"limit_margin": -0.1}, "limit_margin: must be a finite number >= 0, got -0.1"),
        ({"tol": -1e-6}, "tol: must be a finite number > 0, got -1e-06"),
        (
            {"torque_limits": "yes"},
            "torque_limits: unknown value 'yes' (valid choices: True, False)",
        ),
        ({"limits": None}, "limits: must be a JointLimits, got NoneType"),
    ],
)
def test_params_validation_messages(kwargs, message):
    with pytest.raises(ConfigError) as exc:
        InitialGuessParams(**kwargs)
    assert str(exc.value) == message


def _good_inputs():
    t = np.linspace(0.0, 0.2, 5)
    p = np.zeros((5, 3))
    R = np.repeat(FLIP[None], 5, axis=0)
    return t, p, R


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"T": 0.0}, "T: must be a finite number > 0, got 0.0"),
        ({"T": None}, "T: must be a finite number > 0, got None"),
        (
            {"t": np.linspace(0.0, 0.3, 5)},
            "demo_hand_t: must lie in [0, T] = [0, 0.2] s, got [0, 0.3]",
        ),
        ({"t": np.array([0.0, 0.1, 0.1, 0.15, 0.2])}, "demo_hand_t: must be strictly increasing"),
        ({"t": np.array([0.0])}, "demo_hand_t: must have shape (k,) with k >= 2, got (1,)"),
        ({"p": np.zeros((5, 2))}, "demo_hand_p: must have shape (5, 3), got (5, 2)"),
        ({"p": np.full((5, 3), np.nan)}, "demo_hand_p: must be finite everywhere"),
        ({"R": np.zeros((5, 3))}, "demo_hand_R: must have shape (5, 3, 3), got (5, 3)"),
        (
            {"R": np.repeat(np.diag([1.0, 1.0, -1.0])[None], 5, axis=0)},
            "demo_hand_R: must hold rotation matrices; sample 0 has max|R^T R - I| = 0, det = -1",
        ),
        ({"q_seed": np.zeros(6)}, "q_seed: must be a finite array of shape (7,) [rad]"),
        ({"robot": object()}, "robot: must be a 7-joint learner.kinematics.RobotModel"),
        ({"params": {}}, "params: must be InitialGuessParams, got dict"),
    ],
)
def test_input_validation_messages(robot, change, message):
    t, p, R = _good_inputs()
    kw = {"t": t, "p": p, "R": R, "T": 0.2, "robot": robot, "q_seed": None, "params": None}
    kw.update(change)
    with pytest.raises(ConfigError) as exc:
        build_problem(
            kw["t"],
            kw["p"],
            kw["R"],
            kw["T"],
            kw["robot"],
            params=kw["params"],
            q_seed=kw["q_seed"],
        )
    assert str(exc.value) == message


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    a=arrays(float, (2, 3), elements=st.floats(-4.0, 4.0)),
)
def test_rotation_error_sq_is_quaternion_vector_part(a):
    """The smooth rotation term is the squared quaternion vector part, close to |Log|^2.

    3 - tr(R_h^T R) = 4 sin^2(theta / 2) = |2 v|^2 and theta^2 (1 - theta^2 / 12) <= it <= theta^2,
    with theta = |Log(R_h^T R)| and v the quaternion vector part.
    """
    R_h = Rotation.from_rotvec(a[:1]).as_matrix()
    R = Rotation.from_rotvec(a[1:]).as_matrix()
    e = rotation_error_sq(R_h, R)[0]
    theta = np.linalg.norm(rotation_log(R_h, R)[0])
    assert 0.0 <= theta <= np.pi + 1e-12
    assert e == pytest.approx(4.0 * np.sin(theta / 2) ** 2, abs=1e-12)
    quat = Rotation.from_matrix(R_h[0].T @ R[0]).as_quat(scalar_first=True)
    assert e == pytest.approx(4.0 * float(quat[1:] @ quat[1:]), abs=1e-12)
    assert theta**2 * (1 - theta**2 / 12) - 1e-12 <= e <= theta**2 + 1e-12


def test_rotation_log_is_exact():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    for angle in (0.0, 0.3, 2.0, np.pi - 1e-6):
        R_h = Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix()
        R = R_h @ Rotation.from_rotvec(angle * axis).as_matrix()
        np.testing.assert_allclose(rotation_log(R_h[None], R[None])[0], angle * axis, atol=1e-9)


def test_hand_velocity_rule():
    """Central differences are exact for quadratics inside; first-order one-sided at the ends."""
    t = np.linspace(0.0, 0.5, 101)
    c = np.array([[0.1, -2.0, 3.0], [1.0, 0.5, -4.0]])  # p = c0 t + c1 t^2
    p = t[:, None] * c[0] + t[:, None] ** 2 * c[1]
    v = hand_velocity(t, p)
    np.testing.assert_allclose(v[1:-1], c[0] + 2 * t[1:-1, None] * c[1], atol=1e-10)
    np.testing.assert_allclose(v[0], (p[1] - p[0]) / (t[1] - t[0]), atol=1e-12)
    np.testing.assert_allclose(v[-1], (p[-1] - p[-2]) / (t[-1] - t[-2]), atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    x=arrays(float, (N_X,), elements=st.floats(-5.0, 5.0)),
    T=st.floats(0.05, 3.0),
)
def test_knots_from_x_rest_ends_and_round_trip(x, T):
    knots = knots_from_x(x)
    _assert_rest_ends(knots, T)
    np.testing.assert_array_equal(x_from_knots(knots), x)
    BezierCommand(knots, T)  # base rows constant


def test_x_from_knots_messages():
    knots = knots_from_x(np.arange(N_X, dtype=float))
    bad = knots.copy()
    bad[2, 1] += 1.0
    with pytest.raises(ConfigError, match=r"^knots: arm rows need knot 1 = knot 0 and knot 6"):
        x_from_knots(bad)
    bad = knots.copy()
    bad[8, 3] += 1.0
    with pytest.raises(ConfigError, match=r"^knots: base-offset rows must be constant"):
        x_from_knots(bad)


def _assert_rest_ends(knots, T):
    """qd(0) = 7 (k_1 - k_0) / T and qd(T) = 7 (k_7 - k_6) / T are exactly 0: the end knots are
    tied bitwise. Evaluating the basis product adds only rounding (BLAS may use FMA)."""
    arm = knots[:7]
    assert np.all(7.0 / T * (arm[:, 1] - arm[:, 0]) == 0.0)
    assert np.all(7.0 / T * (arm[:, 7] - arm[:, 6]) == 0.0)
    qd = sample_command(knots, T, np.array([0.0, T]), 1)[:, :7]
    assert np.abs(qd).max() <= 1e-13 * max(1.0, np.abs(arm).max()) / T


def test_limit_sample_times():
    t = limit_sample_times(0.5)
    assert t.shape == (126,) and t[-1] == 0.5
    np.testing.assert_allclose(np.diff(t), 0.004, atol=1e-15)
    t = limit_sample_times(0.401)  # the command's samples: 0.401 s itself is never commanded
    assert t.shape == (101,) and t[-1] == pytest.approx(0.4)
    np.testing.assert_array_equal(t, BezierCommand(np.zeros((10, 8)), 0.401).sample_times())


def test_cost_samples_resampling():
    t = np.linspace(0.0, 0.5, 101)
    p = np.c_[t, 2 * t, -t]  # linear: interpolation and velocity are exact
    axis = np.array([0.0, 0.6, 0.8])
    R = Rotation.from_rotvec(np.outer(3.0 * t, axis)).as_matrix()
    ti, pi, Ri, vi = cost_samples(t, p, R, 30.0)
    assert ti.shape == (16,) and ti[0] == 0.0 and ti[-1] == 0.5
    np.testing.assert_allclose(pi, np.c_[ti, 2 * ti, -ti], atol=1e-12)
    np.testing.assert_allclose(vi, np.tile([1.0, 2.0, -1.0], (16, 1)), atol=1e-9)
    np.testing.assert_allclose(
        Rotation.from_matrix(Ri).as_rotvec(), np.outer(3 * ti, axis), atol=1e-9
    )
    same = cost_samples(t, p, R, None)
    assert same[0] is t and same[1] is p


# --------------------------------------------------------------------------------------------
# the NLP: values and derivatives
# --------------------------------------------------------------------------------------------


def test_objective_matches_numpy(robot, small_problem):
    problem, x, (t, p, R) = small_problem
    knots = knots_from_x(x)
    T = problem.T
    q, qd, q3 = (bernstein_basis(t, T, r) @ knots[:7].T for r in (0, 1, 3))
    tip = robot.tip_states(q, qd)
    v_h = hand_velocity(t, p)
    w = problem.params
    expect = [
        w.w_p * np.sum((tip.p + knots[7:, 0] - p) ** 2),
        w.w_r * np.sum(rotation_error_sq(R, tip.R)),
        w.w_v * np.sum((tip.v - v_h) ** 2),
        w.w_j * np.sum(q3**2),
    ]
    terms = np.asarray(problem.terms(x)).ravel()
    np.testing.assert_allclose(terms, expect, rtol=1e-10)
    assert float(problem.f(x)) == pytest.approx(sum(expect), rel=1e-12)


def test_constraints_match_numpy(robot, small_problem):
    problem, x, _ = small_problem
    knots = knots_from_x(x)
    T, tl = problem.T, problem.t_limit
    g = np.asarray(problem.g(x)).ravel()
    q = sample_command(knots, T, tl)[:, :7]
    qd, qdd = command_derivatives(q, tl[1] - tl[0])  # as the controllers take them
    expect = {"pos": q, "vel": qd, "acc": qdd, "tau": robot.torques(q, qd, qdd)}
    assert list(problem.blocks) == ["z", "pos", "vel", "acc", "tau"]
    for name, value in expect.items():
        a, z = problem.blocks[name]
        scale = max(1.0, np.abs(value).max())
        np.testing.assert_allclose(g[a:z], value.ravel(), rtol=0, atol=1e-10 * scale)
    z0 = robot.tip_states(knots[None, :7, 0], np.zeros((1, 7))).p[0, 2] + knots[9, 0]
    assert g[0] == pytest.approx(z0, abs=1e-12)
    lim, keep = problem.params.limits, 1.0 - problem.params.limit_margin
    a, z = problem.blocks["vel"]
    np.testing.assert_allclose(problem.ubg[a:z], np.tile(keep * lim.qd_max, len(tl)))
    a, z = problem.blocks["pos"]
    np.testing.assert_allclose(problem.lbg[a:z], np.tile(lim.q_min + POSITION_MARGIN, len(tl)))
    assert problem.lbg[0] == problem.params.z_min and problem.ubg[0] == np.inf


def test_seed(robot, small_problem):
    problem, _, (_, p, _) = small_problem
    knots = knots_from_x(problem.x0)
    np.testing.assert_array_equal(knots[:7], np.repeat(HOME_Q[:, None], 8, axis=1))
    tip = robot.tip_states(HOME_Q[None], np.zeros((1, 7)))
    np.testing.assert_allclose(tip.p[0] + knots[7:, 0], p[0], atol=1e-12)


def test_jac_g_matches_finite_differences(small_problem):
    problem, x, _ = small_problem
    g0, J = problem.jac_g(x, [])
    J = np.asarray(ca.densify(J))
    np.testing.assert_allclose(np.asarray(g0).ravel(), np.asarray(problem.g(x)).ravel())
    J_fd = np.empty_like(J)
    for i in range(N_X):
        e = np.zeros(N_X)
        e[i] = FD_STEP
        J_fd[:, i] = (np.asarray(problem.g(x + e)) - np.asarray(problem.g(x - e))).ravel()
    J_fd /= 2 * FD_STEP
    assert np.abs(J - J_fd).max() <= FD_RTOL * max(1.0, np.abs(J).max())


def test_hess_lag_matches_casadi_and_finite_differences(small_problem):
    problem, x, _ = small_problem
    r = problem.lbg.size
    rng = np.random.default_rng(1)
    lam_f, lam_g = 0.7, rng.standard_normal(r)
    H = np.asarray(ca.densify(problem.hess_lag(x, [], lam_f, lam_g)))
    assert np.array_equal(H, np.triu(H))
    H = H + np.triu(H, 1).T

    lf, lg = ca.MX.sym("lf"), ca.MX.sym("lg", r)
    lag = lf * problem.f(problem.x) + ca.dot(lg, problem.g(problem.x))
    H_ad = ca.Function("h", [problem.x, lf, lg], [ca.hessian(lag, problem.x)[0]])
    H_ad = np.asarray(H_ad(x, lam_f, lam_g))
    assert np.abs(H - H_ad).max() <= AD_RTOL * max(1.0, np.abs(H_ad).max())

    grad = ca.Function("gl", [problem.x, lf, lg], [ca.gradient(lag, problem.x)])
    H_fd = np.empty_like(H)
    for i in range(N_X):
        e = np.zeros(N_X)
        e[i] = FD_STEP
        H_fd[:, i] = np.asarray(grad(x + e, lam_f, lam_g) - grad(x - e, lam_f, lam_g)).ravel()
    H_fd /= 2 * FD_STEP
    assert np.abs(H - H_fd).max() <= FD_RTOL * max(1.0, np.abs(H).max())


def test_torque_rows_optional(robot):
    t, p, R = _good_inputs()
    problem = build_problem(t, p, R, 0.2, robot, params=InitialGuessParams(torque_limits=False))
    assert list(problem.blocks) == ["z", "pos", "vel", "acc"]
    H = problem.hess_lag(problem.x0, [], 1.0, np.ones(problem.lbg.size))
    assert np.all(np.isfinite(np.asarray(ca.densify(H))))


# --------------------------------------------------------------------------------------------
# solves
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reachable(robot):
    knots, _ = _knots_true()
    T = 0.6
    t, p, R = _demo_from_knots(robot, knots, T)
    return initial_guess(t, p, R, T, robot)


def test_recovers_reachable_trajectory(reachable):
    """FK of a known command + base offset is tracked within 5 mm and 3 deg (the paper's jerk
    weight costs a little accuracy; the knots themselves are not unique: 10 rows for 6 DoF)."""
    res = reachable
    assert res.success and res.status in IPOPT_SUCCESS, res.status
    assert res.max_errors["position"] < 5e-3
    assert np.degrees(res.max_errors["rotation"]) < 3.0
    assert res.max_errors["velocity"] < 0.1  # includes the demo's finite-difference error
    assert require_success(res) is res
    assert sum(res.cost_terms.values()) == pytest.approx(res.cost, rel=1e-12)
    assert set(res.cost_terms) == set(COST_TERMS)


def _check_limits_at_250hz(robot, res, params):
    """Every limit at the 250 Hz command samples, analytic Bezier derivatives, and z_min."""
    lim = params.limits
    T = res.T
    t = res.command.sample_times()
    q, qd, qdd = (sample_command(res.knots, T, t, r)[:, :7] for r in (0, 1, 2))
    assert np.all(q >= lim.q_min) and np.all(q <= lim.q_max)
    assert np.all(np.abs(qd) <= lim.qd_max)
    assert np.all(np.abs(qdd) <= lim.qdd_max)
    assert np.all(np.abs(robot.torques(q, qd, qdd)) <= lim.tau_max)
    z0 = robot.tip_states(res.knots[None, :7, 0], np.zeros((1, 7))).p[0, 2] + res.knots[9, 0]
    assert z0 >= params.z_min - 1e-6
    return q


@pytest.mark.parametrize(
    "limits",
    [JointLimits(), JointLimits(qdd_max=np.full(7, 40.0))],
    ids=["paper", "qdd40"],
)
def test_too_fast_hand_still_gives_a_valid_command(robot, limits):
    from flyknot_sim.faults import first_fault

    t, p, R = _fast_demo()
    params = InitialGuessParams(sample_rate_hz=100.0, limits=limits)
    res = initial_guess(t, p, R, t[-1], robot, params=params)
    assert res.success, (res.status, res.violations)
    # the demo is far beyond the arm: speed limits bind and tracking is poor
    assert res.limit_usage["vel"] == pytest.approx(0.95, abs=1e-3)
    assert res.max_errors["velocity"] > 2.0
    # the hand starts at 0.9 m: the start-height row binds
    assert res.active_limits["z"] == 1 and abs(res.limit_usage["z"]) < 1e-6
    if limits.qdd_max[0] < 100:
        assert res.limit_usage["acc"] == pytest.approx(0.95, abs=1e-3)
    q = _check_limits_at_250hz(robot, res, params)
    # the controller's own check (central differences of the 250 Hz samples)
    assert first_fault(q, 0.004, limits=limits) is None
    _assert_rest_ends(res.knots, res.T)


def test_failure_is_reported_not_raised(robot):
    t, p, R = _fast_demo()
    res = initial_guess(t, p, R, t[-1], robot, params=InitialGuessParams(max_iter=1))
    assert res.status == "Maximum_Iterations_Exceeded"
    assert not res.converged and not res.success
    assert res.iterations == 1
    with pytest.raises(SolverError) as exc:
        require_success(res)
    assert str(exc.value).startswith("ipopt failed with status 'Maximum_Iterations_Exceeded'")
    assert exc.value.status == "Maximum_Iterations_Exceeded"


def test_start_height_in_the_lab_frame_ignores_the_base_offset():
    """With the lab's base height given, z_min holds above the lab's floor, not the demo's."""
    from learner.kinematics import RobotModel

    robot = RobotModel.from_mjcf()
    T = 0.5
    t = np.linspace(0, T, 51)
    # A hand held still low in the demo frame: tracking it pulls the fingertip down.
    p = np.tile([0.4, 0.0, 0.6], (t.size, 1))
    R = np.tile(np.diag([1.0, -1.0, -1.0]), (t.size, 1, 1))
    params = InitialGuessParams(base_height=1.0, z_min=1.2, torque_limits=False)
    res = initial_guess(t, p, R, T, robot, params=params)
    assert res.success, res.status
    z_lab = float(np.asarray(robot.fk(res.knots[:7, 0])[0])[2, 0]) + 1.0
    assert z_lab >= 1.2 - 1e-6
    with pytest.raises(ConfigError, match="base_height: must be a finite number >= 0"):
        InitialGuessParams(base_height=-1.0)


@pytest.mark.slow
def test_iteration_reports_follow_ipopt_and_change_nothing(robot, reachable):
    knots, _ = _knots_true()
    T = 0.6
    t, p, R = _demo_from_knots(robot, knots, T)
    seen = []
    res = initial_guess(t, p, R, T, robot, on_iteration=lambda k, f: seen.append((k, f)))
    assert [k for k, _ in seen] == list(range(1, len(seen) + 1))
    assert len(seen) >= 2 and all(np.isfinite(f) for _, f in seen)
    assert seen[-1][1] == pytest.approx(res.cost, rel=1e-6)
    np.testing.assert_array_equal(res.knots, reachable.knots)

"""Tests of learner/inverse_qp.py (the builder's math without a solver, then both backends)
and of the limit rows it takes (learner/limit_rows.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.constants import QD_MAX, XARM7_XML
from flyknot.errors import ConfigError, SolverError
from flyknot.limits import JointLimits, command_derivatives
from learner.bezier import sample_command
from learner.inverse_qp import (
    FollowThrough,
    InverseModelWeights,
    base_equality_rows,
    build_inverse_qp,
    rest_equality_rows,
)
from learner.kinematics import RobotModel
from learner.limit_rows import LIMIT_KINDS, LimitRows, limit_rows, subset_rows
from learner.qp_solve import BACKENDS, require_solved, solve_qp

CHAIN7 = Path(__file__).parent / "data" / "chain7.xml"
N_MARK = 11
HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
T = 0.8
T_SAMPLES = np.arange(0.0, T + 1e-9, 1.0 / 250.0)  # 201 samples at 250 Hz
AGREE = 1e-5  # backends vs each other / closed form [knot units]


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_mjcf(XARM7_XML if XARM7_XML.is_file() else CHAIN7)


def _problem(seed: int, k_ft: int = 9):
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(6 * N_MARK, 80)) * 0.1
    err = rng.normal(size=6 * N_MARK) * 0.05
    follow = FollowThrough(
        e=rng.normal(size=(k_ft, 9)) * 0.01,
        J=rng.normal(size=(k_ft, 9, 80)) * 0.1,
        is_tc=np.arange(k_ft) == 0,
    )
    return M, err, follow


def _direct_cost(x, M, err, follow, w: InverseModelWeights) -> float:
    """The paper's objective evaluated term by term, independent of the builder."""
    n = M.shape[0] // 2
    r = M @ x - err
    cost = w.w_crit_pos * r[:n] @ r[:n] + w.w_crit_vel * r[n:] @ r[n:]
    if follow is not None:
        for e, J, tc in zip(follow.e, follow.J, follow.is_tc, strict=True):
            res = e - J @ x  # value after subtracting the update
            wp, wr, wv = (
                (w.w_pc, w.w_rc, w.w_vc) if tc else (w.w_pft, w.w_rft, w.w_ft_velocity * w.w_vft)
            )
            cost += wp * res[:3] @ res[:3] + wr * res[3:6] @ res[3:6] + wv * res[6:] @ res[6:]
    cost += w.w_control * x[:56] @ x[:56]
    return float(cost)


def _knots(amplitude: float = 0.35, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, 8)
    k = np.zeros((10, 8))
    bump = np.sin(np.pi * s)
    bump[[1, 6]] = bump[[0, 7]]  # tied end knots: at rest at both ends, as every command is
    k[:7] = HOME[:, None] + amplitude * bump[None, :] * rng.uniform(-1, 1, (7, 1))
    k[7:] = np.array([[0.3], [0.0], [0.2]])
    return k


# ------------------------------------------------------------------------------- inputs


def test_weights_defaults_are_the_papers():
    w = InverseModelWeights()
    assert (w.w_control, w.w_crit_pos, w.w_crit_vel) == (0.5, 25.0, 0.00375)
    assert (w.w_pc, w.w_vc, w.w_rc, w.w_pft, w.w_vft, w.w_rft) == (100.0, 0.1, 5.0, 1.0, 0.1, 0.1)
    assert w.w_ft_velocity == 0.5
    np.testing.assert_allclose(w.follow_weights(True), np.repeat([100.0, 5.0, 0.1], 3))
    np.testing.assert_allclose(w.follow_weights(False), np.repeat([1.0, 0.1, 0.05], 3))


def test_bad_weights_raise_exact_messages():
    with pytest.raises(ConfigError) as exc:
        InverseModelWeights(w_control=-1.0)
    assert str(exc.value) == "w_control: must be a finite number >= 0, got -1.0"
    with pytest.raises(ConfigError) as exc:
        InverseModelWeights(w_rc=float("nan"))
    assert str(exc.value) == "w_rc: must be a finite number >= 0, got nan"


def test_bad_inputs_raise_exact_messages():
    M, err, follow = _problem(0)
    with pytest.raises(ConfigError) as exc:
        build_inverse_qp(M_crit=M[:, :79], err_crit=err)
    assert str(exc.value) == "M_crit: must have shape (6N, 80), got (66, 79)"
    with pytest.raises(ConfigError) as exc:
        build_inverse_qp(M_crit=M, err_crit=err, equal=[(M, err)])
    assert str(exc.value) == "equal: give either M_crit/err_crit or equal, not both"
    with pytest.raises(ConfigError) as exc:
        build_inverse_qp(M_crit=M, err_crit=err, base_update="free")
    assert str(exc.value) == ("base_update: unknown value 'free' (valid choices: constant, zero)")
    with pytest.raises(ConfigError) as exc:
        FollowThrough(e=follow.e, J=follow.J[:, :, :10], is_tc=follow.is_tc)
    assert str(exc.value) == "J: must have shape (9, 9, 80), got (9, 9, 10)"
    with pytest.raises(ConfigError) as exc:
        LimitRows(J=np.zeros((2, 80)), b=np.zeros(2), lo=np.ones(2), hi=np.zeros(2))
    assert str(exc.value) == "lo: must be <= hi in every row"
    with pytest.raises(ConfigError) as exc:
        limit_rows(_knots(), T, T_SAMPLES[:5], None, kinds=("pos", "jerk"))
    assert str(exc.value) == (
        "kinds: unknown value 'jerk' (valid choices: pos, vel, acc, tau, tau_links)"
    )
    with pytest.raises(ConfigError) as exc:
        JointLimits(qd_max=np.zeros(7))
    assert str(exc.value) == "limits.qd_max: must be > 0; joint 1 is 0.0"


def test_bad_backend_raises_exact_message():
    M, err, _ = _problem(0)
    qp = build_inverse_qp(M_crit=M, err_crit=err)
    with pytest.raises(ConfigError) as exc:
        solve_qp(qp, backend="gurobi")
    assert str(exc.value) == "backend: unknown value 'gurobi' (valid choices: osqp, clarabel)"


# ------------------------------------------------------------------ builder math (no solver)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), use_follow=st.booleans())
def test_objective_equals_direct_cost_terms(seed: int, use_follow: bool):
    M, err, follow = _problem(seed)
    follow = follow if use_follow else None
    w = InverseModelWeights()
    qp = build_inverse_qp(M_crit=M, err_crit=err, weights=w, follow=follow)
    P = qp.P.toarray()
    assert np.array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() >= -1e-9 * np.abs(P).max()
    x = np.random.default_rng(seed + 1).normal(size=80)
    direct = _direct_cost(x, M, err, follow, w)
    assert qp.objective(x) == pytest.approx(direct, rel=1e-10, abs=1e-12)
    assert qp.objective(np.zeros(80)) == pytest.approx(
        _direct_cost(np.zeros(80), M, err, follow, w), rel=1e-12
    )


def test_equal_weight_objective_is_the_mean_over_samples():
    rng = np.random.default_rng(3)
    samples = [(rng.normal(size=(66, 80)), rng.normal(size=66)) for _ in range(4)]
    w = InverseModelWeights()
    qp = build_inverse_qp(equal=samples, weights=w)
    x = rng.normal(size=80)
    direct = (
        np.mean(
            [_direct_cost(x, M, e, None, w) - w.w_control * x[:56] @ x[:56] for M, e in samples]
        )
        + w.w_control * x[:56] @ x[:56]
    )
    assert qp.objective(x) == pytest.approx(direct, rel=1e-10)


@pytest.mark.parametrize("mode", ["constant", "zero"])
def test_base_equality_rows(mode: str):
    E = base_equality_rows(mode)
    assert E.shape == ((21, 80) if mode == "constant" else (24, 80))
    # Every update in the null space of E has base rows constant over knots (or zero) and
    # leaves the arm rows free; the null space has the expected dimension.
    _, s, Vt = np.linalg.svd(E)
    null = Vt[np.sum(s > 1e-12) :]
    assert null.shape[0] == 56 + (3 if mode == "constant" else 0)
    for v in null:
        base = v.reshape(10, 8)[7:]
        np.testing.assert_allclose(base, base[:, :1].repeat(8, axis=1), atol=1e-12)
        if mode == "zero":
            np.testing.assert_allclose(base, 0.0, atol=1e-12)
    M, err, _ = _problem(1)
    qp = build_inverse_qp(M_crit=M, err_crit=err, base_update=mode)
    a, z = qp.blocks["base"]
    np.testing.assert_array_equal(qp.A[a:z].toarray(), E)
    assert np.all(qp.l[a:z] == 0) and np.all(qp.u[a:z] == 0)


def test_limit_rows_values_and_jacobians(robot: RobotModel):
    """b equals the sampled command/torques; J equals central differences w.r.t. the knots."""
    knots = _knots(seed=4)
    t = T_SAMPLES[::20]
    rows = limit_rows(knots, T, t, robot)
    m = t.size
    q = sample_command(knots, T, t)[:, :7]
    qd, qdd = command_derivatives(q, t[1] - t[0])  # as the controllers take them
    for kind, y in (("pos", q), ("vel", qd), ("acc", qdd)):
        a, z = rows.blocks[kind]
        np.testing.assert_allclose(rows.b[a:z], y.ravel(), rtol=1e-9, atol=1e-9)
    a, z = rows.blocks["tau"]
    np.testing.assert_allclose(rows.b[a:z], robot.torques(q, qd, qdd).ravel(), atol=1e-12)
    np.testing.assert_allclose(rows.lo[a:z], -np.tile(JointLimits().tau_max, m))
    # the links' part is the torque the simulated controller faults on (MuJoCo's RNE of the
    # robot alone), and it differs from the learner's whole torque by the joints' damping
    from flyknot_sim.faults import command_torques
    from flyknot_sim.robot import load_robot_model

    a, z = rows.blocks["tau_links"]
    lab = command_torques(load_robot_model(), q, qd, qdd)
    np.testing.assert_allclose(rows.b[a:z], lab.ravel(), atol=1e-9)
    assert np.abs(rows.b[a:z] - rows.b[slice(*rows.blocks["tau"])]).max() > 0.1
    h = 1e-6
    J_fd = np.zeros_like(rows.J)
    for c in range(80):
        e = np.zeros(80)
        e[c] = h
        plus = limit_rows(knots + e.reshape(10, 8), T, t, robot).b
        minus = limit_rows(knots - e.reshape(10, 8), T, t, robot).b
        J_fd[:, c] = (plus - minus) / (2 * h)
    for kind in LIMIT_KINDS:
        a, z = rows.blocks[kind]
        scale = max(1.0, np.abs(rows.J[a:z]).max())
        assert np.abs(rows.J[a:z] - J_fd[a:z]).max() <= 1e-6 * scale, kind
    assert np.all(rows.J[:, 56:] == 0)  # base offset rows move no joint


def test_the_grid_forms_only_the_rows_asked_for(robot: RobotModel):
    """Rows taken from the grid equal those of the whole Jacobian bit for bit, in any block
    order; J dkappa without the Jacobian equals the product with it."""
    knots = _knots(seed=5)
    t = T_SAMPLES[::10]
    for kinds in (LIMIT_KINDS, ("tau", "pos"), ("tau_links", "vel", "tau")):
        grid = limit_rows(knots, T, t, robot, kinds=kinds)
        full = grid.J
        idx = np.sort(np.random.default_rng(1).choice(grid.n_rows, 40, replace=False))
        np.testing.assert_array_equal(grid.rows(idx), full[idx])
        taken = subset_rows(grid, idx)
        np.testing.assert_array_equal(taken.J, full[idx])
        np.testing.assert_array_equal(taken.b, grid.b[idx])
        assert list(taken.blocks) == list(kinds)
        dk = np.random.default_rng(2).standard_normal(80)
        np.testing.assert_allclose(grid.product(dk), full @ dk, rtol=1e-10, atol=1e-9)


# ------------------------------------------------------------------------------ solving


@pytest.mark.parametrize("mode", ["constant", "zero"])
def test_without_limits_solution_is_closed_form(mode: str):
    M, err, follow = _problem(5)
    qp = build_inverse_qp(M_crit=M, err_crit=err, follow=follow, base_update=mode)
    E = np.vstack([base_equality_rows(mode), rest_equality_rows()])
    P = qp.P.toarray()
    kkt = np.block([[P, E.T], [E, np.zeros((E.shape[0], E.shape[0]))]])
    x = np.linalg.solve(kkt, np.concatenate([-qp.q, np.zeros(E.shape[0])]))[:80]
    for backend in BACKENDS:
        res = require_solved(solve_qp(qp, backend))
        np.testing.assert_allclose(res.dkappa.ravel(), x, atol=AGREE)
        assert res.objective == pytest.approx(qp.objective(x), rel=1e-6)
        base = res.dkappa[7:]
        np.testing.assert_allclose(base, base[:, :1].repeat(8, axis=1), atol=1e-8)
        arm = res.dkappa[:7]
        np.testing.assert_allclose(arm[:, 1], arm[:, 0], atol=1e-8)  # qd(0) stays 0
        np.testing.assert_allclose(arm[:, 7], arm[:, 6], atol=1e-8)  # qd(T) stays 0


def test_rest_rows_can_be_dropped():
    M, err, _ = _problem(5)
    with_rest = build_inverse_qp(M_crit=M, err_crit=err)
    without = build_inverse_qp(M_crit=M, err_crit=err, keep_rest=False)
    assert with_rest.A.shape[0] == without.A.shape[0] + 14
    assert with_rest.blocks["rest"] == (21, 35)
    x = require_solved(solve_qp(without, "clarabel")).dkappa
    assert np.abs(x[:7, 1] - x[:7, 0]).max() > 1e-6  # unconstrained, the start moves


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_backends_agree_on_random_feasible_qps(seed: int):
    M, err, follow = _problem(10 + seed)
    rng = np.random.default_rng(seed)
    r = 300
    J = rng.normal(size=(r, 80)) * 0.2
    b = rng.normal(size=r) * 0.1
    slack = rng.uniform(0.0, 0.05, size=(2, r))  # dkappa = 0 feasible; many rows near binding
    lo, hi = b - slack[0], b + slack[1]
    hi[::7] = np.inf
    limits = LimitRows(J=J, b=b, lo=lo, hi=hi)
    qp = build_inverse_qp(M_crit=M, err_crit=err * 20, follow=follow, limits=limits)
    res = {name: require_solved(solve_qp(qp, name)) for name in BACKENDS}
    np.testing.assert_allclose(res["osqp"].dkappa, res["clarabel"].dkappa, atol=AGREE)
    after = b - J @ res["osqp"].dkappa.ravel()
    assert np.all(after >= lo - 1e-7) and np.all(after <= hi + 1e-7)
    n_active = np.sum(np.minimum(after - lo, hi - after) < 1e-6)
    assert n_active >= 1  # the test exercises binding constraints
    unconstrained = require_solved(
        solve_qp(build_inverse_qp(M_crit=M, err_crit=err * 20, follow=follow))
    )
    assert unconstrained.objective < res["osqp"].objective


@pytest.mark.parametrize("backend", BACKENDS)
def test_binding_position_and_velocity_limits_hold_on_the_sampled_trajectory(
    robot: RobotModel, backend: str
):
    """The update asks joint 2 past q_max and joint 1 past qd_max; the updated command obeys."""
    knots = _knots(amplitude=0.2, seed=6)
    knots[1] = 1.7  # joint 2 at rest, 0.2 rad below q_max = 1.9
    target = np.zeros((10, 8))
    target[1] = -0.5  # subtracting it would put joint 2 at 2.2 rad
    target[0] = 3.0 * np.array(
        [0, 0, -1, 1, -1, 1, 0, 0]
    )  # fast swings of joint 1, at rest at the ends
    rng = np.random.default_rng(7)
    M = rng.normal(size=(6 * N_MARK, 80)) * 0.3
    err = M @ target.ravel()
    limits = limit_rows(knots, T, T_SAMPLES, robot)
    free = require_solved(solve_qp(build_inverse_qp(M_crit=M, err_crit=err), backend))
    new_free = knots - free.dkappa
    assert sample_command(new_free, T, T_SAMPLES)[:, 1].max() > 1.9 + 0.1
    assert np.abs(sample_command(new_free, T, T_SAMPLES, 1)[:, :7]).max() > QD_MAX[0] + 0.5
    res = require_solved(solve_qp(build_inverse_qp(M_crit=M, err_crit=err, limits=limits), backend))
    new = knots - res.dkappa
    q = sample_command(new, T, T_SAMPLES)[:, :7]
    qd = command_derivatives(q, 1.0 / 250.0)[0]  # the velocity the controllers check
    lim = JointLimits()
    assert np.all(q <= lim.q_max + 1e-6) and np.all(q >= lim.q_min - 1e-6)
    assert np.all(np.abs(qd) <= lim.qd_max + 1e-6)
    assert q[:, 1].max() == pytest.approx(1.9, abs=1e-5)  # binding, not merely satisfied
    assert np.abs(qd).max() == pytest.approx(QD_MAX[0], abs=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_infeasible_qp_reports_status(backend: str):
    M, err, _ = _problem(8)
    J = np.zeros((2, 80))
    J[:, 0] = 1.0
    # b - dkappa[0] >= 1 and b - dkappa[0] <= -1 cannot both hold.
    limits = LimitRows(J=J, b=np.zeros(2), lo=np.array([1.0, -np.inf]), hi=np.array([np.inf, -1]))
    res = solve_qp(build_inverse_qp(M_crit=M, err_crit=err, limits=limits), backend)
    assert not res.solved
    assert res.status == {"osqp": "primal infeasible", "clarabel": "PrimalInfeasible"}[backend]
    assert np.all(np.isnan(res.dkappa)) and np.isnan(res.objective)
    with pytest.raises(SolverError) as exc:
        require_solved(res)
    assert str(exc.value) == f"{backend} failed with status {res.status!r}"
    assert exc.value.status == res.status


def test_realistic_size_agrees_across_backends(robot: RobotModel):
    """N = 11 markers, 201 samples x 7 joints x 5 limits, 9 follow-through samples."""
    M, err, follow = _problem(9)
    limits = limit_rows(_knots(), T, T_SAMPLES, robot)
    qp = build_inverse_qp(M_crit=M, err_crit=err * 10, follow=follow, limits=limits)
    assert qp.m == 21 + 14 + len(LIMIT_KINDS) * 7 * T_SAMPLES.size
    assert set(qp.blocks) == {"base", "rest", *LIMIT_KINDS}
    res = {name: require_solved(solve_qp(qp, name)) for name in BACKENDS}
    np.testing.assert_allclose(res["osqp"].dkappa, res["clarabel"].dkappa, atol=AGREE)
    for r in res.values():
        assert qp.violation(r.dkappa) <= 1e-7


# ------------------------------------------------------------------------------ trust region


def test_trust_region_rows_are_a_box_on_the_arm_knots():
    M, err, follow = _problem(3)
    plain = build_inverse_qp(M_crit=M, err_crit=err, follow=follow)
    qp = build_inverse_qp(M_crit=M, err_crit=err, follow=follow, trust_region=0.02)
    a, z = qp.blocks["trust"]
    assert z - a == 56 and qp.A.shape[0] == plain.A.shape[0] + 56
    box = qp.A.toarray()[a:z]
    np.testing.assert_array_equal(box[:, :56], np.eye(56))
    np.testing.assert_array_equal(box[:, 56:], 0.0)  # the base rows are not boxed
    np.testing.assert_array_equal(qp.l[a:z], -0.02)
    np.testing.assert_array_equal(qp.u[a:z], 0.02)
    np.testing.assert_array_equal(qp.P.toarray(), plain.P.toarray())  # the cost is unchanged


@pytest.mark.parametrize("backend", BACKENDS)
def test_trust_region_binds_and_caps_the_step(backend: str):
    M, err, _ = _problem(4)
    free = require_solved(solve_qp(build_inverse_qp(M_crit=M, err_crit=err * 50), backend))
    radius = 0.25 * np.abs(free.dkappa[:7]).max()
    qp = build_inverse_qp(M_crit=M, err_crit=err * 50, trust_region=radius)
    boxed = require_solved(solve_qp(qp, backend))
    assert np.abs(boxed.dkappa[:7]).max() <= radius * (1 + 1e-5)
    assert np.abs(boxed.dkappa[:7]).max() >= radius * (1 - 1e-4)  # it binds
    assert boxed.objective > free.objective
    # a radius larger than the free step changes nothing
    wide = build_inverse_qp(M_crit=M, err_crit=err * 50, trust_region=2 * np.abs(free.dkappa).max())
    np.testing.assert_allclose(
        require_solved(solve_qp(wide, backend)).dkappa, free.dkappa, atol=AGREE
    )


@pytest.mark.parametrize("bad", [0.0, -0.1, float("nan"), float("inf"), "0.1", True])
def test_bad_trust_region_raises_exact_message(bad):
    M, err, _ = _problem(0)
    with pytest.raises(ConfigError) as e:
        build_inverse_qp(M_crit=M, err_crit=err, trust_region=bad)
    assert str(e.value) == f"trust_region: must be a finite number > 0, got {bad!r}"


def test_a_command_within_the_whole_torque_but_not_the_links_torque_is_refused(
    robot: RobotModel,
):
    """The two torques part by the joints' damping and rotor inertia: limits that the whole
    torque keeps but the links' part breaks are broken (the simulated controller faults)."""
    from dataclasses import replace

    from learner.limit_rows import sampled_violation

    knots = _knots(amplitude=0.6, seed=0)
    rows = limit_rows(knots, T, T_SAMPLES, robot)
    whole = np.abs(rows.b[slice(*rows.blocks["tau"])]).reshape(-1, 7).max(axis=0)
    links = np.abs(rows.b[slice(*rows.blocks["tau_links"])]).reshape(-1, 7).max(axis=0)
    assert np.any(links > whole + 0.1)  # this command's links need more than the whole
    limits = replace(JointLimits(), tau_max=whole + 1e-6)
    assert sampled_violation(knots, T, T_SAMPLES, robot, limits) > 1e-3
    limits = replace(JointLimits(), tau_max=np.maximum(whole, links) + 1e-6)
    assert sampled_violation(knots, T, T_SAMPLES, robot, limits) == 0.0


def test_links_torque_rows_join_only_once_violated(robot: RobotModel):
    """With a margin > 0 the first solve holds no ``tau_links`` row, even one at its bound
    (so an update they do not bind is the one without them); with margin 0 it holds all."""
    from dataclasses import replace
    from types import SimpleNamespace

    from learner.limit_rows import generate_constraints

    knots = _knots(amplitude=0.6, seed=2)
    rows = limit_rows(knots, T, T_SAMPLES[::5], robot)
    a, z = rows.blocks["tau_links"]
    peak = np.abs(rows.b[a:z]).reshape(-1, 7).max(axis=0)
    near = replace(JointLimits(), tau_max=peak * 1.001)
    rows = limit_rows(knots, T, T_SAMPLES[::5], robot, near)
    seen = []

    def solve(lim):
        seen.append(lim.blocks)
        return SimpleNamespace(solved=False)

    generate_constraints(rows, solve, margin=0.9, max_rounds=3)
    first = seen.pop()
    assert first["tau_links"][1] == first["tau_links"][0]  # none of them
    assert first["tau"][1] > first["tau"][0]  # the whole torque's near rows are there
    generate_constraints(rows, solve, margin=0.0, max_rounds=3)
    assert dict(seen.pop()) == dict(rows.blocks)  # every row of every block


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_a_centred_control_term_is_the_distance_to_the_centre(seed: int):
    """center c: w_control ||x_arm - c_arm||^2 in place of w_control ||x_arm||^2; the base
    rows of c are ignored."""
    M, err, follow = _problem(seed)
    w = InverseModelWeights()
    rng = np.random.default_rng(seed + 2)
    c, x = rng.normal(size=80), rng.normal(size=80)
    qp = build_inverse_qp(M_crit=M, err_crit=err, weights=w, follow=follow, center=c)
    plain = _direct_cost(x, M, err, follow, w) - w.w_control * x[:56] @ x[:56]
    direct = plain + w.w_control * (x[:56] - c[:56]) @ (x[:56] - c[:56])
    assert qp.objective(x) == pytest.approx(direct, rel=1e-10, abs=1e-12)
    np.testing.assert_array_equal(qp.P.toarray(), build_inverse_qp(
        M_crit=M, err_crit=err, weights=w, follow=follow).P.toarray())  # fmt: skip


def test_a_centred_step_moves_toward_the_centre_where_the_model_cannot_see():
    """With fewer state rows than knots, the step toward a centre keeps the fitted state
    (M dk = err, as without a centre) and its difference from the plain step lies in M's null
    space, as near the centre as the rest rows allow."""
    rng = np.random.default_rng(7)
    M = np.zeros((6 * N_MARK, 80))
    M[:, :56] = rng.normal(size=(6 * N_MARK, 56))
    M[:36] = 0.0  # 30 state rows on the 42 arm directions the rest rows leave free
    x0 = rng.normal(size=(10, 8)) * 0.1
    x0[:, 1], x0[:, 6] = x0[:, 0], x0[:, 7]  # at rest at both ends
    err = M @ x0.ravel()
    w = InverseModelWeights(w_control=1e-6)
    c = np.zeros(80)
    c[:56] = rng.normal(size=56)
    plain = require_solved(
        solve_qp(build_inverse_qp(M_crit=M, err_crit=err, weights=w), "clarabel")
    )
    pulled = require_solved(
        solve_qp(build_inverse_qp(M_crit=M, err_crit=err, weights=w, center=c), "clarabel")
    )
    d = (pulled.dkappa - plain.dkappa).ravel()
    np.testing.assert_allclose(M @ pulled.dkappa.ravel(), err, atol=1e-3)
    assert np.linalg.norm(M @ d) < 1e-3 * np.linalg.norm(d)
    assert np.linalg.norm(d[:56]) > 0.1 * np.linalg.norm(c[:56])
    assert (pulled.dkappa.ravel()[:56] - c[:56]) @ (pulled.dkappa.ravel()[:56] - c[:56]) < (
        plain.dkappa.ravel()[:56] - c[:56]
    ) @ (plain.dkappa.ravel()[:56] - c[:56])


def test_a_bad_centre_raises_exact_messages():
    M, err, _ = _problem(1)
    with pytest.raises(ConfigError) as e:
        build_inverse_qp(M_crit=M, err_crit=err, center=np.zeros(79))
    assert str(e.value) == "center: must have 80 entries, got 79"
    with pytest.raises(ConfigError) as e:
        build_inverse_qp(M_crit=M, err_crit=err, center=np.full(80, np.nan))
    assert str(e.value) == "center: must be finite"

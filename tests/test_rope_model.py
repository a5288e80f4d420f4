"""The paper's 11-link rope model: parameters, energy, Newton step, rollout properties."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError, SolverError
from learner.rope_model import (
    RopeModelParams,
    RopeTrajectory,
    _StepSolver,
    bending_energy,
    constraints,
    hanging_state,
    link_vectors,
    rollout,
    rope_energy,
)

TIP = np.array([0.0, 0.0, 1.5])
DOWN = np.array([0.0, 0.0, -1.0])


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix, (3, 3)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _straight(tip: np.ndarray, d: np.ndarray, params: RopeModelParams) -> np.ndarray:
    return tip + params.link_length * np.arange(1, params.n_links + 1)[:, None] * d


def _motion(K: int, dt: float, seed: int = 0, scale: float = 1.0):
    """A smooth fingertip motion from rest: random cubic path, tube swinging about x and y."""
    rng = np.random.default_rng(seed)
    t = np.arange(K + 1) * dt
    Tm = max(t[-1], dt)
    s = 0.5 * (1.0 - np.cos(np.pi * t / Tm))  # starts and ends at rest
    a = rng.normal(size=(3, 3)) * 0.15 * scale
    p_tip = TIP + np.stack([a[i, 0] * s + a[i, 1] * s**2 + a[i, 2] * s**3 for i in range(3)], 1)
    ax, ay = rng.normal(size=2) * 0.8 * scale
    d = np.stack([np.sin(ay * s), -np.sin(ax * s) * np.cos(ay * s), -np.cos(ax * s)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return p_tip, d


# --- parameters ----------------------------------------------------------------------
def test_defaults_are_the_papers_table():
    p = RopeModelParams()
    assert (p.stiffness, p.damping, p.link_mass, p.end_mass) == (1e5, 50.0, 1.0, 5.0)
    assert (p.link_length, p.n_links, p.dt, p.gravity) == (0.1, 11, 0.005, 9.81)
    np.testing.assert_array_equal(p.masses, [1.0] * 10 + [5.0])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stiffness": -1.0}, "stiffness: must be a finite number >= 0, got -1.0"),
        ({"damping": float("nan")}, "damping: must be a finite number >= 0, got nan"),
        ({"dt": 0}, "dt: must be a finite number > 0, got 0.0"),
        ({"end_mass": "5"}, "end_mass: must be a finite number > 0, got '5'"),
        ({"n_links": 0}, "n_links: must be an integer >= 1, got 0"),
        ({"n_links": 2.5}, "n_links: must be an integer >= 1, got 2.5"),
    ],
)
def test_param_validation_messages(kwargs, message):
    with pytest.raises(ConfigError) as e:
        RopeModelParams(**kwargs)
    assert str(e.value) == message


# --- energy ----------------------------------------------------------------------------
def test_bending_energy_zero_when_straight_and_angle_form():
    params = RopeModelParams()
    d = np.array([0.6, 0.0, -0.8])
    assert bending_energy(_straight(TIP, d, params), TIP, d, params) == pytest.approx(0, abs=1e-12)
    # Bend only the fingertip joint by theta: E = k (1 - cos theta).
    theta = 0.3
    p = _straight(TIP, _rot([0, 1, 0], theta) @ d, params)
    want = params.stiffness * (1 - np.cos(theta))
    assert bending_energy(p, TIP, d, params) == pytest.approx(want, rel=1e-12)


@settings(max_examples=30, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.floats(-np.pi, np.pi),
    shift=st.tuples(*[st.floats(-2, 2) for _ in range(3)]),
    seed=st.integers(0, 1000),
)
def test_bending_energy_invariant_to_rigid_motions(axis, angle, shift, seed):
    params = RopeModelParams(stiffness=3.0)
    rng = np.random.default_rng(seed)
    p = TIP + np.cumsum(rng.normal(size=(11, 3)) * 0.1, axis=0)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    R = _rot(axis, angle)
    e0 = bending_energy(p, TIP, d, params)
    e1 = bending_energy(p @ R.T + shift, R @ TIP + shift, R @ d, params)
    assert e1 == pytest.approx(e0, rel=1e-10)


# --- the Newton step ---------------------------------------------------------------------
def test_kkt_matrix_matches_finite_differences_of_residual():
    params = RopeModelParams(stiffness=7.0, damping=0.3)
    solver = _StepSolver(params, 1e-10, 25)
    rng = np.random.default_rng(3)
    n = params.n_links
    p_k = _straight(TIP, DOWN, params) + rng.normal(size=(n, 3)) * 0.01
    v_k = rng.normal(size=(n, 3))
    A_k = np.stack([TIP - 0.1 * DOWN, TIP])
    A_next = A_k + rng.normal(size=(2, 3)) * 0.01
    c = solver.constant(p_k, v_k, A_k, A_next)
    p = p_k + rng.normal(size=(n, 3)) * 0.01
    mu = rng.normal(size=n) * 1e-3
    z = np.concatenate([p.ravel(), mu])

    def res(z):
        r1, r2 = solver.residual(z[: 3 * n].reshape(n, 3), z[3 * n :], c, A_next[1])
        return np.concatenate([r1.ravel(), r2])

    h = 1e-6
    fd = np.stack([(res(z + h * e) - res(z - h * e)) / (2 * h) for e in np.eye(4 * n)], axis=1)
    J = solver.kkt(p, mu, A_next[1]).copy()
    assert np.max(np.abs(J - fd)) / np.max(np.abs(J)) < 1e-8


def test_constraints_hold_after_every_step_and_newton_is_fast():
    params = RopeModelParams()
    p_tip, d_tip = _motion(160, params.dt, seed=1, scale=2.0)
    tr = rollout(p_tip, d_tip, params)
    assert isinstance(tr, RopeTrajectory)
    assert tr.p.shape == (161, 11, 3) and tr.v.shape == (161, 11, 3) and tr.lam.shape == (161, 11)
    lengths = np.linalg.norm(
        np.stack([link_vectors(p, t) for p, t in zip(tr.p, p_tip, strict=True)]), axis=2
    )
    assert np.max(np.abs(lengths - params.link_length)) < 1e-9
    assert np.max(tr.iterations) <= 4
    assert np.mean(tr.iterations) <= 3.0
    # v is the backward difference of p (paper eq. rope_vi_pos).
    np.testing.assert_allclose(tr.v[1:], np.diff(tr.p, axis=0) / params.dt, atol=1e-9)
    np.testing.assert_array_equal(tr.lam[0], 0.0)


def test_step_satisfies_the_papers_equations():
    """Residuals of eq. rope_vi_dyn / rope_vi_con evaluated independently of the solver."""
    params = RopeModelParams(stiffness=20.0, damping=2.0)
    p_tip, d_tip = _motion(20, params.dt, seed=4)
    tr = rollout(p_tip, d_tip, params)
    k, ell, dt, n = params.stiffness, params.link_length, params.dt, params.n_links
    m = params.masses[:, None]
    for i in range(20):
        P1 = np.vstack([p_tip[i + 1] - ell * d_tip[i + 1], p_tip[i + 1], tr.p[i + 1]])
        P0 = np.vstack([p_tip[i] - ell * d_tip[i], p_tip[i], tr.p[i]])
        V = (P1 - P0) / dt
        V[2:] = tr.v[i + 1]
        e = P1[2:] - 2 * P1[1:-1] + P1[:-2]
        ed = V[2:] - 2 * V[1:-1] + V[:-2]
        # Force on point j from e_j, e_{j+1}, e_{j+2}: -(k/l^2) (D^T e) on the free points.
        f = np.zeros((n + 2, 3))
        for j in range(n):
            for off, w in ((0, 1.0), (1, -2.0), (2, 1.0)):
                f[j + off] -= w * (k * e[j] + params.damping * ed[j]) / ell**2
        f = f[2:] + m * np.array([0, 0, -params.gravity])
        dvec = link_vectors(tr.p[i + 1], p_tip[i + 1])
        GTlam = 2 * dvec * tr.lam[i + 1][:, None]
        GTlam[:-1] -= 2 * dvec[1:] * tr.lam[i + 1][1:, None]
        r = m * (tr.v[i + 1] - tr.v[i]) - dt * f - dt * GTlam
        assert np.max(np.abs(r)) < 1e-6  # [N s], forces here are ~1e2 N
        assert np.max(np.abs(constraints(tr.p[i + 1], p_tip[i + 1], params))) < 1e-10


# --- physical properties -------------------------------------------------------------------
def test_hanging_rope_stays_put_with_the_tension_of_the_weight_below():
    params = RopeModelParams()
    p0, v0 = hanging_state(TIP, DOWN, params)
    np.testing.assert_allclose(p0, _straight(TIP, DOWN, params), atol=1e-15)
    assert not v0.any()
    K = 100
    tr = rollout(np.tile(TIP, (K + 1, 1)), np.tile(DOWN, (K + 1, 1)), params)
    assert np.max(np.abs(tr.p - p0)) < 1e-12
    assert np.max(np.abs(tr.v)) < 1e-9
    # Tension of link j carries the weight of points j..N: lam_j = -g sum_{i>=j} m_i / (2 l).
    want = -params.gravity * np.cumsum(params.masses[::-1])[::-1] / (2 * params.link_length)
    np.testing.assert_allclose(tr.lam[1:], np.tile(want, (K, 1)), rtol=1e-9)


@pytest.mark.parametrize("stiffness", [0.0, 1.0, 1e5])
def test_hanging_state_is_static_for_any_tube_direction(stiffness):
    params = RopeModelParams(stiffness=stiffness)
    d = np.array([0.0, 0.6, 0.8])  # tube pointing up and sideways
    p0, _ = hanging_state(TIP, d, params)
    assert np.max(np.abs(constraints(p0, TIP, params))) < 1e-10
    tr = rollout(np.tile(TIP, (21, 1)), np.tile(d, (21, 1)), params, p0=p0)
    assert np.max(np.abs(tr.p - p0)) < 1e-8
    if stiffness == 0.0:  # a chain hangs straight down whatever the tube does
        np.testing.assert_allclose(p0, _straight(TIP, DOWN, params), atol=1e-8)


def test_energy_decays_and_damping_dissipates_more():
    tip_d = np.tile(DOWN, (201, 1))
    tips = np.tile(TIP, (201, 1))
    ends = []
    for b in (0.0, 1.0):
        params = RopeModelParams(stiffness=10.0, damping=b)
        p0 = _straight(TIP, _rot([1, 0, 0], np.deg2rad(40)) @ DOWN, params)
        tr = rollout(tips, tip_d, params, p0=p0)
        E = np.array(
            [rope_energy(p, v, TIP, DOWN, params) for p, v in zip(tr.p, tr.v, strict=True)]
        )
        assert np.all(np.diff(E) <= 1e-9)
        ends.append(E[-1])
    assert ends[1] < ends[0] - 1.0


@pytest.mark.parametrize("length", [0.1, 0.5])
def test_small_pendulum_period(length):
    params = RopeModelParams(stiffness=0.0, damping=0.0, n_links=1, link_length=length)
    theta = np.deg2rad(5.0)
    p0 = TIP + length * np.array([[np.sin(theta), 0.0, -np.cos(theta)]])
    period = 2 * np.pi * np.sqrt(length / params.gravity)
    K = int(3.2 * period / params.dt)
    tr = rollout(np.tile(TIP, (K + 1, 1)), np.tile(DOWN, (K + 1, 1)), params, p0=p0)
    x, t = tr.p[:, 0, 0], tr.t
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    crossings = t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])
    assert len(crossings) >= 2
    assert np.mean(np.diff(crossings)) == pytest.approx(period, rel=0.02)


@settings(max_examples=8, deadline=None)
@given(angle=st.floats(-np.pi, np.pi), seed=st.integers(0, 100))
def test_rollout_commutes_with_rotations_about_gravity(angle, seed):
    params = RopeModelParams(stiffness=50.0, damping=1.0)
    p_tip, d_tip = _motion(25, params.dt, seed=seed)
    R = _rot([0, 0, 1], angle)
    tr = rollout(p_tip, d_tip, params)
    tr_r = rollout(p_tip @ R.T, d_tip @ R.T, params)
    np.testing.assert_allclose(tr_r.p, tr.p @ R.T, atol=1e-9)
    # multipliers converge to ~1e-6 with the 1e-10 m Newton tolerance on positions
    np.testing.assert_allclose(tr_r.lam, tr.lam, rtol=1e-5, atol=1e-5)


# --- errors ----------------------------------------------------------------------------
def test_rollout_validation_messages():
    params = RopeModelParams()
    tips = np.tile(TIP, (5, 1))
    with pytest.raises(ConfigError) as e:
        rollout(tips, np.tile([0.0, 0.0, -2.0], (5, 1)), params)
    assert str(e.value) == "d_tip: must be unit vectors (within 0.001), got norms in [2, 2]"
    with pytest.raises(ConfigError) as e:
        rollout(tips, np.tile(DOWN, (4, 1)), params)
    assert str(e.value) == "d_tip: must have the shape of p_tip (5, 3), got (4, 3)"
    with pytest.raises(ConfigError) as e:
        rollout(tips, np.tile(DOWN, (5, 1)), params, p0=np.zeros((10, 3)))
    assert str(e.value) == "p0: must have shape (11, 3), got (10, 3)"
    with pytest.raises(ConfigError) as e:
        rollout(tips, np.tile(DOWN, (5, 1)), params, max_iter=0)
    assert str(e.value) == "max_iter: must be an integer >= 1, got 0"


def test_newton_failure_raises_solver_error_with_status():
    params = RopeModelParams()
    p_tip, d_tip = _motion(10, params.dt, seed=2, scale=3.0)
    with pytest.raises(SolverError) as e:
        rollout(p_tip, d_tip, params, max_iter=1)
    assert e.value.status == "max_iter"
    assert str(e.value).startswith("rope Newton failed with status 'max_iter': step 0: residual ")


def test_trajectory_is_frozen():
    params = RopeModelParams()
    tr = rollout(np.tile(TIP, (3, 1)), np.tile(DOWN, (3, 1)), params)
    with pytest.raises(dataclasses.FrozenInstanceError):
        tr.p = tr.p  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        tr.p[0, 0, 0] = 1.0
    assert tr.x.shape == (3, 66)

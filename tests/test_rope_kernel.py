"""The compiled Newton step of the learner's rope model against its NumPy reference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_rope_model import _motion

from flyknot.errors import SolverError
from learner import rope_model
from learner.rope_model import RopeModelParams, _StepSolver, rollout


def _numpy_rollout(monkeypatch, *args, **kw):
    with monkeypatch.context() as mp:
        mp.setattr(_StepSolver, "compiled", False)
        return rollout(*args, **kw)


@given(st.integers(0, 500), st.sampled_from([(1e5, 50.0), (100.0, 0.5), (1e3, 5.0)]))
@settings(max_examples=12, deadline=None)
def test_every_step_matches_the_numpy_iteration(seed, model):
    params = RopeModelParams(stiffness=model[0], damping=model[1])
    p_tip, d_tip = _motion(60, params.dt, seed=seed, scale=1.5)
    tr = rollout(p_tip, d_tip, params)
    solver = _StepSolver(params, rope_model.NEWTON_TOL, rope_model.NEWTON_MAX_ITER)
    reference = _StepSolver(params, rope_model.NEWTON_TOL, rope_model.NEWTON_MAX_ITER)
    reference.compiled = False
    A = rope_model._anchor(p_tip, d_tip, params.link_length)
    mu = tr.lam * (2 * params.link_length * params.dt**2)
    for k in range(0, 60, 7):
        args = (k, tr.p[k], tr.v[k], A[k], A[k + 1], mu[k])
        p1, mu1, it1 = solver.solve(*args)
        p2, mu2, it2 = reference.solve(*args)
        assert it1 == it2
        np.testing.assert_allclose(p1, p2, rtol=0, atol=1e-12)
        # the multipliers to the Newton tolerance itself (1e-10 m, scaled)
        np.testing.assert_allclose(mu1, mu2, rtol=0, atol=rope_model.NEWTON_TOL)


def test_a_rollout_matches_the_numpy_rollout(monkeypatch):
    params = RopeModelParams()
    p_tip, d_tip = _motion(300, params.dt, seed=4, scale=2.0)
    fast = rollout(p_tip, d_tip, params)
    ref = _numpy_rollout(monkeypatch, p_tip, d_tip, params)
    np.testing.assert_array_equal(fast.iterations, ref.iterations)
    np.testing.assert_allclose(fast.p, ref.p, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast.lam, ref.lam, rtol=0, atol=1e-6 * np.abs(ref.lam).max())


def test_a_failed_step_raises_the_numpy_paths_error(monkeypatch):
    params = RopeModelParams()
    p_tip, d_tip = _motion(10, params.dt, seed=2, scale=3.0)
    with pytest.raises(SolverError) as fast:
        rollout(p_tip, d_tip, params, max_iter=1)
    with pytest.raises(SolverError) as ref:
        _numpy_rollout(monkeypatch, p_tip, d_tip, params, max_iter=1)
    assert str(fast.value) == str(ref.value) and fast.value.status == "max_iter"
    solver = _StepSolver(params, 1e-10, 25)
    A = rope_model._anchor(p_tip, d_tip, params.link_length)
    nan = np.full((params.n_links, 3), np.nan)
    with pytest.raises(SolverError) as e:
        solver.solve(3, nan, np.zeros_like(nan), A[3], A[4], np.zeros(params.n_links))
    assert e.value.status == "non-finite"
    assert str(e.value) == "rope Newton failed with status 'non-finite': step 3, iteration 0"


@given(st.integers(0, 10_000), st.integers(1, 12))
@settings(max_examples=30, deadline=None)
def test_the_compiled_kkt_matrix_is_the_numpy_one_bit_for_bit(seed, n):
    from learner.rope_kernel import kkt_into

    params = RopeModelParams(n_links=n, stiffness=1e3, damping=5.0)
    rng = np.random.default_rng(seed)
    p, mu, tip = rng.normal(size=(n, 3)), rng.normal(size=n), rng.normal(size=3)
    solver = _StepSolver(params, 1e-10, 25)
    K, dvec = np.zeros((4 * n, 4 * n)), np.empty((n, 3))
    kkt_into(p, mu, tip, solver.ops.H0, params.link_length, K, dvec)
    np.testing.assert_array_equal(K, solver.kkt(p, mu, tip))


def test_compiled_sensitivity_matches_the_numpy_propagation(monkeypatch):
    from learner import rope_sensitivity
    from learner.rope_sensitivity import state_sensitivity

    params = RopeModelParams()
    p_tip, d_tip = _motion(80, params.dt, seed=7, scale=1.5)
    tr = rollout(p_tip, d_tip, params)
    dU = np.random.default_rng(1).normal(size=(81, 6, 9))
    steps = [0, 17, 40, 80]
    fast = state_sensitivity(tr, dU, steps=steps)
    monkeypatch.setattr(rope_sensitivity, "COMPILED", False)
    ref = state_sensitivity(tr, dU, steps=steps)
    np.testing.assert_array_equal(fast[0], 0.0)
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())

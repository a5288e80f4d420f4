"""The limits a command may use, and the derivatives they apply to, as every cell checks them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flyknot.errors import ConfigError
from flyknot.limits import (
    JointLimits,
    central_differences,
    command_derivatives,
    difference_matrices,
)
from flyknot.record import JointCommand
from flyknot_hw.config import Margins
from flyknot_hw.preflight import PreflightError, effective_limits, preflight
from learner.bezier import BezierCommand, basis_jacobian, controller_basis, controller_jacobian

DT = 0.004


def test_difference_matrices_are_the_central_differences_with_rest_padding():
    d1, d2 = difference_matrices(4, 0.5)
    np.testing.assert_array_equal(
        d1, [[-1, 1, 0, 0], [-1, 0, 1, 0], [0, -1, 0, 1], [0, 0, -1, 1]]
    )  # [1/s]: (q_{i+1} - q_{i-1}) / (2 dt), q_{-1} = q_0, q_4 = q_3
    np.testing.assert_array_equal(
        d2, 4 * np.array([[-1, 1, 0, 0], [1, -2, 1, 0], [0, 1, -2, 1], [0, 0, 1, -1]])
    )
    assert difference_matrices(1, 0.5)[1].tolist() == [[0.0]]
    with pytest.raises(ConfigError) as e:
        difference_matrices(0, 0.5)
    assert str(e.value) == "n: must be an integer >= 1, got 0"
    with pytest.raises(ConfigError, match=r"^dt: "):
        difference_matrices(3, 0.0)


def test_controller_basis_gives_what_the_controllers_compute():
    rng = np.random.default_rng(2)
    knots = rng.normal(size=(10, 8))
    knots[:, 1], knots[:, 6] = knots[:, 0], knots[:, 7]  # at rest at both ends
    knots[7:] = 0.3  # a constant base offset
    command = BezierCommand(knots, 0.61)
    t = command.sample_times()
    q = command.joint_command().q
    qd, qdd = command_derivatives(q, DT)
    np.testing.assert_allclose(controller_basis(t, 0.61, 0) @ knots[:7].T, q, atol=1e-12)
    np.testing.assert_allclose(controller_basis(t, 0.61, 1) @ knots[:7].T, qd, atol=1e-9)
    np.testing.assert_allclose(controller_basis(t, 0.61, 2) @ knots[:7].T, qdd, atol=1e-6)
    with pytest.raises(ConfigError) as e:
        controller_basis(np.array([0.0, 0.1, 0.3]), 0.61, 1)
    assert str(e.value) == "t: must be a uniform grid of sample times from 0 (a command's)"


def test_controller_jacobian_is_the_bases_jacobian_kept_per_grid():
    t = BezierCommand(np.zeros((10, 8)), 0.61).sample_times()
    for r in (0, 1, 2):
        jac = controller_jacobian(t, 0.61, r)
        assert np.array_equal(jac, basis_jacobian(controller_basis(t, 0.61, r)))
        assert not jac.flags.writeable
        assert controller_jacobian(t.copy(), 0.61, r) is jac  # kept, not rebuilt
    assert controller_jacobian(t, 0.62, 1) is not controller_jacobian(t, 0.61, 1)
    with pytest.raises(ConfigError) as e:
        controller_jacobian(np.array([0.0, 0.1, 0.3]), 0.61, 1)
    assert str(e.value) == "t: must be a uniform grid of sample times from 0 (a command's)"


def test_margins_shrink_every_limit_as_the_preflight_counts_them():
    lim = JointLimits()
    m = lim.with_margins(position=0.1, velocity=0.05, acceleration=0.2, torque=0.5)
    np.testing.assert_allclose(m.qd_max, 0.95 * lim.qd_max)
    np.testing.assert_allclose(m.qdd_max, 0.8 * lim.qdd_max)
    np.testing.assert_allclose(m.tau_max, 0.5 * lim.tau_max)
    np.testing.assert_allclose(m.q_max - m.q_min, 0.9 * (lim.q_max - lim.q_min))
    np.testing.assert_allclose(m.q_max + m.q_min, lim.q_max + lim.q_min)
    for name in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max"):
        np.testing.assert_allclose(getattr(lim.with_margins(), name), getattr(lim, name))
    with pytest.raises(ConfigError) as e:
        lim.with_margins(velocity=1.0)
    assert str(e.value) == "margin.velocity: must lie in [0, 1), got 1.0"


@settings(max_examples=30, deadline=None)
@given(use=st.floats(0.2, 1.2), joint=st.integers(0, 6), margin=st.sampled_from([0.0, 0.05, 0.2]))
def test_a_command_within_the_margined_limits_passes_the_preflight(use, joint, margin):
    """A joint swung so that its peak velocity (as the controllers difference it) is ``use``
    of the margined limit: the preflight refuses it exactly when use > 1."""
    margins = Margins(position=0.0, velocity=margin, acceleration=0.0, torque=0.0)
    allowed = margins.apply(effective_limits())
    t = DT * np.arange(500)
    q = np.zeros((t.size, 7))
    q[:, joint] = 1.0 - np.cos(2 * np.pi * t / 2.0)  # at rest at both ends
    peak = np.abs(command_derivatives(q, DT)[0][:, joint]).max()
    q[:, joint] *= use * allowed.qd_max[joint] / peak
    q[:, 3] += 1.0  # joint 4 inside its range
    command = JointCommand(q, rate_hz=1 / DT)
    if use <= 1.0 - 1e-9:
        preflight(command, effective_limits(), margins=margins)
    elif use > 1.0 + 1e-9:
        with pytest.raises(PreflightError, match=f"joint {joint + 1} velocity"):
            preflight(command, effective_limits(), margins=margins)


def test_central_differences_are_the_difference_matrices_on_any_width():
    x = np.random.default_rng(4).normal(size=(9, 3))  # e.g. fingertip positions
    d1, d2 = difference_matrices(9, DT)
    v, a = central_differences(x, DT)
    np.testing.assert_allclose(v, d1 @ x, rtol=0, atol=1e-9 * np.abs(v).max())
    np.testing.assert_allclose(a, d2 @ x, rtol=0, atol=1e-9 * np.abs(a).max())

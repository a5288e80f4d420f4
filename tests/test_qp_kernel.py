"""The update's fast paths give the slow paths' numbers bit for bit.

The learner's output feeds a chaotic lab whose records the tests hold bit for bit
(``tests/test_lab_fingerprint.py``), so the compiled follow-through sums, the direct CSC
construction and the caches must not change a single bit of what they replace.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from flyknot.errors import ConfigError
from learner.bezier import controller_basis
from learner.inverse_qp import dense_csc
from learner.qp_kernel import weighted_gram, weighted_rhs

_VALUES = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False, width=64)


@st.composite
def follow_terms(draw):
    """Rows J (k, m, n) with some zero columns and rows, weights W >= 0 and errors e."""
    k, m, n = draw(st.integers(1, 12)), draw(st.integers(1, 9)), draw(st.integers(1, 20))
    J = draw(arrays(float, (k, m, n), elements=_VALUES))
    J[:, :, draw(st.integers(0, n)) :] = 0.0  # the Bezier basis leaves late knots untouched
    W = draw(arrays(float, (k, m), elements=st.floats(0.0, 1e3, width=64)))
    e = draw(arrays(float, (k, m), elements=_VALUES))
    return J, W, e


@settings(max_examples=200, deadline=None)
@given(follow_terms())
def test_the_follow_through_sums_are_the_einsums_bit_for_bit(terms):
    J, W, e = terms
    np.testing.assert_array_equal(weighted_gram(J, W), np.einsum("tic,ti,tid->cd", J, W, J))
    np.testing.assert_array_equal(weighted_rhs(J, W, e), np.einsum("tic,ti,ti->c", J, W, e))


def test_the_follow_through_sums_on_a_realistic_size():
    rng = np.random.default_rng(7)
    J, W = rng.standard_normal((90, 9, 80)), rng.random((90, 9))
    e = rng.standard_normal((90, 9))
    assert np.array_equal(weighted_gram(J, W), np.einsum("tic,ti,tid->cd", J, W, J))
    assert np.array_equal(weighted_rhs(J, W, e), np.einsum("tic,ti,ti->c", J, W, e))
    # the order matters: BLAS's differs in the last bits, which is why the kernel exists
    A = J.reshape(-1, 80)
    assert not np.array_equal(A.T @ (W.reshape(-1, 1) * A), weighted_gram(J, W))


@settings(max_examples=200, deadline=None)
@given(
    st.tuples(st.integers(1, 30), st.integers(1, 12)).flatmap(
        lambda shape: arrays(
            float,
            shape,
            elements=st.one_of(st.just(0.0), st.just(-0.0), _VALUES, st.just(np.nan)),
        )
    )
)
def test_dense_csc_is_scipys_csc(D):
    mine, theirs = dense_csc(D), sp.csc_matrix(D)
    assert mine.shape == theirs.shape
    np.testing.assert_array_equal(mine.indptr, theirs.indptr)
    np.testing.assert_array_equal(mine.indices, theirs.indices)
    np.testing.assert_array_equal(mine.data, theirs.data)
    assert mine.has_canonical_format


def test_controller_basis_is_kept_per_grid_and_read_only():
    t = np.arange(200) / 250.0
    first = controller_basis(t, 0.8, 2)
    again = controller_basis(t.copy(), 0.8, 2)
    assert again is first
    assert not first.flags.writeable
    other = controller_basis(t, 0.9, 2)
    assert other is not first and not np.array_equal(other, first)
    with pytest.raises(ConfigError) as err:
        controller_basis(t, -1.0, 1)
    assert err.value.field == "T"

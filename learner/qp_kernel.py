"""The follow-through sums of the inverse-model QP, compiled (numba).

The follow-through term adds ``sum_t J_t^T W_t J_t`` to the QP's Hessian and
``sum_t J_t^T W_t e_t`` to its gradient (:func:`learner.inverse_qp.build_inverse_qp`), over
~100 samples t of 9 rows and 80 columns. NumPy's three-operand ``einsum`` forms them in a
plain nested loop (~5 ms, most of a QP build); BLAS would be faster still but sums in another
order, and the learner's output feeds a chaotic lab whose records the tests hold bit for bit.
These kernels run the ``einsum``'s arithmetic in its order: for each output entry the terms
``(J[t, i, c] * W[t, i]) * J[t, i, d]`` are added one by one, t outer, i inner, starting from
0.0, so the result is the ``einsum``'s exactly (``tests/test_qp_kernel.py``).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["weighted_gram", "weighted_rhs"]


@numba.njit(cache=True)
def weighted_gram(J: np.ndarray, W: np.ndarray) -> np.ndarray:
    """H = sum_t sum_i W[t, i] J[t, i, :]^T J[t, i, :], shape (n, n).

    Args:
        J: Rows, shape (k, m, n) (k samples of m rows over n columns).
        W: Row weights, shape (k, m).

    Returns:
        ``np.einsum("tic,ti,tid->cd", J, W, J)``, bit for bit.
    """
    k, m, n = J.shape
    H = np.zeros((n, n))
    for t in range(k):
        for i in range(m):
            w = W[t, i]
            for c in range(n):
                a = J[t, i, c] * w
                for d in range(n):
                    H[c, d] += a * J[t, i, d]
    return H


@numba.njit(cache=True)
def weighted_rhs(J: np.ndarray, W: np.ndarray, e: np.ndarray) -> np.ndarray:
    """g = sum_t sum_i W[t, i] e[t, i] J[t, i, :], shape (n,).

    Args:
        J: Rows, shape (k, m, n).
        W: Row weights, shape (k, m).
        e: Row errors, shape (k, m).

    Returns:
        ``np.einsum("tic,ti,ti->c", J, W, e)``, bit for bit.
    """
    k, m, n = J.shape
    g = np.zeros(n)
    for t in range(k):
        for i in range(m):
            w, r = W[t, i], e[t, i]
            for c in range(n):
                g[c] += J[t, i, c] * w * r
    return g

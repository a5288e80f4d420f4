"""Solve the inverse-model QP built by :func:`learner.inverse_qp.build_inverse_qp`: Clarabel
(the default, the paper's solver) or OSQP, one :class:`QPResult` either way."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from flyknot.constants import N_KNOTS, N_ROWS
from flyknot.errors import ConfigError, SolverError, check_choice
from flyknot.geometry import readonly
from learner.inverse_qp import QPData, dense_csc

BACKENDS = ("osqp", "clarabel")

# OSQP: ADMM to 1e-6, then polishing (an equality-constrained solve on the guessed active set)
# makes the answer exact; 10 refinement steps let polishing succeed on the ill-conditioned
# torque rows. Measured (tests/test_inverse_qp.py problems): eps 1e-8 returned the same polished
# answer with 2-3x the iterations; eps 1e-5 let polishing pick a wrong active set (5e-3 off).
_OSQP_DEFAULTS = {
    "verbose": False,
    "polishing": True,
    "polish_refine_iter": 10,
    "eps_abs": 1e-6,
    "eps_rel": 1e-6,
    "max_iter": 20000,
}


@dataclass(frozen=True)
class QPResult:
    """Outcome of :func:`solve_qp`.

    Attributes:
        dkappa: Knot update (10, 8), to be *subtracted* from the knots; all NaN unless solved.
        status: The solver's own status text (OSQP: ``"solved"``, ``"primal infeasible"``, ...;
            Clarabel: ``"Solved"``, ``"PrimalInfeasible"``, ...).
        solved: True only for a converged, feasible solution.
        objective: Full QP cost at ``dkappa`` (NaN unless solved).
        solve_time: Wall time of setup and solve [s].
        backend: ``"osqp"`` or ``"clarabel"``.
        iterations: Solver iterations.
    """

    dkappa: np.ndarray
    status: str
    solved: bool
    objective: float
    solve_time: float
    backend: str
    iterations: int


def _solve_osqp(qp: QPData, settings: dict) -> tuple[np.ndarray | None, str, bool, int]:
    import osqp

    opts = {**_OSQP_DEFAULTS, **settings}
    solver = osqp.OSQP()
    try:
        solver.setup(sp.triu(qp.P, format="csc"), qp.q, qp.A, qp.l, qp.u, **opts)
    except (TypeError, ValueError) as exc:
        raise ConfigError("settings", f"OSQP rejected the settings: {exc}") from exc
    res = solver.solve(raise_error=False)
    status = str(res.info.status)
    return res.x, status, status == "solved", int(res.info.iter)


def _clarabel_form(qp: QPData) -> tuple[sp.csc_matrix, np.ndarray, int, int]:
    """Two-sided rows as Clarabel cones, ``A_c x + s = b_c``.

    Rows with ``l == u`` go to the zero cone (``A x = u``); finite upper bounds give
    ``A x + s = u, s >= 0``; finite lower bounds give ``-A x + s = -l, s >= 0``.

    Returns:
        ``A_c``, ``b_c``, number of zero-cone rows, number of nonnegative-cone rows.
    """
    lb, ub = qp.l, qp.u
    eq = np.flatnonzero(lb == ub)
    up = np.flatnonzero((lb != ub) & np.isfinite(ub))
    lo = np.flatnonzero((lb != ub) & np.isfinite(lb))
    A = qp.A.toarray()  # (m, 80): row selection is cheaper dense than sparse
    A_c = dense_csc(np.vstack([A[eq], A[up], -A[lo]]))
    b_c = np.concatenate([ub[eq], ub[up], -lb[lo]])
    return A_c, b_c, eq.size, up.size + lo.size


def _solve_clarabel(qp: QPData, settings: dict) -> tuple[np.ndarray | None, str, bool, int]:
    import clarabel

    opts = clarabel.DefaultSettings()
    opts.verbose = False
    for key, value in settings.items():
        if not hasattr(opts, key):
            raise ConfigError("settings", f"unknown Clarabel setting {key!r}")
        setattr(opts, key, value)
    A_c, b_c, n_eq, n_ineq = _clarabel_form(qp)
    cones = []
    if n_eq:
        cones.append(clarabel.ZeroConeT(n_eq))
    if n_ineq:
        cones.append(clarabel.NonnegativeConeT(n_ineq))
    P_upper = dense_csc(np.triu(qp.P.toarray()))
    solver = clarabel.DefaultSolver(P_upper, qp.q, A_c, b_c, cones, opts)
    sol = solver.solve()
    status = str(sol.status)
    return np.asarray(sol.x), status, status == "Solved", int(sol.iterations)


def solve_qp(qp: QPData, backend: str = "clarabel", **settings: object) -> QPResult:
    """Solve a :class:`QPData` with Clarabel (default, the paper's solver) or OSQP.

    Clarabel runs with its default interior-point tolerances (1e-8); it needs ~15-20 iterations
    whatever the active set. OSQP runs with ``eps_abs = eps_rel = 1e-6`` and polishing unless
    overridden; it is fast while few limits bind but needs thousands of ADMM iterations (and
    may stop at ``max_iter`` = 20000, reported as not solved) when many torque/velocity rows
    bind on a badly conditioned P. Extra keyword arguments go to the solver's settings.

    Args:
        qp: The problem.
        backend: ``"osqp"`` or ``"clarabel"``.
        **settings: Solver settings.

    Returns:
        The result; ``solved`` is False (and ``dkappa`` NaN) for any status other than
        converged-and-feasible, with the solver's status kept.

    Raises:
        ConfigError: Unknown backend or setting.
    """
    check_choice("backend", backend, BACKENDS)
    t0 = time.perf_counter()
    if backend == "osqp":
        x, status, solved, iters = _solve_osqp(qp, settings)
    else:
        x, status, solved, iters = _solve_clarabel(qp, settings)
    elapsed = time.perf_counter() - t0
    if solved and x is not None and np.all(np.isfinite(x)):
        x = np.asarray(x, dtype=float)
        objective = qp.objective(x)
    else:
        solved = False
        x = np.full(qp.n, np.nan)
        objective = float("nan")
    return QPResult(
        dkappa=readonly(x.reshape(N_ROWS, N_KNOTS)),
        status=status,
        solved=solved,
        objective=objective,
        solve_time=elapsed,
        backend=backend,
        iterations=iters,
    )


def require_solved(result: QPResult) -> QPResult:
    """Return ``result`` if it is solved.

    Raises:
        SolverError: With the solver's status when it is not.
    """
    if not result.solved:
        raise SolverError(result.backend, result.status)
    return result


__all__ = ["BACKENDS", "QPResult", "require_solved", "solve_qp"]

"""The initial command kappa_0: trajectory optimisation tracking the demonstration hand.

Paper, section "Initial Guess" (eq. ik_trajopt) and appendix "Demonstration Tracking". The
problem (cost, limits, decision vector, structured derivatives) is stated and built in
:mod:`learner.initial_guess_problem`; :func:`initial_guess` builds it and solves it here
(:func:`solve_problem`), then checks the command (:func:`tracking_errors`,
:func:`check_command`).

Solver: CasADi + IPOPT (MUMPS, default options; the paper used SNOPT through Drake). IPOPT gets
exact first and second derivatives assembled from per-sample ones
(:func:`learner.initial_guess_problem.build_problem`): CasADi's own Hessian through all samples
at once needs 45 directional sweeps and was 2-3x slower on the reference motion. Measured there
(T = 0.715 s, 144 demo samples at 200 Hz, 180 limit samples, 2 shared cores): ~33-45 iterations,
3-6 s; ~75 % of it the torque rows' Hessian (torque_limits=False: 1.5 s). A coarser cost grid
hardly helps because the 250 Hz torque rows dominate: 200 / 100 / 50 / 25 Hz gave 3.3 / 3.0 /
3.3 / 6.3 s with tracking errors on the 200 Hz demo within 4 % of each other, so the default
keeps the demonstration's samples. The problem is non-convex: other seeds can reach other local
minima (62.6 vs 67.5 on the reference motion with joint 1 or 7 of the seed moved). Seed: every
knot at ``q_seed`` (default the xArm home) and b such that FK(q_seed) + b = p_h(t_0), so the
seed tracks the first sample exactly and stands still. A failed solve is reported through
``status``/``success``; only :func:`require_success` raises.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from flyknot.constants import N_JOINTS, N_ROWS
from flyknot.errors import SolverError
from flyknot.geometry import readonly
from learner.bezier import BezierCommand, bernstein_basis, controller_basis
from learner.initial_guess_params import (
    COST_TERMS,
    InitialGuessParams,
    knots_from_x,
    limit_sample_times,
    rotation_log,
)
from learner.initial_guess_problem import InitialGuessProblem, build_problem

if TYPE_CHECKING:
    from learner.kinematics import RobotModel

Z_TOL = 1e-6  # [m] IPOPT's tolerance on the z_min row when judging feasibility
ACTIVE_RTOL = 1e-3  # a limit row counts as binding within this fraction of its bound
IPOPT_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


# --------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InitialGuessResult:
    """Outcome of :func:`initial_guess`.

    Attributes:
        knots: Knots kappa_0 (10, 8): rows 0-6 joints [rad], rows 7-9 the base offset [m]
            (constant across knots). The solver's last iterate, also when it failed (the seed
            if that iterate is not finite).
        T: Command duration [s].
        status: IPOPT's own return status (``"Solve_Succeeded"``, ``"Infeasible_Problem_
            Detected"``, ``"Maximum_Iterations_Exceeded"``, ...).
        converged: IPOPT reported success (``IPOPT_SUCCESS``).
        feasible: The command respects every limit at its 250 Hz samples (analytic
            derivatives, torque if ``torque_limits``) and the z_min row (to ``Z_TOL``).
        success: ``converged and feasible``.
        cost: Objective at ``knots`` (the surrogate rotation term) [-].
        cost_terms: ``COST_TERMS`` -> weighted sums [-]; they add up to ``cost``.
        max_errors: Largest tracking errors over the cost samples: ``"position"`` [m],
            ``"rotation"`` [rad] (exact |Log|), ``"velocity"`` [m/s].
        rms_errors: Root-mean-square of the same [m], [rad], [m/s].
        limit_usage: Largest |value| / limit over the 250 Hz samples and joints for
            ``"vel"``, ``"acc"``, ``"tau"``; for ``"pos"`` the largest |q - mid| / half-range;
            for ``"z"`` the start height margin z_tip(q(0)) + b_z - z_min [m].
        active_limits: ``LIMIT_BLOCKS`` -> number of limit rows within ``ACTIVE_RTOL`` of their
            (margin-reduced) bound at the solution.
        violations: One line per violated limit (empty when feasible).
        iterations: IPOPT iterations.
        build_time: Wall time to build the NLP and the IPOPT instance [s].
        solve_time: Wall time of the IPOPT solve [s].
    """

    knots: np.ndarray
    T: float
    status: str
    converged: bool
    feasible: bool
    success: bool
    cost: float
    cost_terms: Mapping[str, float]
    max_errors: Mapping[str, float]
    rms_errors: Mapping[str, float]
    limit_usage: Mapping[str, float]
    active_limits: Mapping[str, int]
    violations: tuple[str, ...]
    iterations: int
    build_time: float
    solve_time: float

    @property
    def base_offset(self) -> np.ndarray:
        """Base offset b (3,) [m]: the robot base's position in the demonstration frame."""
        return self.knots[N_JOINTS:, 0].copy()

    @property
    def command(self) -> BezierCommand:
        """The knots and duration as a :class:`BezierCommand`."""
        return BezierCommand(self.knots, self.T)


def require_success(result: InitialGuessResult) -> InitialGuessResult:
    """Return ``result`` if the solve converged to a feasible command.

    Raises:
        SolverError: With IPOPT's status, and the violated limits if it converged to an
            infeasible command.
    """
    if not result.success:
        detail = "; ".join(result.violations) if result.violations else ""
        if result.converged and not result.feasible:
            detail = f"converged but infeasible: {detail}"
        raise SolverError("ipopt", result.status, detail)
    return result


# --------------------------------------------------------------------------------------------
# checking a command
# --------------------------------------------------------------------------------------------


def tracking_errors(
    knots: np.ndarray,
    T: float,
    t: np.ndarray,
    p_h: np.ndarray,
    R_h: np.ndarray,
    v_h: np.ndarray,
    robot: RobotModel,
) -> dict[str, np.ndarray]:
    """Fingertip tracking errors of a command at sample times, with the exact rotation Log.

    |p_tip(q(t)) + b - p_h|, |Log(R_h^T R_tip(q(t)))|, |J_p(q) qd(t) - v_h|, with q, qd from
    the knots and b = knots[7:10, 0].

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        t: Sample times (m,) [s] in [0, T].
        p_h: Desired positions (m, 3) [m].
        R_h: Desired orientations (m, 3, 3).
        v_h: Desired velocities (m, 3) [m/s].
        robot: Robot model.

    Returns:
        ``{"position": (m,) [m], "rotation": (m,) [rad], "velocity": (m,) [m/s]}``.
    """
    q = bernstein_basis(t, T, 0) @ knots[:N_JOINTS].T
    qd = bernstein_basis(t, T, 1) @ knots[:N_JOINTS].T
    tip = robot.tip_states(q, qd)
    return {
        "position": np.linalg.norm(tip.p + knots[N_JOINTS:, 0] - p_h, axis=1),
        "rotation": np.linalg.norm(rotation_log(R_h, tip.R), axis=1),
        "velocity": np.linalg.norm(tip.v - v_h, axis=1),
    }


def check_command(
    knots: np.ndarray,
    T: float,
    robot: RobotModel,
    params: InitialGuessParams,
) -> tuple[dict[str, float], list[str]]:
    """Usage of every limit by a command at its 250 Hz samples, and the violations.

    Samples t = :func:`limit_sample_times` (T); q, qd, qdd as the controllers take them
    (:func:`learner.bezier.controller_basis`);
    tau = robot.torques(q, qd, qdd). A violation is q outside [q_min, q_max], |qd| > qd_max,
    |qdd| > qdd_max, |tau| > tau_max (if ``params.torque_limits``; the *unreduced* limits) or
    z_tip(q(0)) + b_z < z_min - Z_TOL.

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        robot: Robot model.
        params: Limits, z_min and the torque flag.

    Returns:
        ``(usage, violations)``: usage as in :attr:`InitialGuessResult.limit_usage`; one line
        per violated quantity (worst joint and time).
    """
    lim = params.limits
    t = limit_sample_times(T)
    q, qd, qdd = (controller_basis(t, T, r) @ knots[:N_JOINTS].T for r in (0, 1, 2))
    tau = robot.torques(q, qd, qdd)
    mid, half = 0.5 * (lim.q_max + lim.q_min), 0.5 * (lim.q_max - lim.q_min)
    ratios = {
        "pos": np.abs(q - mid) / half,
        "vel": np.abs(qd) / lim.qd_max,
        "acc": np.abs(qdd) / lim.qdd_max,
        "tau": np.abs(tau) / lim.tau_max,
    }
    values = {"pos": q, "vel": qd, "acc": qdd, "tau": tau}
    usage: dict[str, float] = {}
    violations: list[str] = []
    for name, ratio in ratios.items():
        usage[name] = float(ratio.max())
        if name == "tau" and not params.torque_limits:
            continue
        if ratio.max() > 1.0:
            a, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
            violations.append(
                f"{name} joint {j + 1} = {values[name][a, j]:.4g} at t = {t[a]:.3f} s "
                f"({ratio[a, j]:.3f} x limit)"
            )
    z_base = knots[N_ROWS - 1, 0] if params.base_height is None else params.base_height
    z0 = float(np.asarray(robot.fk(knots[:N_JOINTS, 0])[0])[2, 0] + z_base)
    usage["z"] = z0 - params.z_min
    if usage["z"] < -Z_TOL:
        violations.append(f"z start height {z0:.4f} m below z_min {params.z_min:g} m")
    return usage, violations


# --------------------------------------------------------------------------------------------
# solving
# --------------------------------------------------------------------------------------------


def _ipopt_options(params: InitialGuessParams) -> dict:
    return {
        "ipopt.max_iter": int(params.max_iter),
        "ipopt.tol": float(params.tol),
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
    }


class _IterationReport(ca.Callback):
    """IPOPT's iteration callback: calls ``on_iteration(k, f)`` after iteration k (objective f);
    it only reads, so the solution is the same with or without it."""

    def __init__(self, nx: int, ng: int, on_iteration: Callable[[int, float], None]):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.on_iteration, self.k = nx, ng, on_iteration, 0
        self.construct("initial_guess_progress", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.dense(1)
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def eval(self, arg: list) -> list:
        self.k += 1
        self.on_iteration(self.k, float(arg[ca.nlpsol_out().index("f")]))
        return [0]


def solve_problem(
    problem: InitialGuessProblem,
    robot: RobotModel,
    on_iteration: Callable[[int, float], None] | None = None,
) -> InitialGuessResult:
    """Solve a built problem with IPOPT and evaluate the outcome.

    Args:
        problem: From :func:`build_problem`.
        robot: The robot model it was built with (for the checks).
        on_iteration: Called after every IPOPT iteration with (iteration, objective), e.g.
            for a progress display; None: nothing.

    Returns:
        The result; ``success`` is False (with IPOPT's ``status`` kept) unless IPOPT converged
        and the command respects every limit at 250 Hz.
    """
    params = problem.params
    t_build = time.perf_counter()
    nlp = {"x": problem.x, "f": problem.f(problem.x), "g": problem.g(problem.x)}
    opts = {**_ipopt_options(params), "jac_g": problem.jac_g, "hess_lag": problem.hess_lag}
    if on_iteration is not None:
        nx, ng = problem.x.numel(), problem.g(problem.x).numel()
        opts["iteration_callback"] = _IterationReport(nx, ng, on_iteration)
    solver = ca.nlpsol("initial_guess", "ipopt", nlp, opts)
    build_time = time.perf_counter() - t_build
    t0 = time.perf_counter()
    sol = solver(x0=problem.x0, lbg=problem.lbg, ubg=problem.ubg)
    solve_time = time.perf_counter() - t0
    stats = solver.stats()
    status = str(stats.get("return_status", "unknown"))
    x = np.asarray(sol["x"]).ravel()
    converged = status in IPOPT_SUCCESS and bool(np.all(np.isfinite(x)))
    if not np.all(np.isfinite(x)):
        x = problem.x0.copy()
    knots = knots_from_x(x)
    return _evaluate(problem, robot, x, knots, status, converged, stats, build_time, solve_time)


def _evaluate(
    problem: InitialGuessProblem,
    robot: RobotModel,
    x: np.ndarray,
    knots: np.ndarray,
    status: str,
    converged: bool,
    stats: dict,
    build_time: float,
    solve_time: float,
) -> InitialGuessResult:
    """Errors, costs, limit usage and binding rows of the solution x."""
    T = problem.T
    terms = np.asarray(problem.terms(x)).ravel()
    errs = tracking_errors(knots, T, problem.t_cost, problem.p_h, problem.R_h, problem.v_h, robot)
    usage, violations = check_command(knots, T, robot, problem.params)
    g = np.asarray(problem.g(x)).ravel()
    tol = ACTIVE_RTOL * np.maximum(
        np.where(np.isfinite(problem.ubg), np.abs(problem.ubg), np.abs(problem.lbg)), 1e-12
    )
    near = (np.abs(g - problem.lbg) <= tol) | (np.abs(problem.ubg - g) <= tol)
    active = {name: int(near[a:z].sum()) for name, (a, z) in problem.blocks.items()}
    feasible = not violations
    return InitialGuessResult(
        knots=readonly(knots),
        T=T,
        status=status,
        converged=converged,
        feasible=feasible,
        success=converged and feasible,
        cost=float(terms.sum()),
        cost_terms=MappingProxyType({k: float(v) for k, v in zip(COST_TERMS, terms, strict=True)}),
        max_errors=MappingProxyType({k: float(v.max()) for k, v in errs.items()}),
        rms_errors=MappingProxyType({k: float(np.sqrt(np.mean(v**2))) for k, v in errs.items()}),
        limit_usage=MappingProxyType(usage),
        active_limits=MappingProxyType(active),
        violations=tuple(violations),
        iterations=int(stats.get("iter_count", 0)),
        build_time=build_time,
        solve_time=solve_time,
    )


def initial_guess(
    demo_hand_t: np.ndarray,
    demo_hand_p: np.ndarray,
    demo_hand_R: np.ndarray,
    T: float,
    robot: RobotModel,
    *,
    params: InitialGuessParams | None = None,
    q_seed: np.ndarray | None = None,
    on_iteration: Callable[[int, float], None] | None = None,
) -> InitialGuessResult:
    """The initial command kappa_0 tracking the demonstration hand (module docstring).

    Args:
        demo_hand_t: Demonstration times, shape (k,) [s], within [0, T].
        demo_hand_p: Desired fingertip positions, shape (k, 3) [m], demonstration frame.
        demo_hand_R: Desired fingertip orientations, shape (k, 3, 3) (tip-site convention).
        T: Command duration [s] (the demonstration's hand-motion length).
        robot: Robot model.
        params: Weights, limits and settings (default: the paper's).
        q_seed: Seed joint angles (7,) [rad]; default ``HOME_Q``.
        on_iteration: Called after every IPOPT iteration with (iteration, objective).

    Returns:
        The result (check ``success`` or call :func:`require_success`).

    Raises:
        ConfigError: Malformed inputs.
    """
    t0 = time.perf_counter()
    problem = build_problem(
        demo_hand_t, demo_hand_p, demo_hand_R, T, robot, params=params, q_seed=q_seed
    )
    built = time.perf_counter() - t0
    result = solve_problem(problem, robot, on_iteration)
    return replace(result, build_time=built + result.build_time)


__all__ = [
    "ACTIVE_RTOL",
    "IPOPT_SUCCESS",
    "Z_TOL",
    "InitialGuessParams",
    "InitialGuessResult",
    "check_command",
    "initial_guess",
    "require_success",
    "solve_problem",
    "tracking_errors",
]

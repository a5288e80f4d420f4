"""The limit rows of the inverse-model QP: build them, scale them, and generate the active set.

Every joint limit of the updated command (position, velocity, acceleration, torque) on the
250 Hz command samples is a linearised row ``lo <= b - J dkappa <= hi`` (:func:`limit_rows`,
:class:`LimitRows`), with b the current value and J its knot Jacobian, so the row holds for the
*updated* command: exactly for position, velocity and acceleration (linear in the knots) and to
first order for torque. :func:`learner.inverse_qp.build_inverse_qp` turns rows into the QP's
constraint blocks.

Torque is bounded twice: the learner's inverse dynamics (``tau``: the links, the rotors'
inertia and the joints' damping, what a motor delivers and the hardware preflight checks) and
the links' rigid-body part alone (``tau_links``: the torque the paper's limits apply to, which
the simulated controller faults on; :meth:`learner.kinematics.RobotModel.passive_torques` is
the difference). Neither bounds the other: the joints' damping adds to the links' torque or
takes from it with the sign of the velocity (on a person-paced swipe the two differ by 8 N m
at joint 3, against a 40 N m limit).

The full grid has 5 x 7 rows per sample (~7000 for a 0.8 s command); most never come near their
bound. :func:`generate_constraints` solves with the rows whose current value uses at least
``margin`` of the range (:func:`initial_active_rows`; with a margin > 0, the ``tau_links``
rows only once violated, :data:`LATE_KINDS`), adds the rows the solution violates
(:func:`limit_violation`, beyond ``LIMIT_TOL`` of the half range) and solves again, at most
``max_rounds`` times, then once with every row. :func:`sampled_violation` checks a command's
own limits on its samples, without linearisation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from flyknot.constants import N_JOINTS, N_VARS
from flyknot.errors import ConfigError, check_choice
from flyknot.geometry import readonly
from flyknot.limits import JointLimits
from learner.bezier import check_knots, controller_basis, controller_jacobian
from learner.limit_set import LimitRows

if TYPE_CHECKING:
    from learner.kinematics import RobotModel
    from learner.qp_solve import QPResult

LIMIT_KINDS = ("pos", "vel", "acc", "tau", "tau_links")
LATE_KINDS = ("tau_links",)
"""Blocks that join a QP's active set only once its solution violates them, never from the
margin: where they are not violated, the update is the one without them, bit for bit."""
LIMIT_TOL = 1e-6  # a limit row counts as violated beyond this fraction of its half range


# --------------------------------------------------------------------------------------------
# the rows
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _DenseBlock:
    """Rows whose knot Jacobian is at hand: position, velocity, acceleration (exact)."""

    J: np.ndarray  # (r, 80)

    def rows(self, idx: np.ndarray) -> np.ndarray:
        return self.J[idx]

    def product(self, dk: np.ndarray) -> np.ndarray:
        return self.J @ dk


@dataclass(frozen=True)
class _TorqueBlock:
    """Torque rows, row ``a * 7 + j`` for sample a and joint j: the knot Jacobian
    ``dID/dq S_0 + dID/dqd S_1 + dID/dqdd S_2`` of a sample is formed only when one of its rows
    is asked for, and ``J dkappa`` is the inverse dynamics' directional derivative along
    ``(S_0, S_1, S_2) dkappa``, without any Jacobian."""

    robot: RobotModel
    states: tuple[np.ndarray, np.ndarray, np.ndarray]  # q, qd, qdd, each (m, 7)
    S: tuple[np.ndarray, np.ndarray, np.ndarray]  # d q^(r) / d kappa, each (m, 7, 80)
    links_only: bool = False  # the links' rigid-body torque: less the passive part's diagonals

    def rows(self, idx: np.ndarray) -> np.ndarray:
        samples, where = np.unique(idx // N_JOINTS, return_inverse=True)
        dq, dqd, dqdd = self.robot.torque_jacobians(*(x[samples] for x in self.states))
        if self.links_only:
            r = self.robot
            dq, dqd, dqdd = (
                d - np.diag(c) for d, c in ((dq, r.stiffness), (dqd, r.damping), (dqdd, r.armature))
            )
        S0, S1, S2 = (x[samples] for x in self.S)
        J = (
            np.einsum("aij,ajc->aic", dq, S0)
            + np.einsum("aij,ajc->aic", dqd, S1)
            + np.einsum("aij,ajc->aic", dqdd, S2)
        )
        return J[where, idx % N_JOINTS]

    def product(self, dk: np.ndarray) -> np.ndarray:
        v = [S @ dk for S in self.S]  # (m, 7) each
        out = self.robot.torque_jvp(*self.states, *v)
        if self.links_only:  # the passive part is linear: its derivative along v is itself
            r = self.robot
            out = out - (r.armature * v[2] + r.damping * v[1] + r.stiffness * v[0])
        return out.ravel()


@dataclass(frozen=True)
class LimitGrid:
    """Every limit row of a command on its sample grid (:func:`limit_rows`): the values, the
    bounds and the blocks of :class:`LimitRows`, with the knot Jacobian formed only for the
    rows taken into a QP (:meth:`take`) and applied to an update without forming it
    (:meth:`product`).

    Attributes:
        b: Values at the current knots (r,).
        lo: Lower bounds (r,).
        hi: Upper bounds (r,).
        blocks: Named row ranges ``name -> (start, stop)``.
        parts: The row source of each block, in block order.
    """

    b: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    blocks: Mapping[str, tuple[int, int]]
    parts: tuple[_DenseBlock | _TorqueBlock, ...]

    @property
    def n_rows(self) -> int:
        """Number of limit rows."""
        return int(self.b.shape[0])

    @property
    def J(self) -> np.ndarray:
        """Every row's knot Jacobian (r, 80), formed on each call."""
        return self.rows(np.arange(self.n_rows))

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """The knot Jacobian of the rows ``idx`` (sorted), shape (len(idx), 80)."""
        idx = np.asarray(idx, dtype=int)
        out = np.empty((idx.size, N_VARS))
        for (a, z), part in zip(self.blocks.values(), self.parts, strict=True):
            lo, hi = np.searchsorted(idx, a), np.searchsorted(idx, z)
            if hi > lo:
                out[lo:hi] = part.rows(idx[lo:hi] - a)
        return out

    def product(self, dkappa: np.ndarray) -> np.ndarray:
        """``J dkappa`` for every row, shape (r,), with ``dkappa`` (80,)."""
        return np.concatenate([part.product(dkappa) for part in self.parts])

    def take(self, idx: np.ndarray) -> LimitRows:
        """The rows ``idx`` (sorted) as :class:`LimitRows`, the named blocks kept contiguous."""
        idx = np.asarray(idx, dtype=int)
        blocks = {
            name: (int(np.searchsorted(idx, a)), int(np.searchsorted(idx, z)))
            for name, (a, z) in self.blocks.items()
        }
        J = self.rows(idx)
        return LimitRows(J=J, b=self.b[idx], lo=self.lo[idx], hi=self.hi[idx], blocks=blocks)


def limit_rows(
    knots: np.ndarray,
    T: float,
    t_samples: np.ndarray,
    robot_model: RobotModel | None,
    limits: JointLimits | None = None,
    kinds: Sequence[str] = LIMIT_KINDS,
) -> LimitGrid:
    """Joint position, velocity, acceleration and torque limits at sample times.

    For sample a and joint j (row ``a * 7 + j`` of each block), with the basis ``C_r`` of the
    samples and of their derivatives as the controllers take them (r = 0: the Bezier basis at
    t_a; r = 1, 2: its central differences with rest padding,
    :func:`learner.bezier.controller_basis`)::

        q^(r)_j(t_a) = C_r[a] . kappa[j],   d q^(r)_j(t_a) / d kappa[j, :] = C_r[a]
        tau(t_a) = ID(q, qd, qdd)(t_a)
        d tau / d kappa = dID/dq S_0 + dID/dqd S_1 + dID/dqdd S_2,   S_r = d q^(r) / d kappa
        tau_links(t_a) = tau(t_a) - P(q, qd, qdd)(t_a)   (P: ``RobotModel.passive_torques``)

    so a row bounds exactly what the simulated controller faults on and the hardware preflight
    refuses on. The torque rows' Jacobians are formed only for the rows a QP takes
    (:class:`LimitGrid`).

    Bounds: ``q_min <= q <= q_max``, ``|qd| <= qd_max``, ``|qdd| <= qdd_max``,
    ``|tau| <= tau_max``, ``|tau_links| <= tau_max``.

    Args:
        knots: Current knots (10, 8) (rows 0-6 [rad], rows 7-9 [m]).
        T: Command duration [s].
        t_samples: Sample times (m,) [s]: the command's uniform grid from 0 within [0, T].
        robot_model: Inverse dynamics for the torque rows; None leaves torque out.
        limits: Bounds (default: the paper's).
        kinds: Which blocks to build, a subset of :data:`LIMIT_KINDS`.

    Returns:
        The grid of rows: b (r,), lo, hi, blocks named by ``kinds``, the Jacobian on demand.
    """
    limits = JointLimits() if limits is None else limits
    kinds = list(kinds)
    for k in kinds:
        check_choice("kinds", k, LIMIT_KINDS)
    for k in ("tau", "tau_links"):
        if k in kinds and robot_model is None:
            raise ConfigError("robot_model", f"is needed for torque limits (kind {k!r})")
    if not kinds:
        raise ConfigError("kinds", "must name at least one limit", LIMIT_KINDS)
    t = np.asarray(t_samples, dtype=float)
    bases = {r: controller_basis(t, T, r) for r in (0, 1, 2)}  # (m, 8)
    joints = check_knots(knots)[:N_JOINTS].T  # (8, 7)
    derivs = {r: bases[r] @ joints for r in (0, 1, 2)}  # (m, 7)
    jacs = {r: controller_jacobian(t, T, r) for r in (0, 1, 2)}  # (m * 7, 80)
    m = derivs[0].shape[0]
    bounds = {
        "pos": (limits.q_min, limits.q_max),
        "vel": (-limits.qd_max, limits.qd_max),
        "acc": (-limits.qdd_max, limits.qdd_max),
        "tau": (-limits.tau_max, limits.tau_max),
        "tau_links": (-limits.tau_max, limits.tau_max),
    }
    parts, bs, los, his, blocks = [], [], [], [], {}
    start = 0
    states = (derivs[0], derivs[1], derivs[2])
    tau = None  # the whole torque, computed once for both torque blocks
    for kind in kinds:
        if kind in ("tau", "tau_links"):
            links = kind == "tau_links"
            if tau is None:
                tau = robot_model.torques(*states)  # type: ignore[union-attr]
            b = tau - robot_model.passive_torques(*states) if links else tau  # type: ignore[union-attr]
            S = tuple(jacs[r].reshape(m, N_JOINTS, N_VARS) for r in (0, 1, 2))
            parts.append(_TorqueBlock(robot_model, states, S, links))  # type: ignore[arg-type]
        else:
            r = LIMIT_KINDS.index(kind)
            b = derivs[r]
            parts.append(_DenseBlock(jacs[r]))
        lo, hi = bounds[kind]
        bs.append(np.asarray(b).ravel())
        los.append(np.tile(lo, m))
        his.append(np.tile(hi, m))
        blocks[kind] = (start, start + m * N_JOINTS)
        start += m * N_JOINTS
    b, lo, hi = np.concatenate(bs), np.concatenate(los), np.concatenate(his)
    if not np.all(np.isfinite(b)):
        raise ConfigError("b", "must be finite")
    return LimitGrid(
        b=readonly(b),
        lo=readonly(lo),
        hi=readonly(hi),
        blocks=MappingProxyType(blocks),
        parts=tuple(parts),
    )


# --------------------------------------------------------------------------------------------
# scaling, selecting and checking rows
# --------------------------------------------------------------------------------------------


def row_scale(rows: LimitRows | LimitGrid) -> tuple[np.ndarray, np.ndarray]:
    """Mid point and half range of every row (half range 1 where a bound is infinite).

    Every selection and violation below is measured in these units: a row's value y is
    scaled as (y - mid) / half.
    """
    lo, hi = rows.lo, rows.hi
    finite = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    mid = np.where(finite, 0.5 * (lo + hi), 0.0)
    half = np.where(finite, 0.5 * (hi - lo), 1.0)
    return mid, half


def initial_active_rows(rows: LimitRows | LimitGrid, margin: float) -> np.ndarray:
    """Rows whose current value uses at least ``margin`` of the range: |b - mid| >= m * half.

    Args:
        rows: All limit rows.
        margin: Fraction in [0, 1]; 0 selects every row.

    Returns:
        Sorted row indices.
    """
    mid, half = row_scale(rows)
    return np.flatnonzero(np.abs(rows.b - mid) >= margin * half)


def limit_violation(rows: LimitRows | LimitGrid, dkappa: np.ndarray) -> np.ndarray:
    """Linearised violation of every row after the update, relative to the half range.

    y = b - J dkappa,  viol = max(lo - y, y - hi, 0) / half.

    Args:
        rows: Limit rows.
        dkappa: Update (10, 8) or (80,).

    Returns:
        Violations, shape (r,) (0 where the row holds).
    """
    _, half = row_scale(rows)
    dk = np.asarray(dkappa, dtype=float).ravel()
    y = rows.b - (rows.product(dk) if isinstance(rows, LimitGrid) else rows.J @ dk)
    return np.maximum(0.0, np.maximum(rows.lo - y, y - rows.hi)) / half


def sampled_violation(
    knots: np.ndarray, T: float, t: np.ndarray, robot: RobotModel, limits: JointLimits
) -> float:
    """Largest violation of the limits by a command on its samples, relative to half ranges.

    max over samples, joints and kinds of max(lo - y, y - hi, 0) / ((hi - lo) / 2) for
    y = q, qd, qdd as the controllers take them (:func:`learner.bezier.controller_basis`),
    tau = ID(q, qd, qdd) and the links' part of it, tau - P(q, qd, qdd).

    Args:
        knots: Knots (10, 8).
        T: Duration [s].
        t: Sample times (m,) [s]: the command's uniform grid from 0.
        robot: Robot model (inverse dynamics).
        limits: The limits.

    Returns:
        The violation (0 when every limit holds).
    """
    joints = check_knots(knots)[:N_JOINTS].T
    q, qd, qdd = (controller_basis(t, T, r) @ joints for r in (0, 1, 2))
    worst = 0.0
    tau = robot.torques(q, qd, qdd)
    for y, lo, hi in (
        (q, limits.q_min, limits.q_max),
        (qd, -limits.qd_max, limits.qd_max),
        (qdd, -limits.qdd_max, limits.qdd_max),
        (tau, -limits.tau_max, limits.tau_max),
        (tau - robot.passive_torques(q, qd, qdd), -limits.tau_max, limits.tau_max),
    ):
        over = np.maximum(lo - y, y - hi) / (0.5 * (hi - lo))
        worst = max(worst, float(over.max()))
    return worst


def subset_rows(rows: LimitRows | LimitGrid, idx: np.ndarray) -> LimitRows:
    """The rows ``idx`` (sorted) of ``rows``, with the named blocks kept contiguous."""
    if isinstance(rows, LimitGrid):
        return rows.take(idx)
    idx = np.asarray(idx, dtype=int)
    blocks = {}
    for name, (a, z) in rows.blocks.items():
        start = int(np.searchsorted(idx, a))
        stop = int(np.searchsorted(idx, z))
        blocks[name] = (start, stop)
    return LimitRows(J=rows.J[idx], b=rows.b[idx], lo=rows.lo[idx], hi=rows.hi[idx], blocks=blocks)


# --------------------------------------------------------------------------------------------
# constraint generation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GeneratedSolve:
    """Outcome of :func:`generate_constraints`.

    Attributes:
        result: The last solve.
        active: Indices of the rows in the last QP (sorted), or None without rows.
        rounds: Solves made.
        violation: :func:`limit_violation` of every row at the last solve's update, (r,);
            empty without rows or when the first solve failed.
    """

    result: QPResult
    active: np.ndarray | None
    rounds: int
    violation: np.ndarray


def _without_late(rows: LimitRows | LimitGrid, idx: np.ndarray) -> np.ndarray:
    """``idx`` less the rows of the :data:`LATE_KINDS` blocks."""
    for kind in LATE_KINDS:
        if kind in rows.blocks:
            a, z = rows.blocks[kind]
            idx = idx[(idx < a) | (idx >= z)]
    return idx


def generate_constraints(
    rows: LimitRows | LimitGrid | None,
    solve: Callable[[LimitRows | None], QPResult],
    margin: float,
    max_rounds: int,
) -> GeneratedSolve:
    """Solve with an active set of limit rows, adding the violated ones (module docstring).

    The first solve holds :func:`initial_active_rows` (rows, margin). After each solve every
    row is checked at the new update; rows violated beyond ``LIMIT_TOL`` join the set and the QP
    is solved again; after ``max_rounds`` solves the next one holds every row. Stops when no row
    is violated, a solve fails, or every row was in the solve.

    Args:
        rows: All limit rows, or None (a single solve without limits).
        solve: Builds and solves the QP with the given rows (None: none) and returns its result.
        margin: Initial active-set threshold in [0, 1].
        max_rounds: Most solves before the one with every row (>= 1).

    Returns:
        The last solve, its rows, the number of solves and the rows' violations.
    """
    idx = None if rows is None else initial_active_rows(rows, margin)
    if idx is not None and margin > 0:  # margin 0: every row from the start
        idx = _without_late(rows, idx)

    def solve_rows(idx: np.ndarray | None) -> QPResult:
        lim = None if rows is None or idx is None or idx.size == 0 else subset_rows(rows, idx)
        return solve(lim)

    rounds = 0
    res = solve_rows(idx)
    rounds += 1
    viol = np.zeros(0)
    if rows is not None and res.solved:
        tol = LIMIT_TOL
        while True:
            viol = limit_violation(rows, res.dkappa)
            new = np.setdiff1d(np.flatnonzero(viol > tol), idx)
            if new.size == 0:
                break
            if rounds >= max_rounds:  # every row (a late one only once violated)
                every = np.arange(rows.n_rows)
                new = every if margin <= 0 else np.union1d(_without_late(rows, every), new)
            idx = np.union1d(idx, new)
            res = solve_rows(idx)
            rounds += 1
            if not res.solved:
                break
            if idx.size == rows.n_rows:
                viol = limit_violation(rows, res.dkappa)
                break
    return GeneratedSolve(result=res, active=idx, rounds=rounds, violation=viol)


__all__ = [
    "LATE_KINDS",
    "LIMIT_KINDS",
    "LIMIT_TOL",
    "GeneratedSolve",
    "LimitGrid",
    "LimitRows",
    "generate_constraints",
    "initial_active_rows",
    "limit_rows",
    "limit_violation",
    "row_scale",
    "sampled_violation",
    "subset_rows",
]

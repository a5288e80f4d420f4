"""The inverse-model QP (paper eq. inverse_model_qp): build it here, solve it apart
(:mod:`learner.qp_solve`).

Decision variable and update convention:
    The QP's variable is the flattened knot update ``x = dkappa.ravel()`` (80,), the (10, 8)
    knots flattened row-major (row r = joint1..joint7, base_x, base_y, base_z; knot j at index
    ``8 r + j``). The learner *subtracts* it, ``kappa_{k+1} = kappa_k - dkappa`` (paper,
    Algorithm 1). The predicted state change ``dx = M dkappa`` (eq. sysysy) is substituted into
    the cost, so ``dx`` is not a variable.

    Every Jacobian handed to the builder is the plain derivative with respect to the knots,
    ``J = d(.)/d kappa`` at ``kappa_k`` (the paper's definitions of M, J_ft, J_x). Because the
    update is subtracted, a quantity after the update is ``y(kappa_k - dkappa) ~= y_k - J dkappa``.
    Hence the critical-point term ``||M dkappa - err||_Q`` (with ``err = x_k - x_demo``) and the
    follow-through term ``||e_ft - J_ft dkappa||_W``; the paper writes the latter with ``+``,
    which matches its ``-`` update only if J_ft is taken with respect to ``-dkappa``.

Objective (all terms summed; constant kept so that ``QPData.objective`` is the true cost)::

    f(x) = ||M x - err||_Q^2                                      critical point, eq. cpobj
         + sum_t ||e_ft(t) - J_ft(t) x||_W(t)^2                   follow-through, eq. followthrough
         + w_control ||x_arm - c_arm||^2                          control, eq. reg (56 arm entries)
         = 1/2 x^T P x + q^T x + const

    c    = 0 (the paper's), or a centre the step is pulled toward (``center``: an exploring
           step, :class:`learner.stops.Explore`)
    Q    = diag(w_crit_pos I_3N, w_crit_vel I_3N)          rows of M: 3N positions, 3N velocities
    W(t) = diag(w_p I_3, w_R I_3, w_v I_3)                 rows of e_ft: position, rotation,
                                                           velocity
    (w_p, w_R, w_v) = (w_pc, w_rc, w_vc)                   at t = t_c
                    = (w_pft, w_rft, w_ft_velocity w_vft)  for t > t_c

``w_ft_velocity`` (paper table, no equation) is read here as an overall scale on the
follow-through velocity terms after t_c, so the effective velocity weight there is
``0.5 * 0.1 = 0.05``; at t_c the critical weights apply as listed.

The equally weighted baseline (paper, "Weighted Error Objectives") replaces the critical term by
the mean over pre-collision samples s, ``(1/S) sum_s ||M_s x - err_s||_Q^2``: every sample gets
the same weight and the total weight equals the critical objective's, so the control term keeps
the same relative strength.

More rope states (``points``, e.g. the launch objective's, :mod:`learner.objectives`) add
``||M_s x - err_s||_Q^2`` each beside the critical term, weighted as it.

Constraints ``l <= A x <= u``, row blocks in order:
    * ``base``: the 3 base rows' update is the same at all 8 knots (``base_update="constant"``:
      the base stays fixed within a trial but may shift between trials), or zero
      (``"zero"``, the paper's eq. base read literally);
    * limit blocks (``pos``, ``vel``, ``acc``, ``tau``): ``lo <= b - J x <= hi`` with ``b`` the
      current value and ``J`` its knot Jacobian, i.e. the limit holds for the *updated* command
      (exactly for pos/vel/acc, which are linear in the knots, to first order for torque).
      The rows are built, selected and checked in :mod:`learner.limit_rows`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from types import MappingProxyType

import numpy as np
import scipy.sparse as sp

from flyknot.constants import (
    JOINT_NAMES,
    N_JOINTS,
    N_KNOTS,
    N_ROWS,
    N_VARS,
)
from flyknot.errors import (
    ConfigError,
    check_choice,
    check_nonnegative,
    check_positive,
)
from flyknot.geometry import readonly
from learner.limit_set import LimitRows
from learner.qp_kernel import weighted_gram, weighted_rhs

FT_DIM = 9  # follow-through error: position (3), rotation log (3), velocity (3)
BASE_UPDATES = ("constant", "zero")
ROW_NAMES = (*JOINT_NAMES, "base_x", "base_y", "base_z")
COLUMNS = tuple(f"{r}[{j}]" for r in ROW_NAMES for j in range(N_KNOTS))
ARM_COLUMNS = np.arange(N_JOINTS * N_KNOTS)  # the 56 arm-joint knot entries


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise ConfigError(name, "must be finite")


# --------------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InverseModelWeights:
    """Weights of the inverse-model QP (paper, appendix table "Inverse Model Parameters").

    ``w_rc`` and ``w_rft`` are the paper's ``w_Rc`` and ``w_Rft``.

    Attributes:
        w_control: Control cost on the arm-joint knot updates [1/rad^2].
        w_crit_pos: Critical-point marker position weight [1/m^2].
        w_crit_vel: Critical-point marker velocity weight [s^2/m^2].
        w_pc: Fingertip position weight at t_c [1/m^2].
        w_vc: Fingertip velocity weight at t_c [s^2/m^2].
        w_rc: Fingertip rotation weight at t_c [1/rad^2].
        w_pft: Fingertip position weight after t_c [1/m^2].
        w_vft: Fingertip velocity weight after t_c [s^2/m^2].
        w_rft: Fingertip rotation weight after t_c [1/rad^2].
        w_ft_velocity: Scale on the velocity weight after t_c (see the module docstring).
    """

    w_control: float = 0.5
    w_crit_pos: float = 25.0
    w_crit_vel: float = 0.00375
    w_pc: float = 100.0
    w_vc: float = 0.1
    w_rc: float = 5.0
    w_pft: float = 1.0
    w_vft: float = 0.1
    w_rft: float = 0.1
    w_ft_velocity: float = 0.5

    def __post_init__(self) -> None:
        for f in fields(self):
            check_nonnegative(f.name, getattr(self, f.name))

    def critical_diagonal(self, n_rows: int) -> np.ndarray:
        """Diagonal of Q = diag(w_crit_pos I, w_crit_vel I), (n_rows,): positions first."""
        half = n_rows // 2
        return np.concatenate([np.full(half, self.w_crit_pos), np.full(half, self.w_crit_vel)])

    def follow_weights(self, is_tc: bool) -> np.ndarray:
        """Diagonal of W(t), (9,): ``(w_p I3, w_R I3, w_v I3)`` at t_c or after it."""
        if is_tc:
            w = (self.w_pc, self.w_rc, self.w_vc)
        else:
            w = (self.w_pft, self.w_rft, self.w_ft_velocity * self.w_vft)
        return np.repeat(np.asarray(w, dtype=float), 3)


@dataclass(frozen=True)
class FollowThrough:
    """Linearised fingertip follow-through errors at samples t >= t_c.

    Attributes:
        e: Errors at the current knots (k, 9): ``[p_tip - p_h [m], Log(R_h^T R_tip) [rad],
            v_tip - v_h [m/s]]``.
        J: Their knot Jacobians ``d e / d kappa`` (k, 9, 80).
        is_tc: Which samples are the critical time (k,) bool (critical weights there).
    """

    e: np.ndarray
    J: np.ndarray
    is_tc: np.ndarray

    def __post_init__(self) -> None:
        e = np.asarray(self.e, dtype=float)
        if e.ndim != 2 or e.shape[1] != FT_DIM or e.shape[0] < 1:
            raise ConfigError("e", f"must have shape (k, {FT_DIM}) with k >= 1, got {e.shape}")
        k = e.shape[0]
        J = np.asarray(self.J, dtype=float)
        if J.shape != (k, FT_DIM, N_VARS):
            raise ConfigError("J", f"must have shape ({k}, {FT_DIM}, {N_VARS}), got {J.shape}")
        is_tc = np.asarray(self.is_tc)
        if is_tc.shape != (k,) or is_tc.dtype != bool:
            raise ConfigError("is_tc", f"must be a bool array of shape ({k},)")
        _finite("e", e)
        _finite("J", J)
        object.__setattr__(self, "e", readonly(e))
        object.__setattr__(self, "J", readonly(J))
        object.__setattr__(self, "is_tc", readonly(is_tc, bool))


# --------------------------------------------------------------------------------------------
# the QP
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class QPData:
    """A solver-agnostic QP ``min 1/2 x^T P x + q^T x + const  s.t.  l <= A x <= u``.

    Attributes:
        P: Hessian (80, 80), full symmetric, CSC (treat as read-only).
        q: Linear term (80,).
        A: Constraint matrix (m, 80), CSC (treat as read-only).
        l: Lower bounds (m,) (may be -inf).
        u: Upper bounds (m,) (may be +inf; ``l == u`` marks an equality).
        const: Constant term, so that :meth:`objective` is the full cost.
        blocks: Named row ranges of A, ``name -> (start, stop)``.
        columns: Meaning of each of the 80 columns, e.g. ``"joint3[5]"``, ``"base_x[0]"``.
    """

    P: sp.csc_matrix
    q: np.ndarray
    A: sp.csc_matrix
    l: np.ndarray  # noqa: E741 (OSQP's name)
    u: np.ndarray
    const: float
    blocks: Mapping[str, tuple[int, int]]
    columns: tuple[str, ...] = COLUMNS

    def __post_init__(self) -> None:
        n = len(self.columns)
        if self.P.shape != (n, n) or self.A.shape[1] != n or np.shape(self.q) != (n,):
            raise ConfigError("P", f"P, q and A must have {n} columns")
        m = self.A.shape[0]
        if np.shape(self.l) != (m,) or np.shape(self.u) != (m,):
            raise ConfigError("l", f"l and u must have shape ({m},)")
        object.__setattr__(self, "q", readonly(self.q))
        object.__setattr__(self, "l", readonly(self.l))
        object.__setattr__(self, "u", readonly(self.u))
        object.__setattr__(self, "blocks", MappingProxyType(dict(self.blocks)))

    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.P.shape[0])

    @property
    def m(self) -> int:
        """Number of constraint rows."""
        return int(self.A.shape[0])

    def objective(self, x: np.ndarray) -> float:
        """Cost ``1/2 x^T P x + q^T x + const`` at ``x`` (80,) or (10, 8)."""
        x = np.asarray(x, dtype=float).ravel()
        return float(0.5 * x @ (self.P @ x) + self.q @ x + self.const)

    def violation(self, x: np.ndarray) -> float:
        """Largest constraint violation ``max(l - A x, A x - u, 0)`` at ``x``."""
        x = np.asarray(x, dtype=float).ravel()
        ax = self.A @ x
        if ax.size == 0:
            return 0.0
        return float(max(0.0, np.max(self.l - ax), np.max(ax - self.u)))


def _check_rows(name: str, M: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    M = np.asarray(M, dtype=float)
    err = np.asarray(err, dtype=float)
    if M.ndim != 2 or M.shape[1] != N_VARS or M.shape[0] == 0 or M.shape[0] % 6:
        raise ConfigError(name, f"must have shape (6N, {N_VARS}), got {M.shape}")
    if err.shape != (M.shape[0],):
        raise ConfigError(name, f"error must have shape ({M.shape[0]},), got {err.shape}")
    _finite(name, M)
    _finite(name, err)
    return M, err


def base_equality_rows(base_update: str = "constant") -> np.ndarray:
    """Equality rows ``E x = 0`` on the 3 base rows of the knot update.

    ``"constant"``: ``dkappa[r, j] - dkappa[r, 0] = 0`` for base rows r and knots j = 1..7
    (21 rows); ``"zero"``: ``dkappa[r, j] = 0`` for all 8 knots (24 rows).

    Returns:
        E, shape (21, 80) or (24, 80).
    """
    check_choice("base_update", base_update, BASE_UPDATES)
    rows = []
    for r in range(N_JOINTS, N_ROWS):
        for j in range(N_KNOTS):
            if base_update == "constant" and j == 0:
                continue
            e = np.zeros(N_VARS)
            e[r * N_KNOTS + j] = 1.0
            if base_update == "constant":
                e[r * N_KNOTS] = -1.0
            rows.append(e)
    return np.array(rows)


def rest_equality_rows() -> np.ndarray:
    """Equality rows ``E x = 0`` keeping the command at rest at both ends.

    A degree-7 Bezier has qd(0) = 7 (kappa_1 - kappa_0) / T and qd(T) = 7 (kappa_7 -
    kappa_6) / T, so ``dkappa[r, 1] - dkappa[r, 0] = 0`` and ``dkappa[r, 7] - dkappa[r, 6] = 0``
    for the 7 arm rows r keep an update from giving the command a start or end velocity (the
    robot is at rest before and after a trial; a jump would fault it).

    Returns:
        E, shape (14, 80).
    """
    rows = []
    for r in range(N_JOINTS):
        for a, b in ((1, 0), (N_KNOTS - 1, N_KNOTS - 2)):
            e = np.zeros(N_VARS)
            e[r * N_KNOTS + a] = 1.0
            e[r * N_KNOTS + b] = -1.0
            rows.append(e)
    return np.array(rows)


def build_inverse_qp(
    *,
    M_crit: np.ndarray | None = None,
    err_crit: np.ndarray | None = None,
    weights: InverseModelWeights | None = None,
    follow: FollowThrough | None = None,
    limits: LimitRows | None = None,
    equal: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
    points: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    base_update: str = "constant",
    keep_rest: bool = True,
    trust_region: float | None = None,
    center: np.ndarray | None = None,
) -> QPData:
    """Assemble the inverse-model QP (see the module docstring for every term).

    ``P = 2 (sum M^T Q M + sum_t J_t^T W_t J_t + w_control S^T S)``,
    ``q = -2 (sum M^T Q err + sum_t J_t^T W_t e_t + w_control S^T S c)``,
    ``const = sum err^T Q err + sum_t e_t^T W_t e_t + w_control ||S c||^2``, with S selecting
    the 56 arm entries.

    Args:
        M_crit: Linearised model at t_c, ``d x(t_c) / d kappa`` (6N, 80): N marker positions
            (x, y, z each) [m/unit], then N velocities.
        err_crit: Critical-point error ``x_k(t_c) - x_demo(t_c)`` (6N,) [m, m/s].
        weights: QP weights (default: the paper's).
        follow: Fingertip follow-through terms, or None.
        limits: Limit rows, or None.
        equal: Equally weighted baseline: ``[(M_s (6N, 80), err_s (6N,)), ...]`` over
            pre-collision samples, used *instead of* ``M_crit``/``err_crit``.
        points: More rope states fitted beside the critical term, each weighted as it:
            ``[(M_s (6N, 80), err_s (6N,)), ...]``, adding ``||M_s dk - err_s||_Q^2`` each.
        base_update: ``"constant"`` (one base update for all knots) or ``"zero"``.
        keep_rest: Add :func:`rest_equality_rows` (keep zero joint velocity at t = 0 and T).
        trust_region: If given, the box ``-r <= dk_arm <= r`` on each of the 56 arm knot
            entries [rad] (rows ``trust``): the linearised model is only trusted near the
            command it was taken about. None: no box (the paper's).
        center: c, the knot update (10, 8) or (80,) [rad] the control term pulls the step
            toward (its 56 arm entries): w_control ||dk_arm - c_arm||^2. None: c = 0 (the
            paper's).

    Returns:
        The QP.

    Raises:
        ConfigError: Missing or contradictory inputs, bad shapes or non-finite values.
    """
    weights = InverseModelWeights() if weights is None else weights
    check_choice("base_update", base_update, BASE_UPDATES)
    if equal is None:
        if M_crit is None or err_crit is None:
            raise ConfigError("M_crit", "M_crit and err_crit are required unless equal is given")
        terms = [(*_check_rows("M_crit", M_crit, err_crit), 1.0)]
    else:
        if M_crit is not None or err_crit is not None:
            raise ConfigError("equal", "give either M_crit/err_crit or equal, not both")
        if len(equal) == 0:
            raise ConfigError("equal", "must hold at least one (M, err) sample")
        terms = [(*_check_rows("equal", M, e), 1.0 / len(equal)) for M, e in equal]
    terms += [(*_check_rows("points", M, e), 1.0) for M, e in points]
    H = np.zeros((N_VARS, N_VARS))
    g = np.zeros(N_VARS)
    const = 0.0
    for M, err, scale in terms:
        Qd = scale * weights.critical_diagonal(M.shape[0])
        H += M.T @ (Qd[:, None] * M)
        g -= M.T @ (Qd * err)
        const += float(err @ (Qd * err))
    if follow is not None:
        at_tc = np.asarray(follow.is_tc, dtype=bool)[:, None]
        W = np.where(at_tc, weights.follow_weights(True), weights.follow_weights(False))  # (k, 9)
        J = np.ascontiguousarray(follow.J, dtype=float)
        H += weighted_gram(J, W)  # sum_t J_t^T W_t J_t
        g -= weighted_rhs(J, W, np.ascontiguousarray(follow.e, dtype=float))  # sum_t J_t^T W_t e_t
        const += float(np.sum(W * follow.e**2))
    H[ARM_COLUMNS, ARM_COLUMNS] += weights.w_control
    if center is not None:
        c = np.asarray(center, dtype=float).ravel()
        if c.shape != (N_VARS,):
            raise ConfigError("center", f"must have {N_VARS} entries, got {c.size}")
        _finite("center", c)
        g[ARM_COLUMNS] -= weights.w_control * c[ARM_COLUMNS]
        const += weights.w_control * float(c[ARM_COLUMNS] @ c[ARM_COLUMNS])
    P = 2.0 * H
    P = 0.5 * (P + P.T)  # exact symmetry against rounding in the sums
    E = base_equality_rows(base_update)
    blocks = {"base": (0, E.shape[0])}
    if keep_rest:
        R = rest_equality_rows()
        blocks["rest"] = (E.shape[0], E.shape[0] + R.shape[0])
        E = np.vstack([E, R])
    A_blocks = [E]
    l_blocks = [np.zeros(E.shape[0])]
    u_blocks = [np.zeros(E.shape[0])]
    if trust_region is not None:
        check_positive("trust_region", trust_region)
        off = sum(a.shape[0] for a in A_blocks)
        box = np.zeros((ARM_COLUMNS.size, N_VARS))
        box[np.arange(ARM_COLUMNS.size), ARM_COLUMNS] = 1.0
        A_blocks.append(box)
        l_blocks.append(np.full(ARM_COLUMNS.size, -float(trust_region)))
        u_blocks.append(np.full(ARM_COLUMNS.size, float(trust_region)))
        blocks["trust"] = (off, off + ARM_COLUMNS.size)
    if limits is not None:
        off = sum(a.shape[0] for a in A_blocks)
        A_blocks.append(-limits.J)
        l_blocks.append(limits.lo - limits.b)
        u_blocks.append(limits.hi - limits.b)
        for name, (a, z) in limits.blocks.items():
            blocks[name] = (off + a, off + z)
    return QPData(
        P=dense_csc(P),
        q=2.0 * g,
        A=dense_csc(np.vstack(A_blocks)),
        l=np.concatenate(l_blocks),
        u=np.concatenate(u_blocks),
        const=const,
        blocks=blocks,
    )


def dense_csc(D: np.ndarray) -> sp.csc_matrix:
    """The CSC matrix of a dense (m, n) array: its nonzeros column by column, rows ascending.

    The same arrays (data, indices, indptr) as ``scipy.sparse.csc_matrix(D)``, without its
    detour through COO (0.33 -> 0.22 ms for the bench problem's 306 x 80 constraint rows).
    """
    D = np.asarray(D, dtype=float)
    nz = D.T != 0  # (n, m)
    _, rows = np.nonzero(nz)
    index = np.int32 if max(rows.size, *D.shape) < np.iinfo(np.int32).max else np.int64
    indptr = np.zeros(D.shape[1] + 1, dtype=index)
    np.cumsum(np.count_nonzero(nz, axis=1), out=indptr[1:])
    return sp.csc_matrix((D.T[nz], rows.astype(index), indptr), shape=D.shape)


__all__ = [
    "BASE_UPDATES",
    "COLUMNS",
    "FollowThrough",
    "InverseModelWeights",
    "QPData",
    "base_equality_rows",
    "build_inverse_qp",
    "dense_csc",
    "rest_equality_rows",
]

"""Parameters, decision vector and sample grids of the initial-guess optimisation.

The problem (paper, section "Initial Guess") is stated and built in
:mod:`learner.initial_guess_problem` and solved in :mod:`learner.initial_guess`; this module
holds what both use: :class:`InitialGuessParams`, the map between the decision vector x (45,)
and the knots (:func:`knots_from_x`, :func:`x_from_knots`), the cost and limit sample grids
(:func:`cost_samples`, :func:`limit_sample_times`, :func:`hand_velocity`) and the rotation
errors (:func:`rotation_error_sq`, the optimiser's; :func:`rotation_log`, the reported one).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_KNOTS, N_ROWS, Z_MIN_TIP
from flyknot.errors import ConfigError, check_nonnegative, check_positive
from flyknot.limits import JointLimits

HOME_Q = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])  # xArm 7 home [rad]
HOME_Q.setflags(write=False)
POSITION_MARGIN = 1e-3  # [rad] kept free inside each joint's position range
COST_TERMS = ("position", "rotation", "velocity", "jerk")
LIMIT_BLOCKS = ("z", "pos", "vel", "acc", "tau")
N_FREE = N_KNOTS - 2  # free knot columns per joint (k_1 = k_0, k_6 = k_7)
N_X = N_JOINTS * N_FREE + 3  # 45

# E (6, 8): kappa_arm = C E, columns (k_0, k_2, k_3, k_4, k_5, k_7) -> knots 0..7.
FREE_TO_KNOTS = np.zeros((N_FREE, N_KNOTS))
FREE_TO_KNOTS[0, 0] = FREE_TO_KNOTS[0, 1] = 1.0
for _c in range(1, N_FREE - 1):
    FREE_TO_KNOTS[_c, _c + 1] = 1.0
FREE_TO_KNOTS[N_FREE - 1, N_KNOTS - 2] = FREE_TO_KNOTS[N_FREE - 1, N_KNOTS - 1] = 1.0
FREE_TO_KNOTS.setflags(write=False)
# (8,): the free column of each knot, (0, 0, 1, 2, 3, 4, 5, 5)
_KNOT_COLUMN = np.argmax(FREE_TO_KNOTS, axis=0)


# --------------------------------------------------------------------------------------------
# parameters
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class InitialGuessParams:
    """Weights, limits and solver settings of the initial-guess optimisation.

    Defaults are the paper's (appendix table "Demonstration Tracking Parameters"); ``w_r`` is
    the paper's w_R.

    Attributes:
        w_j: Jerk weight [s^6 / rad^2].
        w_p: Fingertip position weight [1 / m^2].
        w_r: Fingertip rotation weight [1 / rad^2].
        w_v: Fingertip velocity weight [s^2 / m^2].
        z_min: Lowest fingertip height at the start above the floor [m].
        base_height: Height of the robot base above the lab's floor [m] (the lab's
            calibration). Given, the start height is the lab's: z_tip(q(0)) + base_height
            >= z_min, so the rope hangs clear of the real floor whatever the base offset;
            None measures it in the demonstration frame: z_tip(q(0)) + b_z >= z_min.
        sample_rate_hz: Rate of the uniform cost grid [Hz]; None uses the demonstration's own
            samples.
        max_iter: IPOPT iteration limit (integer >= 1).
        limit_margin: Fraction of each velocity, acceleration and torque limit kept free,
            in [0, 1).
        tol: IPOPT's relative convergence tolerance, > 0.
        torque_limits: Impose |tau| <= (1 - limit_margin) tau_max at the limit samples.
        limits: Joint limits (default: the paper's).
    """

    w_j: float = 5e-7
    w_p: float = 10.0
    w_r: float = 0.2
    w_v: float = 0.5
    z_min: float = Z_MIN_TIP
    base_height: float | None = None
    sample_rate_hz: float | None = None
    max_iter: int = 500
    limit_margin: float = 0.05
    tol: float = 1e-6
    torque_limits: bool = True
    limits: JointLimits = field(default_factory=JointLimits)

    def __post_init__(self) -> None:
        for name in ("w_j", "w_p", "w_r", "w_v"):
            check_nonnegative(name, getattr(self, name))
        z = self.z_min
        if isinstance(z, bool) or not isinstance(z, numbers.Real) or not math.isfinite(z):
            raise ConfigError("z_min", f"must be a finite number [m], got {z!r}")
        if self.sample_rate_hz is not None:
            check_positive("sample_rate_hz", self.sample_rate_hz)
        if self.base_height is not None:
            check_nonnegative("base_height", self.base_height)
        mi = self.max_iter
        if isinstance(mi, bool) or not isinstance(mi, numbers.Integral) or mi < 1:
            raise ConfigError("max_iter", f"must be an integer >= 1, got {mi!r}")
        check_nonnegative("limit_margin", self.limit_margin)
        if self.limit_margin >= 1:
            raise ConfigError("limit_margin", f"must be < 1, got {self.limit_margin!r}")
        check_positive("tol", self.tol)
        if not isinstance(self.torque_limits, bool):
            raise ConfigError(
                "torque_limits", f"unknown value {self.torque_limits!r}", [True, False]
            )
        if not isinstance(self.limits, JointLimits):
            raise ConfigError("limits", f"must be a JointLimits, got {type(self.limits).__name__}")


# --------------------------------------------------------------------------------------------
# pure kernels
# --------------------------------------------------------------------------------------------


def hand_velocity(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Demonstration hand velocity by finite differences on its own samples.

    pdot_i = (p_{i+1} - p_{i-1}) / (t_{i+1} - t_{i-1}) on a uniform grid (numpy.gradient's
    second-order formula on a non-uniform one), pdot_0 = (p_1 - p_0) / (t_1 - t_0) and
    likewise backwards at the last sample.

    Args:
        t: Sample times, shape (k,) [s], strictly increasing, k >= 2.
        p: Hand positions, shape (k, 3) [m].

    Returns:
        Velocities, shape (k, 3) [m/s].
    """
    return np.gradient(np.asarray(p, dtype=float), np.asarray(t, dtype=float), axis=0)


def rotation_error_sq(R_h: np.ndarray, R_tip: np.ndarray) -> np.ndarray:
    """Smooth squared rotation error, the quaternion vector part of E = R_h^T R_tip.

    ||2 v||^2 = 4 sin^2(theta / 2) = 3 - tr(R_h^T R_tip) = 3 - sum_ab R_h[a, b] R_tip[a, b],
    theta = |Log(E)|.

    Args:
        R_h: Desired orientations, shape (m, 3, 3).
        R_tip: Fingertip orientations, shape (m, 3, 3).

    Returns:
        Squared errors, shape (m,) [rad^2-like, in [0, 4]].
    """
    return 3.0 - np.einsum("mab,mab->m", np.asarray(R_h), np.asarray(R_tip))


def rotation_log(R_h: np.ndarray, R_tip: np.ndarray) -> np.ndarray:
    """Exact rotation error Log(R_h^T R_tip) (rotation vector, |Log| = theta in [0, pi]).

    Args:
        R_h: Desired orientations, shape (m, 3, 3).
        R_tip: Fingertip orientations, shape (m, 3, 3).

    Returns:
        Rotation vectors, shape (m, 3) [rad], in the desired (R_h) frame.
    """
    E = np.einsum("mba,mbc->mac", np.asarray(R_h), np.asarray(R_tip))
    return Rotation.from_matrix(E).as_rotvec()


def knots_from_x(x: np.ndarray) -> np.ndarray:
    """Knots (10, 8) of the decision vector x (45,).

    kappa[0:7] = C E with C = x[:42] as (7, 6) row-major and E the (6, 8) 0/1 map
    (k_1 = k_0, k_6 = k_7); kappa[7:10, :] = x[42:45] repeated.

    Args:
        x: Decision vector, shape (45,) ([rad] then [m]).

    Returns:
        Knots, shape (10, 8).
    """
    x = np.asarray(x, dtype=float)
    if x.shape != (N_X,):
        raise ConfigError("x", f"must have shape ({N_X},), got {x.shape}")
    C = x[: N_JOINTS * N_FREE].reshape(N_JOINTS, N_FREE)
    out = np.empty((N_ROWS, N_KNOTS))
    out[:N_JOINTS] = C[:, _KNOT_COLUMN]  # = C E, by indexing so the ties are bitwise
    out[N_JOINTS:] = x[N_JOINTS * N_FREE :, None]
    return out


def x_from_knots(knots: np.ndarray) -> np.ndarray:
    """Inverse of :func:`knots_from_x` for knots with k_1 = k_0, k_6 = k_7, constant base rows.

    Args:
        knots: Knots, shape (10, 8).

    Returns:
        Decision vector, shape (45,).

    Raises:
        ConfigError: The knots do not have the tied end columns or a constant base.
    """
    k = np.asarray(knots, dtype=float)
    if k.shape != (N_ROWS, N_KNOTS):
        raise ConfigError("knots", f"must have shape ({N_ROWS}, {N_KNOTS}), got {k.shape}")
    arm = k[:N_JOINTS]
    if not (np.array_equal(arm[:, 0], arm[:, 1]) and np.array_equal(arm[:, -1], arm[:, -2])):
        raise ConfigError("knots", "arm rows need knot 1 = knot 0 and knot 6 = knot 7")
    if not np.all(k[N_JOINTS:] == k[N_JOINTS:, :1]):
        raise ConfigError("knots", "base-offset rows must be constant across the knots")
    C = arm[:, [0, 2, 3, 4, 5, 7]]
    return np.concatenate([C.ravel(), k[N_JOINTS:, 0]])


def limit_sample_times(T: float, rate_hz: float = COMMAND_RATE_HZ) -> np.ndarray:
    """Times the limits are imposed at: the command's samples i / rate_hz <= T, the samples
    the controllers check (a T between two samples is never commanded: the arm holds the last
    sample).

    Args:
        T: Command duration [s], > 0.
        rate_hz: Command rate [Hz].

    Returns:
        Times, shape (n,) [s], a uniform grid from 0.
    """
    n = int(np.floor(T * rate_hz + 1e-9)) + 1
    return np.minimum(np.arange(n) / rate_hz, T)


def cost_samples(
    t: np.ndarray, p: np.ndarray, R: np.ndarray, sample_rate_hz: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cost grid and the demonstration on it.

    v = :func:`hand_velocity` (t, p) on the demonstration samples; with a rate, the grid is
    n = ceil((t_k - t_1) rate) + 1 uniform times over [t_1, t_k], p and v interpolated
    linearly and R by slerp; without one the grid is t itself.

    Args:
        t: Demonstration times, shape (k,) [s].
        p: Hand positions, shape (k, 3) [m].
        R: Hand orientations, shape (k, 3, 3).
        sample_rate_hz: Grid rate [Hz] or None.

    Returns:
        ``(t_i (m,) [s], p_h (m, 3) [m], R_h (m, 3, 3), v_h (m, 3) [m/s])``.
    """
    v = hand_velocity(t, p)
    if sample_rate_hz is None:
        return t, p, R, v
    n = max(2, int(np.ceil((t[-1] - t[0]) * sample_rate_hz - 1e-9)) + 1)
    ti = np.linspace(t[0], t[-1], n)
    pi = np.stack([np.interp(ti, t, p[:, a]) for a in range(3)], axis=1)
    vi = np.stack([np.interp(ti, t, v[:, a]) for a in range(3)], axis=1)
    Ri = Slerp(t, Rotation.from_matrix(R))(ti).as_matrix()
    return ti, pi, Ri, vi


__all__ = [
    "COST_TERMS",
    "FREE_TO_KNOTS",
    "HOME_Q",
    "LIMIT_BLOCKS",
    "N_FREE",
    "N_X",
    "POSITION_MARGIN",
    "InitialGuessParams",
    "cost_samples",
    "hand_velocity",
    "knots_from_x",
    "limit_sample_times",
    "rotation_error_sq",
    "rotation_log",
    "x_from_knots",
]

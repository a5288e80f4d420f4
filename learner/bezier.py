"""The learner's command: 10 Bezier curves of degree 7 over [0, T] (paper, appendix "Command
Parametrization").

The knots ``kappa`` have shape (10, 8): rows 0-6 are the joints [rad], rows 7-9 the base offset
(x, y, z) [m]; column i is the i-th control point, the control points being equally spaced in
time over [0, T]. A row's value at time t is

    B(kappa, T)(t) = sum_{i=0}^{7} kappa[:, i] b_i^7(t / T),
    b_i^n(s) = C(n, i) s^i (1 - s)^(n - i),  s in [0, 1].

Everything here is linear in the knots, so the Jacobian of any sample with respect to the knots is
the Bernstein basis itself (:func:`sample_jacobian`).
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache
from math import comb, factorial

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ, N_BASE_ROWS, N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import ConfigError, check_choice, check_positive
from flyknot.limits import difference_matrices
from flyknot.record import JointCommand

DEGREE = N_KNOTS - 1  # 7
DERIVATIVES = (0, 1, 2, 3)
# Relative tolerance (of T) within which sample times slightly outside [0, T] are clipped.
_T_SLACK = 1e-9
# Base-offset rows count as constant when every knot is within this of the row's first knot
# (absolute [m] + relative).
_BASE_ATOL = 1e-12
_BASE_RTOL = 1e-9


def _float_T(T: object) -> float:
    """Validate the duration T and return it as a float [s]."""
    if isinstance(T, numbers.Real) and not isinstance(T, bool):
        T = float(T)
    check_positive("T", T)  # type: ignore[arg-type]
    return T  # type: ignore[return-value]


def _times(t: object, T: float) -> np.ndarray:
    """Validate sample times, shape (m,) [s], inside [0, T] up to rounding; clip the rounding."""
    t = np.asarray(t, dtype=float)
    if t.ndim == 0:
        t = t[None]
    if t.ndim != 1:
        raise ConfigError("t", f"must be a 1-D array of times [s], got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ConfigError("t", "must be finite")
    slack = _T_SLACK * T
    if t.size and (t.min() < -slack or t.max() > T + slack):
        raise ConfigError(
            "t",
            f"must lie in [0, T] = [0, {T:g}] s, got values in [{t.min():g}, {t.max():g}]",
        )
    return np.clip(t, 0.0, T)


def _derivative(derivative: object) -> int:
    check_choice("derivative", derivative, DERIVATIVES)
    return int(derivative)  # type: ignore[call-overload]


def _bernstein_s(s: np.ndarray, n: int) -> np.ndarray:
    """Bernstein polynomials of degree n, b_i^n(s) = C(n, i) s^i (1 - s)^(n - i).

    Args:
        s: Normalised times, shape (m,) in [0, 1].
        n: Degree (>= 0).

    Returns:
        Basis values, shape (m, n + 1).
    """
    i = np.arange(n + 1)
    binom = np.array([comb(n, k) for k in i], dtype=float)
    return binom * s[:, None] ** i * (1.0 - s[:, None]) ** (n - i)


def bernstein_basis(t: np.ndarray, T: float, derivative: int = 0) -> np.ndarray:
    """Time derivatives of the degree-7 Bernstein basis over [0, T].

    With s = t / T and n = 7, the r-th time derivative is

        d^r/dt^r b_i^n(t / T)
            = T^-r n! / (n - r)! sum_{j=0}^{r} (-1)^(r - j) C(r, j) b_{i-j}^{n-r}(s),

    where b_k^m = 0 for k < 0 or k > m. A curve's r-th derivative is ``basis @ knots.T``.

    Args:
        t: Sample times, shape (m,) [s], within [0, T].
        T: Duration of the command [s], > 0.
        derivative: Order r of the time derivative, one of 0, 1, 2, 3.

    Returns:
        Basis, shape (m, 8) [1 / s^r].

    Raises:
        ConfigError: for T <= 0, times outside [0, T] or an unknown derivative order.
    """
    T = _float_T(T)
    r = _derivative(derivative)
    s = _times(t, T) / T
    n = DEGREE
    if r == 0:
        return _bernstein_s(s, n)
    lower = _bernstein_s(s, n - r)  # (m, n - r + 1)
    out = np.zeros((s.shape[0], n + 1))
    for j in range(r + 1):
        out[:, j : j + n - r + 1] += (-1) ** (r - j) * comb(r, j) * lower
    return out * (factorial(n) / factorial(n - r)) / T**r


def _grid_step(t: np.ndarray) -> float:
    """Spacing of a uniform sample grid from 0 [s] (a single sample: the command period)."""
    if t.size < 2:
        return 1.0 / COMMAND_RATE_HZ
    dt = float(t[1] - t[0])
    if t[0] != 0.0 or dt <= 0 or np.abs(np.diff(t) - dt).max() > 1e-9 * max(1.0, dt):
        raise ConfigError("t", "must be a uniform grid of sample times from 0 (a command's)")
    return dt


def controller_basis(t: np.ndarray, T: float, derivative: int = 0) -> np.ndarray:
    """The basis of a command's samples and of their derivatives as the controllers take them.

        b_c^(0) = b^(0)(t),   b_c^(r) = D_r b^(0)(t)   (r = 1, 2)

    with D_1, D_2 the central differences with rest padding at the grid's spacing
    (:func:`flyknot.limits.difference_matrices`): the velocity and acceleration the simulated
    controller faults on and the hardware preflight refuses on. They differ from the analytic
    derivatives by ~dt^2 / 6 times the next-higher derivative (0.1 % of the velocity limit at
    250 Hz in a fast throw), enough to push a command bounded analytically at the margin past it.

    Args:
        t: Sample times, shape (m,) [s]: a uniform grid from 0 within [0, T].
        T: Duration of the command [s], > 0.
        derivative: Order r, one of 0, 1, 2.

    Returns:
        Basis, shape (m, 8) [1 / s^r], read-only (one array per grid, T and r is kept: an
        update asks for the same grid's bases several times).
    """
    check_choice("derivative", derivative, (0, 1, 2))
    t = np.ascontiguousarray(t, dtype=float)
    if t.ndim != 1:
        return _controller_basis(t, T, derivative)  # raises the shape's ConfigError
    return _controller_basis_of(t.tobytes(), _float_T(T), int(derivative))


@lru_cache(maxsize=16)
def _controller_basis_of(t_bytes: bytes, T: float, derivative: int) -> np.ndarray:
    out = _controller_basis(np.frombuffer(t_bytes, dtype=float), T, derivative)
    out.setflags(write=False)
    return out


def _controller_basis(t: np.ndarray, T: float, derivative: int) -> np.ndarray:
    basis = bernstein_basis(t, T, 0)
    if derivative == 0:
        return basis
    return difference_matrices(basis.shape[0], _grid_step(t))[derivative - 1] @ basis


def controller_jacobian(t: np.ndarray, T: float, derivative: int = 0) -> np.ndarray:
    """:func:`basis_jacobian` of :func:`controller_basis`: d q_c^(r) / d kappa of every sample
    and joint, shape (m * 7, 80) [1 / s^r], read-only.

    It depends on the grid, T and r only, so one array per grid is kept (an update's limit
    rows ask for the same three at every update of a run).
    """
    controller_basis(t, T, derivative)  # checks the arguments (and keeps the basis)
    t_bytes = np.ascontiguousarray(t, dtype=float).tobytes()
    return _controller_jacobian_of(t_bytes, _float_T(T), int(derivative))


@lru_cache(maxsize=8)
def _controller_jacobian_of(t_bytes: bytes, T: float, derivative: int) -> np.ndarray:
    out = basis_jacobian(_controller_basis_of(t_bytes, T, derivative))
    out.setflags(write=False)
    return out


def check_knots(knots: object, field: str = "knots") -> np.ndarray:
    """Knots as a float array (10, 8); ConfigError naming ``field`` if malformed."""
    k = np.asarray(knots, dtype=float)
    if k.shape != (N_ROWS, N_KNOTS):
        raise ConfigError(field, f"must have shape ({N_ROWS}, {N_KNOTS}), got {k.shape}")
    if not np.all(np.isfinite(k)):
        r, c = np.argwhere(~np.isfinite(k))[0]
        raise ConfigError(field, f"must be finite; first non-finite value at row {r}, knot {c}")
    return k


def sample_command(knots: np.ndarray, T: float, t: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Sample all 10 curves (or a time derivative) at times t.

    y^(r)(t) = b^(r)(t) kappa^T, with b^(r) from :func:`bernstein_basis`.

    Args:
        knots: Knots kappa, shape (10, 8) (rows 0-6 [rad], rows 7-9 [m]).
        T: Duration [s].
        t: Sample times, shape (m,) [s].
        derivative: Order r of the time derivative, 0..3.

    Returns:
        Samples, shape (m, 10) [rad / s^r for rows 0-6, m / s^r for rows 7-9].
    """
    return bernstein_basis(t, T, derivative) @ check_knots(knots).T


def _rows(rows: Iterable[int]) -> list[int]:
    rows = list(rows)
    valid = range(N_ROWS)
    if not rows:
        raise ConfigError("rows", "must not be empty", valid)
    for r in rows:
        if isinstance(r, bool) or not isinstance(r, numbers.Integral) or r not in valid:
            raise ConfigError("rows", f"unknown row {r!r}", valid)
    return [int(r) for r in rows]


def sample_jacobian(
    t: np.ndarray, T: float, derivative: int = 0, rows: Iterable[int] = range(N_JOINTS)
) -> np.ndarray:
    """Jacobian of the flattened samples with respect to the flattened knots.

    With Y = sample_command(kappa, T, t, r)[:, rows] flattened row-major (sample a, row index c at
    a * len(rows) + c) and kappa flattened row-major (knot (row q, j) at q * 8 + j):

        d Y[a, c] / d kappa[q, j] = delta(q, rows[c]) b_j^(r)(t_a).

    Args:
        t: Sample times, shape (m,) [s].
        T: Duration [s].
        derivative: Order r of the time derivative, 0..3.
        rows: Curve rows to keep (default the 7 joints).

    Returns:
        Jacobian, shape (m * len(rows), 80) [1 / s^r].
    """
    return basis_jacobian(bernstein_basis(t, T, derivative), rows)


def basis_jacobian(basis: np.ndarray, rows: Iterable[int] = range(N_JOINTS)) -> np.ndarray:
    """:func:`sample_jacobian` of samples ``basis @ knots.T`` for any basis (m, 8), e.g.
    :func:`controller_basis`: shape (m * len(rows), 80)."""
    rows = _rows(rows)
    select = np.zeros((len(rows), N_ROWS))
    select[np.arange(len(rows)), rows] = 1.0
    jac = basis[:, None, None, :] * select[None, :, :, None]  # (m, rows, 10, 8)
    return jac.reshape(basis.shape[0] * len(rows), N_ROWS * N_KNOTS)


@dataclass(frozen=True)
class BezierCommand:
    """A command: knots kappa (10, 8) and duration T.

    Attributes:
        knots: Control points, shape (10, 8); rows 0-6 joints [rad], rows 7-9 the base offset
            (x, y, z) [m], constant across the 8 knots (the base never moves within a trial).
        T: Duration [s], > 0.
    """

    knots: np.ndarray
    T: float

    def __post_init__(self) -> None:
        k = check_knots(self.knots).copy()
        T = _float_T(self.T)
        base = k[N_JOINTS:]
        spread = np.abs(base - base[:, :1])
        bad = spread > _BASE_ATOL + _BASE_RTOL * np.abs(base[:, :1])
        if bad.any():
            r = int(np.argwhere(bad)[0, 0])
            raise ConfigError(
                "knots",
                f"base-offset row {N_JOINTS + r} must be constant across the {N_KNOTS} knots, "
                f"varies by {spread[r].max():.3g} m",
            )
        k.setflags(write=False)
        object.__setattr__(self, "knots", k)
        object.__setattr__(self, "T", T)

    @property
    def base_offset(self) -> np.ndarray:
        """Base offset (x, y, z), shape (3,) [m]."""
        return self.knots[N_JOINTS : N_JOINTS + N_BASE_ROWS, 0].copy()

    @property
    def knot_times(self) -> np.ndarray:
        """Times the control points are attached to, i T / 7, shape (8,) [s]."""
        return np.linspace(0.0, self.T, N_KNOTS)

    def sample(self, t: np.ndarray, derivative: int = 0) -> np.ndarray:
        """All 10 curves at times t, shape (m, 10); see :func:`sample_command`."""
        return sample_command(self.knots, self.T, t, derivative)

    def sample_times(self, rate_hz: float = COMMAND_RATE_HZ) -> np.ndarray:
        """Times 0, 1/rate, 2/rate, ... up to T inclusive, shape (n,) [s]."""
        check_positive("rate_hz", float(rate_hz))
        n = int(np.floor(self.T * rate_hz + 1e-9)) + 1
        return np.minimum(np.arange(n) / rate_hz, self.T)

    def joint_command(self, rate_hz: float = COMMAND_RATE_HZ) -> JointCommand:
        """Joint targets q(t) = B(kappa, T)(t)[:7] at t = i / rate_hz up to T inclusive.

        Returns:
            A :class:`JointCommand` of shape (n, 7) [rad] at ``rate_hz``.
        """
        t = self.sample_times(rate_hz)
        q = bernstein_basis(t, self.T) @ self.knots[:N_JOINTS].T
        return JointCommand(q, rate_hz=float(rate_hz))

"""The flying-knot hand motion family: 23 numbers, five Bezier curves, a wind-up time warp.

A person ties the overhand flying knot with one hand: from rest, an upward twisting motion
throws a loop, an arc strikes near the rope's end so the end flips through the loop, and a
follow-through brings the hand to rest. Here that motion is a small family
Here that motion is a small family (:class:`KnotMotion`), played by the free hand of
:mod:`flyknot_sim.hand` (a motion is a :class:`flyknot_sim.hand_params.JointTrajectory`);
the offline demonstration search looks in it for members that tie the knot (see
``docs/demo-synthesis.md``), and :mod:`flyknot_sim.hand_replay` plays a stored member again.

Motion family (23 numbers, :data:`PARAM_NAMES`): duration T, a wind-up (p, r) and five
degree-8 Bezier curves for the hand position (x, y, z) relative to its start and the wrist
angles a (about x) and b (about y, applied after a: R = Ry(b) Rx(a) Rz(0)):

    y(t) = sum_{i=0}^{8} Y_i b_i^8(s(t / T)),   b_i^n(s) = C(n, i) s^i (1 - s)^(n - i),

where s(u) (:func:`windup_warp`) plays the first fraction p of the time at r times the speed
of the rest: a slow wind-up before the throw (p = 0 or r = 1: s(u) = u, the feasibility
study's 21-number family). Measured: scaling the whole motion in time keeps the knot only
within about +-3 % of the duration, while slowing its gentle first 0.1-0.2 s keeps it, so
slower demonstrations differ from fast ones mainly in the wind-up. Control points 0-2 of
each curve are tied to the start (0) and 6-8 to the end value,
so y' = y'' = 0 at both ends: every motion starts and ends at rest. Free: Y_3, Y_4, Y_5 and the
end Y_8 per curve (4 x 5 = 20).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from math import comb, factorial

import numpy as np

from flyknot.errors import ConfigError, RecordError

DEGREE = 8
N_PARAMS = 23
N_HEAD = 3
"""Numbers before the curves' control points: T, p, r."""
CURVES = ("x", "y", "z", "a", "b")
PARAM_NAMES = ("T", "p", "r", *(f"{c}{i}" for c in CURVES for i in ("3", "4", "5", "e")))
"""Names of the 23 numbers: T [s], the wind-up fraction p and speed r [-], then per curve
x, y, z [m], a, b [rad] the control points Y_3, Y_4, Y_5 and the end value
Y_e (= Y_6 = Y_7 = Y_8)."""
IDENTITY_WARP = (0.0, 1.0)
"""(p, r) of no wind-up."""
WINDUP_MAX = 0.6
"""Largest wind-up fraction p."""
WINDUP_SPEED_MIN = 0.1
"""Smallest wind-up speed r."""
BLEND = 0.1
"""Half-width of the wind-up's smooth speed change, in units of T."""
MIN_BLEND = 1e-9
"""A shorter half-width is no wind-up (and pi / (2 d) would overflow)."""


# ----------------------------------------------------------------------------------------
# Bezier kernels
# ----------------------------------------------------------------------------------------
def bernstein(s: np.ndarray, degree: int = DEGREE, order: int = 0) -> np.ndarray:
    """Bernstein basis of ``degree`` n or its ``order``-th derivative in s.

    b_i^n(s) = C(n, i) s^i (1 - s)^(n - i); the r-th derivative is
    d^r b_i^n / ds^r = n! / (n - r)! sum_{j=0}^{r} (-1)^(r - j) C(r, j) b_{i-j}^{n-r}(s)
    (terms with i - j outside [0, n - r] vanish).

    Args:
        s: Parameters, shape (T,) [-], in [0, 1].
        degree: n >= 0.
        order: Derivative order r in 0..n.

    Returns:
        Shape (T, n + 1).
    """
    if order < 0 or order > degree:
        raise ConfigError("order", f"must lie in 0..{degree}, got {order!r}")
    s = np.asarray(s, dtype=float).reshape(-1, 1)
    m = degree - order
    k = np.arange(m + 1)
    low = np.array([comb(m, int(i)) for i in k], dtype=float) * s**k * (1.0 - s) ** (m - k)
    out = np.zeros((s.shape[0], degree + 1))
    for j in range(order + 1):
        out[:, j : j + m + 1] += (-1) ** (order - j) * comb(order, j) * low
    return out * (factorial(degree) / factorial(m))


def windup_warp(u: np.ndarray, p: float, r: float, order: int = 0) -> np.ndarray:
    """Time warp with a slow wind-up: s(u) and its derivatives, u = t / T in [0, 1].

    s'(u) = B (r + (1 - r) h(u)), with h a smooth step from 0 to 1 centred at p of
    half-width d = min(BLEND, p, 1 - p): h = 0 for u <= p - d, 1 for u >= p + d and
    h = (1 - cos(pi (u - p + d) / (2 d))) / 2 between. As the integral of h over [0, 1] is
    1 - p, B = 1 / (1 - p (1 - r)) makes s(1) = 1:

        s(u) = B (r u + (1 - r) H(u)),  H(u) = int_0^u h,
        H = 0, (u - p + d) / 2 - (d / pi) sin(pi (u - p + d) / (2 d)), u - p
        (before, inside, after the step); s'' = B (1 - r) h'(u),
        h' = (pi / (4 d)) sin(pi (u - p + d) / (2 d)) inside the step, else 0.

    s is monotone (s' >= B r > 0), s'(1) = B, s''(0) = s''(1) = 0; r = 1, or a blend
    d <= ``MIN_BLEND`` (p near 0 or 1), gives s(u) = u.

    Args:
        u: Normalised times, shape (k,) [-], in [0, 1].
        p: Wind-up fraction of the time, in [0, 1).
        r: Wind-up speed relative to the rest, in (0, 1].
        order: 0 (s), 1 (ds/du) or 2 (d^2 s/du^2).

    Returns:
        Shape (k,) [-].
    """
    if order not in (0, 1, 2):
        raise ConfigError("order", f"must be 0, 1 or 2, got {order!r}")
    u = np.asarray(u, dtype=float).ravel()
    b = 1.0 / (1.0 - p * (1.0 - r))
    d = min(BLEND, p, 1.0 - p)
    if d <= MIN_BLEND or r >= 1.0:  # no wind-up: the identity
        return u.copy() if order == 0 else np.full_like(u, 1.0 if order == 1 else 0.0)
    lo, hi = p - d, p + d
    inside = (u > lo) & (u < hi)
    phase = np.pi * (u - lo) / (2.0 * d)
    if order == 0:
        big_h = np.where(u <= lo, 0.0, np.where(u >= hi, u - p, 0.0))
        big_h[inside] = (u[inside] - lo) / 2.0 - (d / np.pi) * np.sin(phase[inside])
        return b * (r * u + (1.0 - r) * big_h)
    if order == 1:
        h = np.where(u >= hi, 1.0, 0.0)
        h[inside] = (1.0 - np.cos(phase[inside])) / 2.0
        return b * (r + (1.0 - r) * h)
    dh = np.zeros_like(u)
    dh[inside] = np.pi / (4.0 * d) * np.sin(phase[inside])
    return b * (1.0 - r) * dh


def tie_matrix() -> np.ndarray:
    """Map (Y_3, Y_4, Y_5, Y_e) to the 9 control points (start tied to 0), shape (9, 4)."""
    m = np.zeros((DEGREE + 1, 4))
    m[3, 0] = m[4, 1] = m[5, 2] = 1.0
    m[6:, 3] = 1.0
    return m


_TIE = tie_matrix()


# ----------------------------------------------------------------------------------------
# the motion family
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class KnotMotion:
    """One member of the flying-knot motion family (see the module docstring).

    Attributes:
        x: The 23 numbers in the order of :data:`PARAM_NAMES` [s, -, m, rad].
    """

    x: np.ndarray

    def __post_init__(self) -> None:
        x = np.array(self.x, dtype=float, copy=True).ravel()
        if x.shape != (N_PARAMS,):
            raise ConfigError("KnotMotion.x", f"must hold {N_PARAMS} numbers, got {x.size}")
        if not np.all(np.isfinite(x)):
            raise ConfigError("KnotMotion.x", "must be finite")
        if not 0.1 <= x[0] <= 5.0:
            raise ConfigError("KnotMotion.T", f"must lie in [0.1, 5] s, got {float(x[0])!r}")
        if not 0.0 <= x[1] <= WINDUP_MAX:
            raise ConfigError("KnotMotion.p", f"must lie in [0, {WINDUP_MAX}], got {float(x[1])!r}")
        if not WINDUP_SPEED_MIN <= x[2] <= 1.0:
            raise ConfigError(
                "KnotMotion.r", f"must lie in [{WINDUP_SPEED_MIN}, 1], got {float(x[2])!r}"
            )
        x.setflags(write=False)
        object.__setattr__(self, "x", x)

    @property
    def duration(self) -> float:
        """T [s]."""
        return float(self.x[0])

    def free_points(self) -> np.ndarray:
        """(Y_3, Y_4, Y_5, Y_e) per curve x, y, z, a, b, shape (4, 5) [m, rad]."""
        return self.x[N_HEAD:].reshape(5, 4).T.copy()

    def control_points(self) -> np.ndarray:
        """All 9 control points of the curves x, y, z, a, b, shape (9, 5) [m, rad]."""
        return _TIE @ self.free_points()

    @property
    def core_duration(self) -> float:
        """Duration of the unwarped motion, T (1 - p (1 - r)) [s] (see :func:`windup_warp`)."""
        return self.duration * (1.0 - float(self.x[1]) * (1.0 - float(self.x[2])))

    def warp(self, u: np.ndarray, order: int = 0) -> np.ndarray:
        """The time warp s(u) or its derivative, see :func:`windup_warp`."""
        return windup_warp(u, float(self.x[1]), float(self.x[2]), order)

    def with_windup(self, duration: float, speed: float) -> KnotMotion:
        """The same unwarped motion preceded by a slow wind-up so it lasts ``duration``.

        Keeps the core duration T_c (:attr:`core_duration`) and sets r = ``speed``,
        p = (1 - T_c / T') / (1 - r) for the new duration T' >= T_c.

        Raises:
            ConfigError: ``duration`` shorter than the core, or p beyond its bound.
        """
        core = self.core_duration
        if duration < core - 1e-12:
            raise ConfigError("duration", f"must be >= the core duration {core:.4g} s")
        if not WINDUP_SPEED_MIN <= speed < 1.0:
            raise ConfigError("speed", f"must lie in [{WINDUP_SPEED_MIN}, 1), got {speed!r}")
        p = (1.0 - core / duration) / (1.0 - speed)
        x = self.x.copy()
        x[0], x[1], x[2] = duration, p, speed
        return KnotMotion(x)

    def curves(self, t: np.ndarray, order: int = 0) -> np.ndarray:
        """The curves or their time derivatives at ``t`` (held outside [0, T]).

        With u = clip(t / T, 0, 1), s = s(u) and B(s) = sum_i Y_i b_i^8(s):
        y = B(s), y' = B'(s) s' / T, y'' = (B''(s) s'^2 + B'(s) s'') / T^2 (primes on B in s,
        on s in u); derivatives are 0 outside [0, T] (the motion is at rest there).

        Args:
            t: Times from the motion's start, shape (k,) [s].
            order: 0, 1 or 2.

        Returns:
            Shape (k, 5): x, y, z [m], a, b [rad] (per s^order).
        """
        if order not in (0, 1, 2):
            raise ConfigError("order", f"must be 0, 1 or 2, got {order!r}")
        t = np.asarray(t, dtype=float).ravel()
        T = self.duration
        u = np.clip(t / T, 0.0, 1.0)
        s = np.clip(self.warp(u), 0.0, 1.0)
        cp = self.control_points()
        if order == 0:
            return bernstein(s, DEGREE) @ cp
        s1 = self.warp(u, 1)[:, None]
        b1 = bernstein(s, DEGREE, 1) @ cp
        if order == 1:
            y = b1 * s1 / T
        else:
            s2 = self.warp(u, 2)[:, None]
            y = ((bernstein(s, DEGREE, 2) @ cp) * s1**2 + b1 * s2) / T**2
        y[(t < 0) | (t > T)] = 0.0
        return y

    def joint_targets(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hand joint targets (x, y, z, b, a, c = 0) at ``t`` (k,) [s]: q, qd, qdd (k, 6)."""
        out = []
        for order in range(3):
            y = self.curves(t, order)
            out.append(np.column_stack([y[:, :3], y[:, 4], y[:, 3], np.zeros(len(y))]))
        return out[0], out[1], out[2]

    def hand_limits(self, dt: float = 0.001) -> tuple[float, float]:
        """Peak hand speed max_t |p'(t)| [m/s] and excursion max_t |p(t) - p(0)| [m],
        sampled every ``dt`` over [0, T]."""
        t = np.linspace(0.0, self.duration, max(3, math.ceil(self.duration / dt) + 1))
        v = self.curves(t, 1)[:, :3]
        p = self.curves(t, 0)[:, :3]
        return float(np.linalg.norm(v, axis=1).max()), float(np.linalg.norm(p, axis=1).max())

    def mirrored(self) -> KnotMotion:
        """The mirror image in the x-z plane: y -> -y and a -> -a (b unchanged).

        With S = diag(1, -1, 1): S Rx(a) S = Rx(-a), S Ry(b) S = Ry(b), so the mirrored
        hand turns the opposite way about x and ties the knot of opposite handedness.
        """
        fp = self.free_points()
        fp[:, 1] *= -1.0
        fp[:, 3] *= -1.0
        return KnotMotion(np.concatenate([self.x[:N_HEAD], fp.T.ravel()]))

    def to_dict(self) -> dict[str, float]:
        """The 23 numbers by name (for metadata)."""
        return {n: float(v) for n, v in zip(PARAM_NAMES, self.x, strict=True)}

    @classmethod
    def from_dict(cls, values: Mapping[str, float]) -> KnotMotion:
        """Inverse of :meth:`to_dict`.

        Raises:
            RecordError: A name is missing.
        """
        missing = [n for n in PARAM_NAMES if n not in values]
        if missing:
            raise RecordError(f"motion parameters lack {', '.join(missing)}")
        return cls(np.array([float(values[n]) for n in PARAM_NAMES]))

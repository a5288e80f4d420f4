"""Synthetic human demonstrations of the flying knot: motion family, score, search, replay.

A person ties the overhand flying knot with one hand: from rest, an upward twisting motion
throws a loop, an arc strikes near the rope's end so the end flips through the loop, and a
follow-through brings the hand to rest. Here that motion is a small family
(:class:`KnotMotion`), played by the free hand of :mod:`flyknot_sim.hand`, and searched with
CMA-ES for members that tie the knot and keep tying it under the lab's trial-to-trial
variation. See ``docs/demo-synthesis.md`` for the measured budgets and hit rates.

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
end Y_8 per curve (4 x 5 = 20). Angle control points are bounded to +-300 degrees (without a
bound a search drifts to multi-turn wrist spins).

Score of one trial (:func:`score`; ``docs/demo-synthesis.md`` has the reasoning):

    S = 100 [knot at the end] + 30 f_settle + 10 [knot at any judged frame]
        + 5 [rope self-contact] + 5 min(|Wr|_max, 3) / 3
        - 20 max(0, v_peak - 8 m/s) - 100 max(0, e_max - 0.7 m) - 100 g_variant

with f_settle the knotted fraction of the judged settling frames, Wr the writhe of the
centreline (largest over judged frames), v_peak and e_max the target hand's peak speed and
largest distance from its start, and g_variant a variant's own constraint violation (e.g.
the Swipe's strike must travel as far horizontally as it drops). Motions that break the
speed, excursion or
variant limits are not simulated; they score -10 minus the penalty.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from math import comb, factorial
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import DEMOS_DIR
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError, check_choice, check_positive
from flyknot.knot import TREFOIL
from flyknot.progress import bar_disable
from flyknot_sim.hand import (
    HandLab,
    HandParams,
    HandTrial,
    HandVariation,
    hand_rotation,
    trial_demonstration,
)
from flyknot_sim.mocap import MocapParams

GENERATOR = "flyknot_tools.demo_synth"
GENERATOR_VERSION = 1
"""Bump when a change alters what a given (variant, seed) produces."""

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

ANGLE_BOUND = math.radians(300.0)
"""Bound of the wrist-angle control points [rad]."""
VIA_BOUND = 1.2
"""Bound of the position control points Y_3..Y_5 [m] (the path's excursion is limited
separately)."""
END_BOUND = 0.6
"""Bound of the end position [m]."""
SPEED_LIMIT = 8.0
"""Largest hand speed of a human demonstrator [m/s] (penalised above)."""
EXCURSION_LIMIT = 0.7
"""Largest distance of the hand from its start [m] (penalised above)."""

REFERENCE_MOTION = DEMOS_DIR / "seed_reference_hand_motion_rope1.csv"
"""The feasibility study's flying-knot hand motion (measured data, a search seed)."""


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

    s is monotone (s' >= B r > 0), s'(1) = B, s''(0) = s''(1) = 0; p = 0 or r = 1 gives
    s(u) = u.

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
    if d <= 0.0 or r >= 1.0:  # no wind-up: the identity
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


def _tie_matrix() -> np.ndarray:
    """Map (Y_3, Y_4, Y_5, Y_e) to the 9 control points (start tied to 0), shape (9, 4)."""
    m = np.zeros((DEGREE + 1, 4))
    m[3, 0] = m[4, 1] = m[5, 2] = 1.0
    m[6:, 3] = 1.0
    return m


_TIE = _tie_matrix()


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


def angles_from_quat(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (a, b) of R(quat) = Ry(b) Rx(a), unwrapped in time, and the fit residual.

    R e_x = Ry(b) e_x = (cos b, 0, -sin b), so b = atan2(-R_20, R_00); then
    Ry(b)^T R = Rx(a) gives a = atan2(M_21, M_11) with M = Ry(b)^T R. The residual
    |R - Ry(b) Rx(a)|_F is 0 for orientations of this form.

    Args:
        quat: Hand-body quaternions (w, x, y, z), shape (k, 4).

    Returns:
        a, b: shape (k,) [rad]; residual: shape (k,) [-].
    """
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    b = np.unwrap(np.arctan2(-r[:, 2, 0], r[:, 0, 0]))
    m = np.einsum("kji,kjl->kil", hand_rotation(b, np.zeros_like(b)), r)
    a = np.unwrap(np.arctan2(m[:, 2, 1], m[:, 1, 1]))
    residual = np.linalg.norm(r - hand_rotation(b, a), axis=(1, 2))
    return a, b, residual


def fit_motion(
    t: np.ndarray,
    pos: np.ndarray,
    quat: np.ndarray,
    *,
    durations: Sequence[float] = tuple(np.arange(0.60, 1.2001, 0.002)),
    starts: Sequence[float] | None = None,
) -> tuple[KnotMotion, float, float]:
    """Fit the family to a sampled hand motion (positions relative to the first sample).

    For a fixed start t_0 and duration T the family is linear in its free control points,
    so they are the least-squares solution of B(s_k) Y = y_k over the samples
    (s_k = clip((t_k - t_0) / T, 0, 1)); t_0 and T are chosen on grids by the smallest sum of
    the five curves' largest absolute residuals (m and rad).

    Args:
        t: Sample times, shape (k,) [s].
        pos: Hand positions, shape (k, 3) [m].
        quat: Hand-body orientations (w, x, y, z), shape (k, 4) (of the form Ry(b) Rx(a)).
        durations: Candidate T [s].
        starts: Candidate t_0 [s] (default: every 1 ms within 20 ms before the first moving
            sample).

    Returns:
        The motion, its start t_0 [s] and the largest residual over the curves [m or rad].
    """
    t = np.asarray(t, dtype=float)
    p = np.asarray(pos, dtype=float) - np.asarray(pos, dtype=float)[0]
    a, b, _ = angles_from_quat(quat)
    y = np.column_stack([p, a - a[0], b - b[0]])
    if starts is None:
        moving = np.nonzero(np.abs(np.diff(y, axis=0)).max(axis=1) > 1e-9)[0]
        t_move = t[moving[0]] if len(moving) else t[0]
        starts = np.arange(max(t[0], t_move - 0.02), t_move + 1e-9, 0.001)
    if len(durations) == 0 or len(starts) == 0:
        raise ConfigError("durations", "need at least one duration and one start")
    best: tuple[float, KnotMotion, float, float] | None = None
    for t0 in starts:
        for T in durations:
            basis = bernstein(np.clip((t - t0) / T, 0.0, 1.0)) @ _TIE
            free, *_ = np.linalg.lstsq(basis, y, rcond=None)
            err = np.abs(basis @ free - y).max(axis=0)
            if best is None or err.sum() < best[0]:
                motion = KnotMotion(np.concatenate([[T, *IDENTITY_WARP], free.T.ravel()]))
                best = (float(err.sum()), motion, float(t0), float(err.max()))
    return best[1], best[2], best[3]  # type: ignore[index]


def load_reference_motion(path: str | Path = REFERENCE_MOTION) -> KnotMotion:
    """The family member closest to the feasibility study's hand motion (see
    :func:`fit_motion`; max residual 0.4 mm and 0.2 degree)."""
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"reference motion {str(path)!r} does not exist")
    a = np.loadtxt(path, delimiter=",", comments="#", skiprows=2)
    motion, _, _ = fit_motion(a[:, 0], a[:, 1:4], a[:, 4:8], durations=np.arange(0.66, 0.76, 0.002))
    return motion


# ----------------------------------------------------------------------------------------
# writhe and score
# ----------------------------------------------------------------------------------------
def writhe(points: np.ndarray) -> float:
    """Writhe of an open polyline, the Gauss double integral summed over segment pairs.

    Wr = (1 / 2 pi) sum_{i < j} Omega_ij, with Omega_ij the signed solid angle of segment
    pair (i, j) (Klenin & Langowski, Biopolymers 54 (2000) 307-317, method 1a): for segment
    i from p1 to p2 and j from p3 to p4, r_kl = p_l - p_k,
    n1 = r13 x r14, n2 = r14 x r24, n3 = r24 x r23, n4 = r23 x r13 (normalised),
    Omega* = asin(n1.n2) + asin(n2.n3) + asin(n3.n4) + asin(n4.n1),
    Omega = Omega* sign((r34 x r12) . r13). Adjacent segments contribute 0.

    Args:
        points: Polyline, shape (n, 3) [m], n >= 2.

    Returns:
        Wr [-] (0 for planar curves; it changes sign under reflection).
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
        raise RecordError(f"points must have shape (n, 3) with n >= 2, got {p.shape}")
    m = p.shape[0] - 1
    i, j = np.triu_indices(m, k=2)
    if len(i) == 0:
        return 0.0
    p1, p2, p3, p4 = p[i], p[i + 1], p[j], p[j + 1]
    r13, r14, r23, r24 = p3 - p1, p4 - p1, p3 - p2, p4 - p2

    def unit(v: np.ndarray) -> np.ndarray:
        n = np.linalg.norm(v, axis=1, keepdims=True)
        return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-300)

    n1 = unit(np.cross(r13, r14))
    n2 = unit(np.cross(r14, r24))
    n3 = unit(np.cross(r24, r23))
    n4 = unit(np.cross(r23, r13))

    def asin_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.arcsin(np.clip(np.einsum("ki,ki->k", u, v), -1.0, 1.0))

    omega = asin_dot(n1, n2) + asin_dot(n2, n3) + asin_dot(n3, n4) + asin_dot(n4, n1)
    sign = np.sign(np.einsum("ki,ki->k", np.cross(p4 - p3, p2 - p1), r13))
    return float(np.sum(omega * sign) / (2.0 * math.pi))


@dataclass(frozen=True)
class TrialSummary:
    """What the score needs from one trial of a motion.

    Attributes:
        tied: A trefoil on the settled rope.
        settle_fraction: Knotted fraction of the judged settling frames, in [0, 1].
        knot_any: A trefoil in any judged frame from the motion's start on.
        contact: The rope touched itself.
        writhe: Largest |writhe| over the judged frames [-].
        peak_speed: Peak target hand speed [m/s].
        excursion: Largest target distance of the hand from its start [m].
        violation: The variant's own constraint violation (0 when met) [-].
        simulated: False for motions rejected before simulation (limits broken).
    """

    tied: bool = False
    settle_fraction: float = 0.0
    knot_any: bool = False
    contact: bool = False
    writhe: float = 0.0
    peak_speed: float = 0.0
    excursion: float = 0.0
    violation: float = 0.0
    simulated: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.settle_fraction <= 1.0:
            raise ConfigError(
                "TrialSummary.settle_fraction", f"must lie in [0, 1], got {self.settle_fraction!r}"
            )
        for f in ("writhe", "peak_speed", "excursion", "violation"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"TrialSummary.{f}", f"must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class ScoreWeights:
    """Weights of :func:`score` (see the module docstring).

    Attributes:
        tied: Knot on the settled rope.
        settle: Per unit knotted settling fraction.
        knot_any: Knot in any judged frame.
        contact: Rope self-contact.
        writhe: Per unit of min(|Wr|, writhe_cap) / writhe_cap.
        writhe_cap: Writhe beyond which there is no more credit [-].
        speed: Penalty per m/s above :data:`SPEED_LIMIT`.
        excursion: Penalty per m above :data:`EXCURSION_LIMIT`.
        violation: Penalty per unit of the variant's constraint violation.
        rejected: Extra penalty of a motion that is not simulated.
    """

    tied: float = 100.0
    settle: float = 30.0
    knot_any: float = 10.0
    contact: float = 5.0
    writhe: float = 5.0
    writhe_cap: float = 3.0
    speed: float = 20.0
    excursion: float = 100.0
    violation: float = 100.0
    rejected: float = 10.0

    def __post_init__(self) -> None:
        for f in ("tied", "settle", "knot_any", "contact", "writhe", "speed", "excursion"):
            v = getattr(self, f)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"ScoreWeights.{f}", f"must be a finite number >= 0, got {v!r}")
        check_positive("ScoreWeights.writhe_cap", self.writhe_cap)


def limit_penalty(summary: TrialSummary, weights: ScoreWeights = ScoreWeights()) -> float:
    """P = w_v max(0, v_peak - 8) + w_e max(0, e_max - 0.7) + w_g g_variant (>= 0)."""
    return (
        weights.speed * max(0.0, summary.peak_speed - SPEED_LIMIT)
        + weights.excursion * max(0.0, summary.excursion - EXCURSION_LIMIT)
        + weights.violation * summary.violation
    )


def score(summary: TrialSummary, weights: ScoreWeights = ScoreWeights()) -> float:
    """Shaped score of one trial (module docstring); higher is better.

    S = w_k [tied] + w_s f_settle + w_a [knot_any] + w_c [contact]
        + w_w min(|Wr|, cap) / cap - P  (simulated), or -w_r - P (rejected),
    with P from :func:`limit_penalty`.
    """
    penalty = limit_penalty(summary, weights)
    if not summary.simulated:
        return -weights.rejected - penalty
    return (
        weights.tied * summary.tied
        + weights.settle * summary.settle_fraction
        + weights.knot_any * summary.knot_any
        + weights.contact * summary.contact
        + weights.writhe * min(summary.writhe, weights.writhe_cap) / weights.writhe_cap
        - penalty
    )


# ----------------------------------------------------------------------------------------
# variants
# ----------------------------------------------------------------------------------------
SEEDS = ("reference", "reference-mirrored")
THROW_WINDOW = (0.66, 0.72)
"""Duration window of the throw (the first stage of every variant) [s]: the reference's
0.70 s; scaling a knotting motion in time keeps the knot only within about +-3 %."""
STAGE_KINDS = ("throw", "windup")
PACE_WEIGHT = 0.1
"""Violation per unit of relative excess over a variant's pace limits (10 % over a limit
counts like a 1 cm swipe violation)."""


@dataclass(frozen=True)
class Variant:
    """A kind of flying-knot demonstration (the paper's Fast, Slow, Swipe, Inverse).

    Every variant is searched in stages (:meth:`stages`, :func:`synthesize_motion`): a throw
    in :data:`THROW_WINDOW` from the seed motion (with the variant's own constraint), then,
    for a longer ``duration``, a slow wind-up added before the throw
    (:meth:`KnotMotion.with_windup`).

    Attributes:
        name: Name (lower case).
        description: One line.
        duration: Range of the motion's duration T [s] (a hard bound of the search).
        seed: Start of the search: ``reference`` (the feasibility study's motion, refitted)
            or ``reference-mirrored`` (its mirror image, the opposite twist); its duration
            is clipped into ``duration``.
        swipe_ratio: If > 0, the strike (from the hand's highest point to its end) must
            travel at least this many times farther horizontally than it drops:
            violation g = max(0, dz - dh / swipe_ratio) [m].
        throw_sigma: CMA-ES initial step of the throw stage [normalised units]; a
            constrained throw needs a broader search (measured, see the docs).
        speed_limit: Peak hand speed allowed by the variant [m/s] (inf: only the global
            :data:`SPEED_LIMIT`); the excess counts in the violation (:meth:`violation`).
        axis_rate_limit: Peak angular rate of the rope's exit axis allowed [rad/s] (inf: no
            limit). A robot follows a hand only as fast as its wrist turns: a demonstration
            for a robot is made with a limit near the robot's own (see :meth:`pace`).
    """

    name: str
    description: str
    duration: tuple[float, float]
    seed: str = "reference"
    swipe_ratio: float = 0.0
    throw_sigma: float = 0.3
    speed_limit: float = math.inf
    axis_rate_limit: float = math.inf

    def __post_init__(self) -> None:
        lo, hi = (float(v) for v in self.duration)
        if not 0.1 <= lo <= hi <= 5.0:
            raise ConfigError(
                "Variant.duration", f"need 0.1 <= lo <= hi <= 5 s, got {self.duration}"
            )
        object.__setattr__(self, "duration", (lo, hi))
        check_choice("Variant.seed", self.seed, SEEDS)
        if not (math.isfinite(self.swipe_ratio) and self.swipe_ratio >= 0):
            raise ConfigError("Variant.swipe_ratio", f"must be >= 0, got {self.swipe_ratio!r}")
        check_positive("Variant.throw_sigma", self.throw_sigma)
        for f in ("speed_limit", "axis_rate_limit"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"Variant.{f}", f"must be a number > 0 (inf: none), got {v!r}")

    def pace(self, motion: KnotMotion, dt: float = 0.001) -> tuple[float, float]:
        """Peak hand speed max |p'| [m/s] and peak exit-axis rate max |d'| [rad/s].

        The rope leaves the hand along d = Ry(b) Rx(a) (0, 0, -1), so
        |d'| = sqrt(a'^2 + cos(a)^2 b'^2); sampled every ``dt`` over [0, T].
        """
        t = np.linspace(0.0, motion.duration, max(3, math.ceil(motion.duration / dt) + 1))
        y, yd = motion.curves(t), motion.curves(t, 1)
        speed = np.linalg.norm(yd[:, :3], axis=1)
        rate = np.sqrt(yd[:, 3] ** 2 + (np.cos(y[:, 3]) * yd[:, 4]) ** 2)
        return float(speed.max()), float(rate.max())

    def strike(self, motion: KnotMotion) -> tuple[float, float]:
        """The strike's drop dz and horizontal travel dh [m], from the hand's highest point
        (sampled at 201 times) to its end."""
        t = np.linspace(0.0, motion.duration, 201)
        p = motion.curves(t)[:, :3]
        k = int(np.argmax(p[:, 2]))
        return float(p[k, 2] - p[-1, 2]), float(np.linalg.norm(p[-1, :2] - p[k, :2]))

    def violation(self, motion: KnotMotion) -> float:
        """The variant's constraint violation g(motion) >= 0 (0 when met).

        g = max(0, dz - dh / swipe_ratio) [m] (swipe)
            + PACE_WEIGHT (max(0, v_peak / speed_limit - 1) + max(0, w_peak / axis_rate_limit - 1))
        """
        g = 0.0
        if self.swipe_ratio > 0:
            dz, dh = self.strike(motion)
            g += max(0.0, dz - dh / self.swipe_ratio)
        if math.isfinite(self.speed_limit) or math.isfinite(self.axis_rate_limit):
            speed, rate = self.pace(motion)
            g += PACE_WEIGHT * (
                max(0.0, speed / self.speed_limit - 1.0)
                + max(0.0, rate / self.axis_rate_limit - 1.0)
            )
        return g

    def seed_motion(self) -> KnotMotion:
        """The search's start: the seed motion with T clipped into ``duration``."""
        m = load_reference_motion()
        if self.seed == "reference-mirrored":
            m = m.mirrored()
        x = m.x.copy()
        x[0] = float(np.clip(x[0], *self.duration))
        return KnotMotion(x)

    def stages(self) -> list[tuple[str, Variant]]:
        """The search stages: (kind, stage variant) with kind in :data:`STAGE_KINDS`.

        ``throw`` in :data:`THROW_WINDOW` (with ``swipe_ratio``); a ``windup`` stage moves to
        ``duration`` if that differs from the throw window. The last stage is the variant
        itself.
        """
        if self.duration == THROW_WINDOW:
            return [("throw", self)]
        throw = replace(self, name=f"{self.name}/throw", duration=THROW_WINDOW)
        return [("throw", throw), ("windup", self)]


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("fast", "a quick throw and strike from rest", THROW_WINDOW),
        Variant("slow", "the same kind of throw after a long slow wind-up", (1.00, 1.08)),
        Variant(
            "swipe",
            "the strike sweeps sideways: it travels as far horizontally as it drops",
            (0.80, 0.86),
            swipe_ratio=1.0,
            throw_sigma=0.6,
        ),
        Variant(
            "inverse",
            "the opposite twist (mirror-image seed: a knot of the other handedness)",
            (0.90, 0.96),
            seed="reference-mirrored",
        ),
    )
}
"""The four demonstration kinds, by name."""


def get_variant(name: str) -> Variant:
    """The variant called ``name``.

    Raises:
        ConfigError: Unknown name, listing the valid ones.
    """
    if name not in VARIANTS:
        raise ConfigError("variant", f"unknown value {name!r}", list(VARIANTS))
    return VARIANTS[name]


def param_bounds(variant: Variant) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds of the 21 numbers for ``variant``: lo, hi, shape (21,) [s, m, rad]."""
    lo = np.empty(N_PARAMS)
    hi = np.empty(N_PARAMS)
    lo[0], hi[0] = variant.duration
    lo[1], hi[1] = 0.0, WINDUP_MAX
    lo[2], hi[2] = WINDUP_SPEED_MIN, 1.0
    for c, name in enumerate(CURVES):
        sl = slice(N_HEAD + 4 * c, N_HEAD + 4 + 4 * c)
        bound = ANGLE_BOUND if name in ("a", "b") else VIA_BOUND
        lo[sl], hi[sl] = -bound, bound
        if name not in ("a", "b"):
            lo[N_HEAD + 3 + 4 * c], hi[N_HEAD + 3 + 4 * c] = -END_BOUND, END_BOUND
    return lo, hi


PARAM_SCALE = np.array([0.05, 0.05, 0.05] + [0.1] * 12 + [0.5] * 8)
"""Unit of the search's normalised coordinates per number: 50 ms, 0.05 of p and r, 10 cm,
0.5 rad."""


# ----------------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------------
def motion_summary(motion: KnotMotion, variant: Variant) -> TrialSummary:
    """The limit terms of a motion alone (``simulated`` False): peak speed, excursion and
    the variant's violation."""
    speed, excursion = motion.hand_limits()
    return TrialSummary(
        peak_speed=speed,
        excursion=excursion,
        violation=variant.violation(motion),
        simulated=False,
    )


def trial_summary(trial: HandTrial, limits: TrialSummary) -> TrialSummary:
    """Summary of a simulated trial (limit terms copied from ``limits``)."""
    if trial.diverged:
        return replace(limits, simulated=True)
    wr = max((abs(writhe(trial.vertices[k])) for k in trial.judged), default=0.0)
    return replace(
        limits,
        tied=trial.tied,
        settle_fraction=trial.settle_fraction,
        knot_any=trial.knot_any,
        contact=trial.first_contact is not None,
        writhe=wr,
        simulated=True,
    )


def within_limits(limits: TrialSummary) -> bool:
    """No speed, excursion or variant violation (the motion is worth simulating)."""
    return limit_penalty(limits) == 0.0


@dataclass(frozen=True)
class Evaluation:
    """Trials of one motion.

    Attributes:
        motion: The motion.
        summaries: One per trial (a single rejected one if the limits are broken).
        scores: :func:`score` of each summary.
    """

    motion: KnotMotion
    summaries: tuple[TrialSummary, ...]
    scores: tuple[float, ...]

    @property
    def mean_score(self) -> float:
        """Mean score over the trials."""
        return float(np.mean(self.scores))

    @property
    def ties(self) -> int:
        """Trials that ended with a knot."""
        return sum(s.tied for s in self.summaries)

    @property
    def rate(self) -> float:
        """Fraction of trials that ended with a knot."""
        return self.ties / len(self.summaries)


def evaluate(
    lab: HandLab,
    motion: KnotMotion,
    variant: Variant,
    variations: Sequence[Mapping[str, Any]],
    weights: ScoreWeights = ScoreWeights(),
) -> Evaluation:
    """Score ``motion`` once per variation (:meth:`HandLab.draw_variation` dicts); a motion
    that breaks the limits is scored once without simulation."""
    limits = motion_summary(motion, variant)
    if not within_limits(limits):
        return Evaluation(motion, (limits,), (score(limits, weights),))
    sums = tuple(trial_summary(lab.run(motion, variation=v), limits) for v in variations)
    return Evaluation(motion, sums, tuple(score(s, weights) for s in sums))


# ----------------------------------------------------------------------------------------
# search
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SearchConfig:
    """Budget and settings of :func:`search`.

    Attributes:
        budget: Most simulated trials in total (exploration + confirmation + refinement).
        sigma0: CMA-ES initial step in normalised units (:data:`PARAM_SCALE`).
        popsize: CMA-ES population (0: CMA's default 4 + 3 ln 21 = 13).
        confirm_trials: Trials that confirm a candidate: the nominal one plus
            ``confirm_trials - 1`` varied ones (the same variations for every candidate).
        target_rate: The search stops at the first candidate whose nominal trial ties and
            whose confirmation rate reaches this.
        refine_after: Trials after which, if some candidate was confirmed with a rate below
            the target, CMA-ES restarts around the best one with ``refine_sigma`` and
            ``refine_repeats`` varied trials per candidate (mean score).
        refine_sigma: Step of the refinement [normalised units].
        refine_repeats: Trials per candidate in the refinement.
        hand: Hand-lab settings (rope, settling time, variation).
    """

    budget: int = 900
    sigma0: float = 0.3
    popsize: int = 0
    confirm_trials: int = 20
    target_rate: float = 0.8
    refine_after: int = 400
    refine_sigma: float = 0.1
    refine_repeats: int = 2
    hand: HandParams = field(default_factory=HandParams)

    def __post_init__(self) -> None:
        for f in ("budget", "confirm_trials", "refine_after", "refine_repeats"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"SearchConfig.{f}", f"must be an integer >= 1, got {v!r}")
        if isinstance(self.popsize, bool) or not isinstance(self.popsize, int) or self.popsize < 0:
            raise ConfigError(
                "SearchConfig.popsize", f"must be an integer >= 0, got {self.popsize!r}"
            )
        check_positive("SearchConfig.sigma0", self.sigma0)
        check_positive("SearchConfig.refine_sigma", self.refine_sigma)
        if not 0.0 < self.target_rate <= 1.0:
            raise ConfigError(
                "SearchConfig.target_rate", f"must lie in (0, 1], got {self.target_rate!r}"
            )


@dataclass(frozen=True)
class Candidate:
    """A confirmed candidate.

    Attributes:
        motion: The motion.
        trial: Trial count at which it was found.
        rate: Knot rate over the confirmation trials.
        nominal_tied: Its nominal (unvaried) trial tied.
        mean_score: Mean score over the confirmation trials.
    """

    motion: KnotMotion
    trial: int
    rate: float
    nominal_tied: bool
    mean_score: float

    def key(self) -> tuple[bool, float, float]:
        """Ordering: nominal trial tied, then rate, then mean score."""
        return (self.nominal_tied, self.rate, self.mean_score)


@dataclass(frozen=True)
class SearchResult:
    """Outcome of :func:`search`.

    Attributes:
        variant: Variant name.
        seed: Search seed.
        best: Best confirmed candidate, or None if nothing tied.
        trials: Simulated trials used.
        evaluations: Candidate motions evaluated by CMA-ES.
        first_tie: Trial count at the first knotted trial, or None.
        ties: Knotted trials among the CMA-ES evaluations.
        candidates: Every confirmed candidate, in order.
        history: Per CMA-ES evaluation: (trial count, mean score, ties), shape (E, 3).
        wall_s: Wall time [s].
        stopped: Why the search stopped (``target``, ``budget``).
    """

    variant: str
    seed: int
    best: Candidate | None
    trials: int
    evaluations: int
    first_tie: int | None
    ties: int
    candidates: tuple[Candidate, ...]
    history: np.ndarray
    wall_s: float
    stopped: str

    def to_dict(self, timing: bool = True) -> dict[str, Any]:
        """Plain-data summary (for metadata and reports); ``timing`` adds the wall time
        (left out of saved demonstrations so that a rerun writes the same file)."""
        out = {
            "variant": self.variant,
            "seed": self.seed,
            "trials": self.trials,
            "evaluations": self.evaluations,
            "first_tie": self.first_tie,
            "ties": self.ties,
            "confirmed": len(self.candidates),
            "best_rate": None if self.best is None else self.best.rate,
            "best_nominal_tied": None if self.best is None else self.best.nominal_tied,
            "best_found_at": None if self.best is None else self.best.trial,
            "stopped": self.stopped,
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def variations(lab: HandLab, seed: Sequence[int], n: int, *, nominal_first: bool) -> list[dict]:
    """``n`` trial variations from ``np.random.default_rng(seed)``; the first one nominal if
    ``nominal_first``."""
    rng = np.random.default_rng(list(seed))
    out = [lab.draw_variation(rng) for _ in range(n)]
    if nominal_first and n:
        out[0] = HandLab.nominal_variation()
    return out


def _stream_seed(seed: int, stream: int, what: int) -> int:
    """A CMA-ES seed (>= 1) derived from (seed, stream, what)."""
    return int(np.random.default_rng([seed, stream, what]).integers(1, 2**31 - 1))


def search(
    variant: str | Variant,
    seed: int,
    config: SearchConfig = SearchConfig(),
    *,
    start: KnotMotion | None = None,
    stream: int = 0,
    lab: HandLab | None = None,
    bar: Any = None,
    weights: ScoreWeights = ScoreWeights(),
) -> SearchResult:
    """CMA-ES over the family for a robust flying knot (see ``docs/demo-synthesis.md``).

    CMA-ES (package ``cma``) runs in normalised coordinates z = (x - x_start) / scale
    (:data:`PARAM_SCALE`) inside the variant's box (:func:`param_bounds`), maximising the
    :func:`score` of one varied trial per candidate (every candidate of a generation sees
    the same variation). A candidate whose trial ties is confirmed on ``confirm_trials``
    trials (nominal first, then fixed variations). The search stops at the first candidate
    whose nominal trial ties with a confirmation rate >= ``target_rate``, or when the trial
    budget is spent. After ``refine_after`` trials with only weaker confirmed candidates,
    CMA-ES restarts around the best of them with a smaller step, scoring each candidate by
    its mean over ``refine_repeats`` varied trials.

    Args:
        variant: Variant or its name.
        seed: Seed of CMA-ES and of the trial variations.
        config: Budget and settings.
        start: Start motion (default: the variant's seed motion).
        stream: Sub-stream of the seed (stages of :func:`synthesize_motion` use 0, 1, ...).
        lab: Hand lab to use (default: a new one from ``config.hand``).
        bar: A tqdm bar to advance by simulated trials (None: none).
        weights: Score weights.

    Returns:
        The result; ``best`` is None if nothing tied.
    """
    import cma

    v = get_variant(variant) if isinstance(variant, str) else variant
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", f"must be an integer >= 0, got {seed!r}")
    tic = time.perf_counter()
    lab = HandLab(config.hand) if lab is None else lab
    lo, hi = param_bounds(v)
    x_start = np.clip((v.seed_motion() if start is None else start).x, lo, hi)
    confirm_set = variations(lab, (seed, stream, 1), config.confirm_trials, nominal_first=True)
    state = {"trials": 0, "ties": 0, "first_tie": None, "evals": 0}
    history: list[tuple[int, float, int]] = []
    candidates: list[Candidate] = []
    best: Candidate | None = None
    stopped = "budget"

    def spend(n: int) -> None:
        state["trials"] += n
        if bar is not None:
            bar.update(n)

    def make_es(center: np.ndarray, sigma: float, what: int) -> tuple[Any, np.ndarray]:
        zlo = (lo - center) / PARAM_SCALE
        zhi = (hi - center) / PARAM_SCALE
        opts = {
            "bounds": [zlo.tolist(), zhi.tolist()],
            "seed": _stream_seed(seed, stream, what),
            "verbose": -9,
        }
        if config.popsize:
            opts["popsize"] = config.popsize
        return cma.CMAEvolutionStrategy(np.zeros(N_PARAMS), sigma, opts), center

    es, center = make_es(x_start, config.sigma0, 3)
    repeats, generation, refined = 1, 0, False
    while state["trials"] < config.budget and stopped == "budget":
        if not refined and best is not None and state["trials"] >= config.refine_after:
            es, center = make_es(best.motion.x, config.refine_sigma, 4)
            repeats, refined = config.refine_repeats, True
        zs = es.ask()
        gen_vars = variations(lab, (seed, stream, 2, generation), repeats, nominal_first=False)
        generation += 1
        fitness = []
        for z in zs:
            motion = KnotMotion(np.clip(center + PARAM_SCALE * np.asarray(z), lo, hi))
            ev = evaluate(lab, motion, v, gen_vars, weights)
            state["evals"] += 1
            spend(sum(sm.simulated for sm in ev.summaries))
            fitness.append(-ev.mean_score)
            history.append((state["trials"], ev.mean_score, ev.ties))
            if ev.ties:
                state["ties"] += ev.ties
                if state["first_tie"] is None:
                    state["first_tie"] = state["trials"]
                conf = evaluate(lab, motion, v, confirm_set, weights)
                spend(len(conf.summaries))
                cand = Candidate(
                    motion=motion,
                    trial=state["trials"],
                    rate=conf.rate,
                    nominal_tied=conf.summaries[0].tied,
                    mean_score=conf.mean_score,
                )
                candidates.append(cand)
                if best is None or cand.key() > best.key():
                    best = cand
                if cand.nominal_tied and cand.rate >= config.target_rate:
                    stopped = "target"
                    break
            if bar is not None:
                bar.set_postfix(
                    stage=v.name.split("/")[-1],
                    ties=state["ties"],
                    best="-" if best is None else f"{best.rate:.1f}",
                )
            if state["trials"] >= config.budget:
                break
        if stopped == "budget" and len(fitness) == len(zs):
            es.tell(zs, fitness)
    return SearchResult(
        variant=v.name,
        seed=seed,
        best=best,
        trials=state["trials"],
        evaluations=state["evals"],
        first_tie=state["first_tie"],
        ties=state["ties"],
        candidates=tuple(candidates),
        history=np.array(history, dtype=float).reshape(-1, 3),
        wall_s=time.perf_counter() - tic,
        stopped=stopped,
    )


# ----------------------------------------------------------------------------------------
# demonstrations: making, replaying, saving
# ----------------------------------------------------------------------------------------
HAND_META_FIELDS = (
    "home",
    "hand_mass",
    "hand_inertia",
    "hinge_armature",
    "slide_bandwidth",
    "hinge_bandwidth",
    "hang_s",
    "settle_s",
    "judge_rate_hz",
)
"""HandParams fields stored in a demonstration's metadata (replays rebuild the hand)."""


def hand_metadata(params: HandParams) -> dict[str, Any]:
    """The hand settings a replay needs, as plain data."""
    return {
        f: (list(getattr(params, f)) if f == "home" else getattr(params, f))
        for f in HAND_META_FIELDS
    }


def rope_metadata(rope_id: int | str | Any, ropes: str | None = None) -> dict[str, Any]:
    """The rope's parameters and the simulation settings, as plain data (a shipped demo is
    stale when these differ from ``assets/ropes.toml``). ``rope_id``: anything
    :func:`flyknot_sim.rope.resolve_rope` takes (with the ropes file ``ropes``)."""
    from flyknot_sim.rope import load_sim_settings, resolve_rope

    rope = resolve_rope(rope_id, ropes).to_dict()
    data = {"rope": rope, "simulation": asdict(load_sim_settings())}
    return json.loads(json.dumps(data))  # as stored: tuples become lists


def make_demonstration(
    motion: KnotMotion,
    *,
    variant: str,
    seed: int,
    hand: HandParams | None = None,
    mocap_params: MocapParams | None = None,
    extra: Mapping[str, Any] | None = None,
) -> tuple[Demonstration, HandTrial]:
    """Play ``motion`` once, nominally, and record it as the motion capture would.

    The capture noise is seeded by ``(seed, 3)``; t_c is the simulation's first rope
    self-contact. Metadata: generator and version, variant, seed, the 23 motion numbers, the
    motion's start on the demonstration clock, the hand and rope settings, the settled
    outcome and ``extra``.

    Raises:
        ConfigError: The rope never touched itself (no t_c) or the simulation diverged.
    """
    import mujoco

    hand = HandParams() if hand is None else hand
    if hand.rope_params.custom:
        raise ConfigError(
            "rope",
            f"a demonstration records one of the paper's ropes 1..7, got the custom rope "
            f"{hand.rope_params.name!r} (custom ropes replay demonstrations)",
        )
    hand = replace(hand, variation=HandVariation.none())
    mocap_params = MocapParams() if mocap_params is None else mocap_params
    lab = HandLab(hand)
    trial = lab.run(motion)
    meta = {
        "generator": GENERATOR,
        "generator_version": GENERATOR_VERSION,
        "variant": variant,
        "seed": seed,
        "motion": motion.to_dict(),
        "motion_start": trial.motion_start,
        "motion_duration": motion.duration,
        "hand": hand_metadata(hand),
        "hand_frame": "fingertip: origin at the held end, z along the rope's exit",
        "mocap": asdict(mocap_params),
        "settle_outcome": trial.knot,
        "knot_any": trial.knot_any,
        "settle_fraction": trial.settle_fraction,
        "mujoco": mujoco.__version__,
        **rope_metadata(hand.rope_params),
        **dict(extra or {}),
    }
    demo = trial_demonstration(
        trial,
        lab.rope,
        mocap_params,
        np.random.default_rng([seed, 3]),
        rope_id=hand.rope,
        metadata=meta,
    )
    return demo, trial


def motion_from_demo(demo: Demonstration, source: str = "demonstration") -> KnotMotion:
    """The motion stored in a synthetic demonstration's metadata.

    Raises:
        RecordError: The metadata holds no motion (not made by this module).
    """
    motion = demo.metadata.get("motion")
    if not isinstance(motion, Mapping):
        raise RecordError(
            f"{source}: no motion parameters in its metadata (only demonstrations made by "
            "`flyknot demo synthesize` can be replayed)"
        )
    return KnotMotion.from_dict(motion)


def hand_from_demo(
    demo: Demonstration, rope: int | str, *, vary: bool = True, ropes: str | None = None
) -> HandParams:
    """The hand lab a demonstration was made in, holding rope ``rope`` (an id or a name,
    from ``ropes``, a user's ropes file, for a custom rope)."""
    stored = demo.metadata.get("hand", {})
    # The settle is the lab's own rule (judged at rest, issue 10), not the fixed wait a
    # demonstration made before it stored.
    kwargs = {f: stored[f] for f in HAND_META_FIELDS if f in stored and f != "settle_s"}
    if "home" in kwargs:
        kwargs["home"] = tuple(kwargs["home"])
    variation = HandVariation() if vary else HandVariation.none()
    return HandParams(rope=rope, variation=variation, ropes=ropes, **kwargs)


@dataclass(frozen=True)
class ReplayResult:
    """Replays of a demonstration's motion.

    Attributes:
        rope: Rope id replayed with (a custom rope's name for a custom rope).
        outcomes: Settled knot type per replay (None if the simulation diverged).
        t_c: First rope self-contact per replay [s, demonstration clock], None if none.
        trials: The trials (kept only when asked for).
    """

    rope: int | str
    outcomes: tuple[str | None, ...]
    t_c: tuple[float | None, ...]
    trials: tuple[HandTrial, ...] = ()

    @property
    def knots(self) -> int:
        """Replays that ended with a trefoil."""
        return sum(o == TREFOIL for o in self.outcomes)

    def to_json(self) -> dict[str, Any]:
        """``{"repeats", "knots", "outcomes", "t_c"}``."""
        return {
            "repeats": len(self.outcomes),
            "knots": self.knots,
            "outcomes": list(self.outcomes),
            "t_c": list(self.t_c),
        }


def replay(
    demo: Demonstration,
    *,
    rope: int | str | None = None,
    repeats: int = 1,
    seed: int = 0,
    vary: bool = True,
    settle_s: float | None = None,
    keep_trials: bool = False,
    progress: bool = False,
    ropes: str | None = None,
) -> ReplayResult:
    """Play a synthetic demonstration's hand motion again, on any rope.

    Replay i draws its variation from ``np.random.default_rng([seed, i])`` (or none if not
    ``vary``: then, on the demonstration's rope, the hand trajectory and t_c are the
    demonstration's).

    Args:
        demo: A demonstration made by :func:`make_demonstration`.
        rope: Rope id or name (default: the demonstration's).
        repeats: Number of replays, >= 1.
        seed: Seed of the variations.
        vary: Apply the lab's trial-to-trial variation.
        settle_s: Settling time [s] (default: the demonstration's).
        keep_trials: Keep the trials in the result (memory: ~2 MB each).
        progress: Show a tqdm progress bar.
        ropes: A user's ropes file whose ropes ``rope`` may name.

    Raises:
        RecordError: The demonstration holds no motion.
        ConfigError: Bad rope id, repeats or settling time.
    """
    from tqdm import tqdm

    motion = motion_from_demo(demo)
    rope = demo.rope if rope is None else rope
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise ConfigError("repeats", f"must be an integer >= 1, got {repeats!r}")
    hand = hand_from_demo(demo, rope, vary=vary, ropes=ropes)
    rope = hand.rope_params.id
    if settle_s is not None:
        hand = replace(hand, settle_s=settle_s)
    lab = HandLab(hand)
    outcomes, t_c, trials = [], [], []
    for i in tqdm(range(repeats), desc=f"replay (rope {rope})", disable=bar_disable(progress)):
        rng = np.random.default_rng([seed, i]) if vary else None
        trial = lab.run(motion, rng)
        outcomes.append(trial.knot)
        t_c.append(trial.first_contact)
        if keep_trials:
            trials.append(trial)
    return ReplayResult(rope, tuple(outcomes), tuple(t_c), tuple(trials))


REPLAY_TRUTH_RATE_HZ = 100.0
"""Rate of the true centrelines stored with a saved replay [Hz]."""


def save_replay(
    path: str | Path,
    trial: HandTrial,
    lab_rope: Any,
    *,
    rope: int | str,
    seed: int,
    index: int,
    source: str,
    mocap_params: MocapParams | None = None,
) -> Path:
    """Save one replay as a demonstration-like ``.npz`` (see ``assets/demos/README.md``).

    Arrays ``t``, ``hand_pos``, ``hand_quat``, ``markers`` (the capture's view, seeded by
    ``(seed, index, 3)``) and ``meta`` as in :meth:`Demonstration.save` (so a replay with a
    self-contact loads as a :class:`Demonstration`; ``t_c`` is null without one), plus the
    truth ``t_truth`` (m,) [s] and ``centreline`` (m, n + 1, 3) [m] at 100 Hz.

    Returns:
        The path written.
    """
    from flyknot.demo import DEMO_FORMAT_VERSION
    from flyknot_sim.mocap import emulate, sample_times

    mocap_params = MocapParams() if mocap_params is None else mocap_params
    rng = np.random.default_rng([seed, index, 3])
    t_m = sample_times(float(trial.t[-1]), mocap_params.rate_hz)
    markers = emulate(
        trial.t,
        lab_rope.markers_from_vertices(trial.vertices),
        t_m,
        trial.first_contact,
        mocap_params,
        rng,
    )
    pos = np.column_stack([np.interp(t_m, trial.t, trial.hand_pos[:, i]) for i in range(3)])
    quat = np.column_stack([np.interp(t_m, trial.t, trial.hand_quat[:, i]) for i in range(4)])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    dt = float(trial.t[1] - trial.t[0])
    stride = max(1, round(1.0 / (REPLAY_TRUTH_RATE_HZ * dt)))
    meta = {
        "format_version": DEMO_FORMAT_VERSION,
        "t_c": trial.first_contact,
        "rope": rope,
        "metadata": {
            "generator": GENERATOR,
            "generator_version": GENERATOR_VERSION,
            "kind": "replay",
            "source": source,
            "index": index,
            "seed": seed,
            "outcome": trial.knot,
            "settle": None if trial.settle is None else dict(trial.settle),
            "variation": dict(trial.variation),
            "motion_start": trial.motion_start,
        },
    }
    params = getattr(lab_rope, "params", None)
    if getattr(params, "custom", False):  # a custom rope: the file's parameters
        meta["metadata"]["rope_params"] = params.to_dict()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        t=t_m,
        hand_pos=pos,
        hand_quat=quat,
        markers=markers,
        t_truth=trial.t[::stride],
        centreline=trial.vertices[::stride],
        meta=np.array(json.dumps(meta)),
    )
    return path


# ----------------------------------------------------------------------------------------
# synthesis: staged search, demonstration, check
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SynthConfig:
    """Settings of :func:`synthesize_motion` and :func:`synthesize`.

    Attributes:
        search: The throw stage's search (its ``budget``, ``sigma0``, ``target_rate``, the
            confirmation and the hand); later stages copy it with the fields below.
        stage_budget: Trial budget of every later stage.
        stage_sigma: CMA-ES step of every later stage [normalised units].
        stage_target: Confirmation rate that ends an intermediate stage.
        windup_speeds: Wind-up speeds r tried as the wind-up stage's start (the one tying
            most often in ``windup_trials`` trials, nominal first, is taken).
        windup_trials: Trials per wind-up speed tried.
        total_budget: Most simulated trials over all stages.
    """

    search: SearchConfig = field(default_factory=lambda: SearchConfig(budget=900))
    stage_budget: int = 500
    stage_sigma: float = 0.15
    stage_target: float = 0.5
    windup_speeds: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25)
    windup_trials: int = 3
    total_budget: int = 3000

    def __post_init__(self) -> None:
        for f in ("stage_budget", "windup_trials", "total_budget"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"SynthConfig.{f}", f"must be an integer >= 1, got {v!r}")
        check_positive("SynthConfig.stage_sigma", self.stage_sigma)
        if not 0.0 < self.stage_target <= 1.0:
            raise ConfigError(
                "SynthConfig.stage_target", f"must lie in (0, 1], got {self.stage_target!r}"
            )
        speeds = tuple(float(r) for r in self.windup_speeds)
        if not speeds or not all(WINDUP_SPEED_MIN <= r < 1.0 for r in speeds):
            raise ConfigError(
                "SynthConfig.windup_speeds",
                f"need values in [{WINDUP_SPEED_MIN}, 1), got {self.windup_speeds!r}",
            )
        object.__setattr__(self, "windup_speeds", speeds)


@dataclass(frozen=True)
class StagedResult:
    """Outcome of :func:`synthesize_motion`.

    Attributes:
        variant: Variant name.
        seed: Seed.
        motion: The final motion.
        stages: Per stage: its kind and search result (skipped stages are absent).
        trials: Simulated trials over all stages.
        wall_s: Wall time [s].
    """

    variant: str
    seed: int
    motion: KnotMotion
    stages: tuple[tuple[str, SearchResult], ...]
    trials: int
    wall_s: float

    def to_dict(self, timing: bool = True) -> dict[str, Any]:
        """Plain-data summary (``timing``: with wall times)."""
        out = {
            "variant": self.variant,
            "seed": self.seed,
            "trials": self.trials,
            "stages": [{"kind": k, **r.to_dict(timing)} for k, r in self.stages],
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def _pick_windup(
    lab: HandLab,
    motion: KnotMotion,
    stage: Variant,
    seed: int,
    stream: int,
    config: SynthConfig,
) -> tuple[KnotMotion, int]:
    """The wind-up stage's start: ``motion`` lengthened to the stage's mid duration with the
    wind-up speed (of ``config.windup_speeds``) that ties most often; returns it and the
    trials spent."""
    duration = float(np.mean(stage.duration))
    trials = variations(lab, (seed, stream, 5), config.windup_trials, nominal_first=True)
    best: tuple[tuple[int, float], KnotMotion] | None = None
    spent = 0
    for r in config.windup_speeds:
        cand = motion.with_windup(max(duration, motion.core_duration), r)
        ev = evaluate(lab, cand, stage, trials)
        spent += sum(sm.simulated for sm in ev.summaries)
        key = (ev.ties, ev.mean_score)
        if best is None or key > best[0]:
            best = (key, cand)
    assert best is not None  # windup_speeds is never empty (SynthConfig checks it)
    return best[1], spent


def synthesize_motion(
    variant: str | Variant,
    seed: int,
    config: SynthConfig = SynthConfig(),
    *,
    progress: bool = False,
    on_stage: Callable[[str, SearchResult], None] | None = None,
) -> StagedResult:
    """Search a robust flying-knot motion of ``variant`` in stages (:meth:`Variant.stages`).

    Each stage runs :func:`search` from the previous stage's best motion (the first from the
    variant's seed motion, with the variant's ``throw_sigma``) on its own sub-stream of
    ``seed``; a wind-up stage starts from the best of :meth:`KnotMotion.with_windup` over
    ``config.windup_speeds``. Intermediate stages end at
    ``config.stage_target``, the last at ``config.search.target_rate``. ``on_stage`` is
    called with each finished stage's kind and result.

    Raises:
        SolverError: A stage found no motion whose nominal trial ties, or the total budget
            ran out.
    """
    from tqdm import tqdm

    from flyknot.errors import SolverError

    v = get_variant(variant) if isinstance(variant, str) else variant
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", f"must be an integer >= 0, got {seed!r}")
    tic = time.perf_counter()
    lab = HandLab(config.search.hand)
    stages = v.stages()
    motion = replace(v, duration=THROW_WINDOW).seed_motion()
    bar = tqdm(
        total=config.total_budget,
        unit="trial",
        desc=f"demo {v.name} seed {seed}",
        disable=bar_disable(progress),
    )
    used = 0
    done: list[tuple[str, SearchResult]] = []
    try:
        for k, (kind, stage) in enumerate(stages):
            last = k == len(stages) - 1
            if kind == "windup":
                motion, spent = _pick_windup(lab, motion, stage, seed, k, config)
                used += spent
                bar.update(spent)
            cfg = replace(config.search, sigma0=v.throw_sigma)
            if k > 0:
                cfg = replace(cfg, budget=config.stage_budget, sigma0=config.stage_sigma)
            if not last:
                cfg = replace(cfg, target_rate=config.stage_target)
            left = config.total_budget - used
            if left < 1:
                raise SolverError("demo search", "budget", f"spent before stage {stage.name}")
            cfg = replace(cfg, budget=min(cfg.budget, left))
            res = search(stage, seed, cfg, start=motion, stream=k, lab=lab, bar=bar)
            used += res.trials
            done.append((kind, res))
            if on_stage is not None:
                on_stage(kind, res)
            if res.best is None or not res.best.nominal_tied:
                raise SolverError(
                    "demo search",
                    "no knot",
                    f"stage {stage.name} found no motion whose nominal trial ties in "
                    f"{res.trials} trials; try another seed or a larger budget",
                )
            motion = res.best.motion
    finally:
        bar.close()
    return StagedResult(v.name, seed, motion, tuple(done), used, time.perf_counter() - tic)


@dataclass(frozen=True)
class SynthResult:
    """Outcome of :func:`synthesize`.

    Attributes:
        demo: The demonstration (metadata includes the search summary and the check).
        staged: The staged search.
        check: The varied replays of the saved demonstration, or None if skipped.
    """

    demo: Demonstration
    staged: StagedResult
    check: ReplayResult | None

    def summary(self) -> dict[str, Any]:
        """What the command line prints."""
        m = self.demo.metadata
        return {
            "variant": m["variant"],
            "seed": m["seed"],
            "rope": self.demo.rope,
            "duration_s": round(m["motion_duration"], 4),
            "t_c": round(self.demo.t_c, 4),
            "settle_outcome": m["settle_outcome"],
            "trials": self.staged.trials,
            "search_wall_s": round(self.staged.wall_s, 1),
            "check": None
            if self.check is None
            else f"{self.check.knots}/{len(self.check.outcomes)}",
        }


def pace_metadata(variant: Variant) -> dict[str, Any]:
    """The variant's finite pace limits as plain data (empty if it has none)."""
    out = {}
    for f in ("speed_limit", "axis_rate_limit"):
        v = getattr(variant, f)
        if math.isfinite(v):
            out[f] = float(v)
    return {"pace": out} if out else {}


def synthesize(
    variant: str | Variant,
    seed: int,
    config: SynthConfig = SynthConfig(),
    *,
    check_repeats: int = 20,
    progress: bool = False,
) -> SynthResult:
    """Search a motion (:func:`synthesize_motion`), record it as a demonstration
    (:func:`make_demonstration`) and check it with ``check_repeats`` varied replays
    (:func:`replay` with seed ``seed``; the count goes into the metadata as ``check``)."""
    v = get_variant(variant) if isinstance(variant, str) else variant
    staged = synthesize_motion(v, seed, config, progress=progress)
    hand = config.search.hand
    demo, _ = make_demonstration(
        staged.motion,
        variant=v.name,
        seed=seed,
        hand=hand,
        extra={
            "search": staged.to_dict(timing=False),
            "variant_description": v.description,
            **pace_metadata(v),
        },
    )
    check = None
    if check_repeats > 0:
        check = replay(demo, repeats=check_repeats, seed=seed, progress=progress)
        meta = dict(demo.metadata)
        meta["check"] = {"repeats": check_repeats, "seed": seed, "knots": check.knots}
        demo = replace(demo, metadata=meta)
    return SynthResult(demo, staged, check)

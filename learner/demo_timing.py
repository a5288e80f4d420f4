"""Demonstration timing selection (paper, appendix "Demonstration Timing Selection").

Given a whole demonstration and its annotated critical time t_c (the rope's first
self-contact), keep only the window [t_0, t_f] from the start of the hand's motion to the
end of its follow-through:

1. A temporary range [t0~, tf~] (``search_window``) excludes the human picking the rope up
   and laying it down; by default it is the whole recording.
2. t_peak = the sample of maximum hand speed in [t0~, tf~].
3. Step back from t_peak to the first sample whose speed is near zero,
   |v| <= ``near_zero_frac`` * |v(t_peak)| (3 %): that is t_rest (the paper's updated t0~).
   The step-back stays inside the search window.
4. t_f = t_c + ``follow_through`` (35 ms).
5. Integrate the hand's path length from t_rest to t_f; t_0 is where ``path_frac`` (5 %) of
   it has been travelled.

Speed rule (the paper does not state one): the positions are optionally smoothed by a
centred moving average over ``smooth_s`` seconds (an odd number of samples, edges padded with
the end values; off by default), then differentiated by second-order central differences
(one-sided at the ends, ``numpy.gradient`` with the sample times), and the speed is the
Euclidean norm. The path length uses the same (smoothed) positions, as a polyline with the
position at t_f linearly interpolated; t_0 is found by linear interpolation of the
cumulative length, which is exact for the polyline.

All functions are pure: arrays in, a :class:`DemoWindow` or a new demonstration out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from flyknot.constants import FOLLOW_THROUGH_S, PATH_FRAC  # paper: "5% of the total path length"
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError, check_nonnegative, check_positive

NEAR_ZERO_FRAC = 0.03  # paper: "near-zero (3% of velocity at t_peak)"
MIN_PEAK_SPEED = 1e-6  # [m/s] below this the hand counts as never moving (rounding noise)


@dataclass(frozen=True)
class DemoWindow:
    """The selected part of a demonstration, on the demonstration's clock.

    Attributes:
        t0: Start of the hand motion (5 % of the path from ``t_rest`` to ``tf``) [s].
        tf: End of the follow-through, t_c + 35 ms [s].
        t_peak: Sample of maximum hand speed in the search window [s].
        t_rest: Last near-rest sample before ``t_peak`` [s].
    """

    t0: float
    tf: float
    t_peak: float
    t_rest: float

    def __post_init__(self) -> None:
        for name in ("t0", "tf", "t_peak", "t_rest"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v)):
                raise ConfigError(f"DemoWindow.{name}", f"must be a finite time, got {v!r}")
            object.__setattr__(self, name, float(v))
        if not (self.t_rest <= self.t0 < self.tf):
            raise ConfigError(
                "DemoWindow",
                f"needs t_rest <= t0 < tf, got t_rest={self.t_rest}, t0={self.t0}, tf={self.tf}",
            )
        if self.t_rest > self.t_peak:
            raise ConfigError(
                "DemoWindow",
                f"needs t_rest <= t_peak, got t_rest={self.t_rest}, t_peak={self.t_peak}",
            )

    @property
    def duration(self) -> float:
        """Length of the hand motion, T = t_f - t_0 [s]."""
        return self.tf - self.t0


def _smooth(t: np.ndarray, x: np.ndarray, smooth_s: float) -> np.ndarray:
    """Centred moving average of ``x`` (k, 3) over ``smooth_s`` [s] of samples."""
    if smooth_s <= 0:
        return x
    dt = (t[-1] - t[0]) / (len(t) - 1)
    n = 2 * round(float(0.5 * smooth_s / dt)) + 1
    if n <= 1:
        return x
    return uniform_filter1d(x, size=n, axis=0, mode="nearest")


def hand_speed(t: np.ndarray, hand_pos: np.ndarray, smooth_s: float = 0.0) -> np.ndarray:
    """Hand speed by central differences of the (optionally smoothed) positions.

    v_i = |p_{i+1} - p_{i-1}| / (t_{i+1} - t_{i-1}) on a uniform grid (numpy.gradient's
    second-order formula on a non-uniform one; one-sided first order at the ends).

    Args:
        t: Sample times, shape (k,) [s], strictly increasing, k >= 2.
        hand_pos: Hand positions, shape (k, 3) [m].
        smooth_s: Width of the centred moving average applied to the positions first [s];
            0 disables it.

    Returns:
        Speed, shape (k,) [m/s].
    """
    t, p = _check_motion(t, hand_pos)
    check_nonnegative("smooth_s", smooth_s)
    return np.linalg.norm(np.gradient(_smooth(t, p, smooth_s), t, axis=0), axis=1)


def _check_motion(t: np.ndarray, hand_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float)
    p = np.asarray(hand_pos, dtype=float)
    if t.ndim != 1 or t.shape[0] < 3:
        raise RecordError(f"t must have shape (k,) with k >= 3, got {t.shape}")
    if p.shape != (t.shape[0], 3):
        raise RecordError(f"hand_pos must have shape ({t.shape[0]}, 3), got {p.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise RecordError("t and hand_pos must be finite everywhere")
    if np.any(np.diff(t) <= 0):
        raise RecordError("t must be strictly increasing")
    return t, p


def _interp_rows(t: np.ndarray, x: np.ndarray, tq: float) -> np.ndarray:
    """Linear interpolation of the rows of ``x`` (k, d) at one time ``tq``."""
    j = int(np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2))
    w = (tq - t[j]) / (t[j + 1] - t[j])
    return (1.0 - w) * x[j] + w * x[j + 1]


def select_demo_window(
    t: np.ndarray,
    hand_pos: np.ndarray,
    t_c: float,
    *,
    search_window: tuple[float, float] | None = None,
    near_zero_frac: float = NEAR_ZERO_FRAC,
    follow_through: float = FOLLOW_THROUGH_S,
    path_frac: float = PATH_FRAC,
    smooth_s: float = 0.0,
) -> DemoWindow:
    """Select [t_0, t_f] of a demonstration as in the paper (see the module docstring).

    t_peak = argmax_{t_i in [t0~, tf~]} v_i
    t_rest = max { t_i in [t0~, t_peak] : v_i <= near_zero_frac * v(t_peak) }
    t_f    = t_c + follow_through
    s(t)   = integral_{t_rest}^{t} |dp/dt| dt  (polyline length),
    t_0    = s^{-1}(path_frac * s(t_f))

    Args:
        t: Sample times, shape (k,) [s], strictly increasing.
        hand_pos: Hand positions, shape (k, 3) [m].
        t_c: Critical time (first rope self-contact) [s], inside the samples.
        search_window: (t0~, tf~) [s] to search the peak in; None = all samples.
        near_zero_frac: Fraction of the peak speed that counts as rest, in (0, 1).
        follow_through: t_f - t_c [s], >= 0.
        path_frac: Fraction of the path length that marks t_0, in [0, 1).
        smooth_s: Moving-average width for the speed and path [s]; 0 = raw positions.

    Returns:
        The window.

    Raises:
        ConfigError: A parameter is out of range.
        RecordError: The data do not admit a window (t_c or t_f outside the samples, an
            empty search window, a hand at rest, speed never back to near zero, ...).
    """
    t, p = _check_motion(t, hand_pos)
    check_positive("near_zero_frac", near_zero_frac)
    check_nonnegative("path_frac", path_frac)
    for name, v in (("near_zero_frac", near_zero_frac), ("path_frac", path_frac)):
        if v >= 1:
            raise ConfigError(name, f"must be < 1, got {v!r}")
    check_nonnegative("follow_through", follow_through)
    check_nonnegative("smooth_s", smooth_s)
    if not (np.isfinite(t_c) and t[0] <= t_c <= t[-1]):
        raise RecordError(f"t_c = {t_c} lies outside the samples [{t[0]}, {t[-1]}] s")
    tf = float(t_c) + follow_through
    if tf > t[-1] + 1e-12:
        raise RecordError(
            f"t_f = t_c + {follow_through} = {tf} lies after the last sample {t[-1]} s"
        )
    tf = min(tf, float(t[-1]))

    lo, hi = (t[0], t[-1]) if search_window is None else search_window
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ConfigError("search_window", f"must be (t0~, tf~) with t0~ < tf~, got ({lo}, {hi})")
    inside = np.flatnonzero((t >= lo) & (t <= hi))
    if inside.size == 0:
        raise RecordError(
            f"search_window ({lo}, {hi}) s holds no samples (samples span [{t[0]}, {t[-1]}] s)"
        )

    ps = _smooth(t, p, smooth_s)
    v = np.linalg.norm(np.gradient(ps, t, axis=0), axis=1)
    i_peak = int(inside[np.argmax(v[inside])])
    v_peak = float(v[i_peak])
    if v_peak <= MIN_PEAK_SPEED:
        raise RecordError(
            "the hand does not move inside the search window "
            f"(peak speed below {MIN_PEAK_SPEED:g} m/s)"
        )
    rest = np.flatnonzero(v[inside[0] : i_peak + 1] <= near_zero_frac * v_peak)
    if rest.size == 0:
        raise RecordError(
            f"hand speed never falls to {near_zero_frac:g} of its peak {v_peak:.4g} m/s "
            f"between the search window start {t[inside[0]]} s and t_peak {t[i_peak]} s"
        )
    i_rest = int(inside[0] + rest[-1])
    t_rest = float(t[i_rest])
    if t_rest >= t_c:
        raise RecordError(
            f"t_c = {t_c} s is not after the hand starts moving (t_rest = {t_rest} s)"
        )

    # Path length s(t) on the polyline t_rest = t_j, ..., t_m <= t_f, then p(t_f).
    i_end = int(np.searchsorted(t, tf, side="left"))  # samples t[i_rest:i_end] < tf
    tt = np.append(t[i_rest:i_end], tf)
    pp = np.vstack([ps[i_rest:i_end], _interp_rows(t, ps, tf)[None]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pp, axis=0), axis=1))])
    if s[-1] <= 0.0:
        raise RecordError(f"the hand does not move between t_rest = {t_rest} s and t_f = {tf} s")
    target = path_frac * s[-1]
    if target == 0.0:
        t0 = t_rest
    else:
        # first vertex with s >= target (so s[m-1] < target <= s[m]); interpolate between
        m = int(np.searchsorted(s, target, side="left"))
        w = (target - s[m - 1]) / (s[m] - s[m - 1])
        t0 = float(tt[m - 1] + w * (tt[m] - tt[m - 1]))
    if t0 > t_c:
        raise RecordError(f"t_0 = {t0} s lies after t_c = {t_c} s")
    return DemoWindow(t0=t0, tf=tf, t_peak=float(t[i_peak]), t_rest=t_rest)


def _slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions, rows of (m, 4), weights (m,).

    q(w) = sin((1-w) a)/sin(a) q0 + sin(w a)/sin(a) q1',  cos(a) = |q0 . q1|,
    q1' = sign(q0 . q1) q1 (shortest arc); normalised lerp when a < 1e-6.
    """
    d = np.sum(q0 * q1, axis=1)
    q1 = np.where(d[:, None] < 0, -q1, q1)
    d = np.clip(np.abs(d), 0.0, 1.0)
    a = np.arccos(d)
    small = a < 1e-6
    sa = np.where(small, 1.0, np.sin(a))
    c0 = np.where(small, 1.0 - w, np.sin((1.0 - w) * a) / sa)
    c1 = np.where(small, w, np.sin(w * a) / sa)
    q = c0[:, None] * q0 + c1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _interp_nan_aware(t: np.ndarray, x: np.ndarray, tq: np.ndarray) -> np.ndarray:
    """Linear interpolation of (k, ...) samples at times (m,); NaN where a used end is NaN."""
    j = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    w = np.clip((tq - t[j]) / (t[j + 1] - t[j]), 0.0, 1.0)
    shape = (-1,) + (1,) * (x.ndim - 1)
    w = w.reshape(shape)
    a, b = x[j], x[j + 1]
    out = (1.0 - w) * a + w * b
    out = np.where(w == 0.0, a, out)
    return np.where(w == 1.0, b, out)


def trim_demonstration(demo: Demonstration, window: DemoWindow) -> Demonstration:
    """Cut a demonstration to [t_0, t_f] and restart its clock at t_0.

    The new samples are uniform and hit both ends exactly:
    n = ceil((t_f - t_0) / dt) + 1 with dt the demonstration's mean sample period,
    t'_i = i (t_f - t_0) / (n - 1) [s]; the data are interpolated at t_0 + t'_i (positions
    and markers linearly, a marker lost at either neighbour stays lost; orientation by
    slerp). t_c' = t_c - t_0.

    Args:
        demo: The whole demonstration.
        window: From :func:`select_demo_window` on the same clock.

    Returns:
        The trimmed demonstration; ``metadata["timing"]`` records the window on the
        original clock.

    Raises:
        RecordError: The window does not lie inside the demonstration or misses t_c.
    """
    t = demo.t
    if window.t0 < t[0] - 1e-12 or window.tf > t[-1] + 1e-12:
        raise RecordError(
            f"window [{window.t0}, {window.tf}] s is not inside the demonstration "
            f"[{t[0]}, {t[-1]}] s"
        )
    if not (window.t0 <= demo.t_c <= window.tf):
        raise RecordError(
            f"window [{window.t0}, {window.tf}] s does not contain t_c = {demo.t_c} s"
        )
    dt = (t[-1] - t[0]) / (len(t) - 1)
    length = window.tf - window.t0
    n = int(np.ceil(length / dt - 1e-9)) + 1
    t_new = np.linspace(0.0, length, max(n, 2))
    tq = np.clip(window.t0 + t_new, t[0], t[-1])
    j = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    w = np.clip((tq - t[j]) / (t[j + 1] - t[j]), 0.0, 1.0)
    metadata = dict(demo.metadata)
    metadata["timing"] = {
        "t0": window.t0,
        "tf": window.tf,
        "t_peak": window.t_peak,
        "t_rest": window.t_rest,
    }
    return Demonstration(
        t=t_new,
        hand_pos=_interp_nan_aware(t, demo.hand_pos, tq),
        hand_quat=_slerp(demo.hand_quat[j], demo.hand_quat[j + 1], w),
        markers=_interp_nan_aware(t, demo.markers, tq),
        t_c=min(max(demo.t_c - window.t0, 0.0), length),
        rope=demo.rope,
        metadata=metadata,
    )

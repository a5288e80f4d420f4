"""Relating the mocap clock to the robot clock: a start event, then speed cross-correlation.

Convention: ``t_robot = t_mocap + offset_s``. A trial record's marker times are the capture
times plus the offset, on the clock of the joint samples (0 at the first command sample).

1. **Start event** (coarse, :func:`start_event_time`): the first time a track leaves its
   rest position by more than ``threshold_m`` (the median of its first ``rest_window_s`` is
   the rest position), linearly interpolated between the two frames that straddle the
   threshold. Applied to the fingertip in both clocks (mocap: a fingertip marker or marker
   cluster; robot: forward kinematics of the measured joints) it gives a first offset, good
   to about a millisecond on clean data and to tens of milliseconds with 1 mm noise on a slow
   start (the threshold is crossed early or late): well inside the search window of step 2.
   A hardware sync signal, if the lab has one, replaces it (``coarse_offset_s``). With a base
   pose, the event is the fingertip's **departure** from the command's start pose instead
   (:func:`departure_time`): the last time it leaves that pose before its main motion. A
   capture that began while the arm was still approaching the start pose (the capture
   software's pre-trigger buffer) then gives the right event, where the first departure
   from its first position does not (measured on the fake lab: 0.26-0.43 s off, and the
   search of step 2 locked onto a wrong peak). Not for rope marker 0, which hangs below.
2. **Speed cross-correlation** (:func:`align_clocks`): speeds are frame-invariant, so the
   fingertip speed from forward kinematics (``fk``, injected: the robot base frame) and the
   speed of the fingertip track in the mocap frame can be compared before any calibration.
   Both are put on a common grid (``grid_hz``, linear interpolation of the speeds), and the
   normalised cross-correlation is evaluated at every grid lag within ``search_s`` of the
   coarse offset; the peak is refined to a fraction of a grid step by a parabola through
   the peak and its two neighbours.
3. **Position refinement** (optional, on by default): the offset minimising the RMS distance
   between the mocap track and the forward-kinematics fingertip (cubic-spline interpolated
   at ``t_mocap + offset``, mapped into the mocap frame by ``base_pose``, or by the rigid
   fit of :func:`flyknot_hw.mocap.calibration.rigid_fit` at each offset when no base pose is
   given) is searched within two frame intervals (the longer of the grid step and the mocap
   frame interval) of the correlation's estimate (bounded scalar minimisation). This is what
   gets sub-millisecond accuracy; its RMS is the reported residual.

The residual says how good the alignment is: noiseless data with a fingertip marker give a
residual near 0 (simulated trial through C3D: offset error 2e-8 s, residual 1e-7 m; with
1 mm noise on every marker, 5e-5 s and 1 mm). With rope marker 0 instead (0.10 m down the
rope, it lags the hand in a fast motion) the offset is good to about 10 ms, and the residual
holds the 0.10 m offset when ``base_pose`` is given (a few centimetres when fitted). Clock
drift is not modelled (tens of ppm: under a millisecond over a trial).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize_scalar

from flyknot.constants import N_JOINTS
from flyknot.errors import ConfigError, HardwareError, check_positive
from flyknot.geometry import readonly
from flyknot_hw.mocap.calibration import apply_pose, pose_from_rt, rigid_fit

__all__ = [
    "ClockAlignment",
    "align_clocks",
    "departure_time",
    "fingertip_speed",
    "start_event_time",
]

Fk = Callable[[np.ndarray], np.ndarray]
"""Forward kinematics of the fingertip: q (n, 7) [rad] -> positions (n, 3) [m], base frame."""


@dataclass(frozen=True)
class ClockAlignment:
    """The offset between the clocks and how well it explains the data.

    Attributes:
        offset_s: ``t_robot = t_mocap + offset_s`` [s].
        coarse_offset_s: The start-event (or given) offset the search started from [s].
        correlation: Peak normalised cross-correlation of the speeds, in [-1, 1].
        residual_rms_m: RMS fingertip position error after alignment [m].
        residual_max_m: Largest fingertip position error after alignment [m].
        n_samples: Mocap frames that entered the residual.
        base_pose: The base pose used for the residual (given, or fitted when none was
            given), (x, y, z, qw, qx, qy, qz).
    """

    offset_s: float
    coarse_offset_s: float
    correlation: float
    residual_rms_m: float
    residual_max_m: float
    n_samples: int
    base_pose: np.ndarray

    def __post_init__(self) -> None:
        if not np.isfinite(self.offset_s):
            raise ConfigError("ClockAlignment.offset_s", f"must be finite, got {self.offset_s}")
        object.__setattr__(self, "base_pose", readonly(self.base_pose))


def _times(name: str, t: object) -> np.ndarray:
    a = np.asarray(t, dtype=float)
    if a.ndim != 1 or a.shape[0] < 3 or not np.all(np.isfinite(a)) or np.any(np.diff(a) <= 0):
        raise ConfigError(
            name, f"must be finite, strictly increasing, shape (m,), m >= 3; got {a.shape}"
        )
    return a


def _track(name: str, p: object, m: int) -> np.ndarray:
    a = np.asarray(p, dtype=float)
    if a.shape != (m, 3):
        raise ConfigError(name, f"must have shape ({m}, 3), got {a.shape}")
    return a


def start_event_time(
    times: np.ndarray,
    positions: np.ndarray,
    *,
    threshold_m: float = 0.005,
    rest_window_s: float = 0.1,
) -> float:
    """First time [s] the track is farther than ``threshold_m`` from its rest position.

    Args:
        times: Sample times, shape (m,) [s].
        positions: Track, shape (m, 3) [m]; NaN frames are skipped.
        threshold_m: Displacement that counts as motion [m] (above noise, below a frame's
            travel in the motion).
        rest_window_s: The rest position is the median over this first stretch [s].

    Raises:
        HardwareError: The track never moves that far (or has no valid rest samples).
    """
    t = _times("times", times)
    p = _track("positions", positions, t.shape[0])
    check_positive("threshold_m", threshold_m)
    check_positive("rest_window_s", rest_window_s)
    ok = np.all(np.isfinite(p), axis=1)
    rest = ok & (t <= t[ok][0] + rest_window_s) if ok.any() else ok
    if not rest.any():
        raise HardwareError("start event: the track has no valid samples at rest")
    p0 = np.median(p[rest], axis=0)
    d = np.where(ok, np.linalg.norm(p - p0, axis=1), np.nan)
    above = np.flatnonzero(d > threshold_m)
    if above.size == 0:
        raise HardwareError(f"start event: the track never moves more than {threshold_m} m")
    k = int(above[0])
    prev = np.flatnonzero(ok[:k])
    if prev.size == 0:
        return float(t[k])
    j = int(prev[-1])
    f = (threshold_m - d[j]) / (d[k] - d[j])
    return float(t[j] + f * (t[k] - t[j]))


def fingertip_speed(times: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Speed |dp/dt| [m/s], shape (m,), by central differences; NaN next to missing frames."""
    t = np.asarray(times, dtype=float)
    p = np.asarray(positions, dtype=float)
    v = np.gradient(p, t, axis=0)
    return np.linalg.norm(v, axis=1)


def departure_time(
    times: np.ndarray,
    positions: np.ndarray,
    rest: np.ndarray,
    *,
    threshold_m: float = 0.005,
    onset_frac: float = 0.3,
    search_m: float = 0.02,
) -> float:
    """When the track last leaves its rest at ``rest`` before its main motion [s].

    The rest position is the median of the samples within ``search_m`` of ``rest`` before
    the main motion (its onset: the first sample at ``onset_frac`` of the peak speed); the
    departure is the last crossing of ``threshold_m`` from it before the onset, linearly
    interpolated.

    Args:
        times: Sample times, shape (m,) [s].
        positions: Track, shape (m, 3) [m]; NaN frames are skipped.
        rest: Where the track rests before the motion (3,) [m], to within ``search_m``.
        threshold_m: Displacement that counts as motion [m].
        onset_frac: Fraction of the peak speed that marks the main motion.
        search_m: How far from ``rest`` the resting samples may lie [m].

    Raises:
        HardwareError: The track never rests near ``rest`` before moving.
    """
    t = _times("times", times)
    p = _track("positions", positions, t.shape[0])
    ok = np.all(np.isfinite(p), axis=1)
    v = fingertip_speed(t[ok], p[ok])
    if v.size < 3 or not np.any(np.isfinite(v)):
        raise HardwareError("departure: the track has too few samples")
    idx = np.flatnonzero(ok)
    onset = int(idx[np.flatnonzero(v >= onset_frac * np.nanmax(v))[0]])
    before = ok & (np.arange(t.shape[0]) < onset)
    near = before & (np.linalg.norm(p - np.asarray(rest, dtype=float), axis=1) <= search_m)
    if not near.any():
        raise HardwareError(
            f"departure: the track never rests within {search_m} m of the start pose before "
            "it moves; check the base pose"
        )
    p0 = np.median(p[near], axis=0)
    d = np.where(ok, np.linalg.norm(p - p0, axis=1), np.nan)
    still = np.flatnonzero(before & (d <= threshold_m))
    if still.size == 0:
        raise HardwareError(f"departure: the track never rests within {threshold_m} m")
    j = int(still[-1])
    after = np.flatnonzero(ok & (np.arange(t.shape[0]) > j))
    if after.size == 0:
        return float(t[j])
    k = int(after[0])
    f = (threshold_m - d[j]) / (d[k] - d[j]) if d[k] > d[j] else 0.0
    return float(t[j] + min(max(f, 0.0), 1.0) * (t[k] - t[j]))


def _fk_track(fk: Fk, q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != N_JOINTS:
        raise ConfigError("q_meas", f"must have shape (n, {N_JOINTS}), got {q.shape}")
    p = np.asarray(fk(q), dtype=float)
    if p.shape != (q.shape[0], 3) or not np.all(np.isfinite(p)):
        raise ConfigError(
            "fk", f"must return finite positions of shape ({q.shape[0]}, 3), got {p.shape}"
        )
    return p


def _xcorr(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Normalised correlation of a[k] with b[k - lag] over the overlap, per lag (NaN-aware)."""
    n = a.shape[0]
    out = np.full(lags.shape[0], np.nan)
    for r, lag in enumerate(lags):
        lo, hi = max(0, lag), min(n, b.shape[0] + lag)
        if hi - lo < 3:
            continue
        x, y = a[lo:hi], b[lo - lag : hi - lag]
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 3:
            continue
        x, y = x[ok] - x[ok].mean(), y[ok] - y[ok].mean()
        den = np.sqrt(np.sum(x * x) * np.sum(y * y))
        out[r] = np.sum(x * y) / den if den > 0 else np.nan
    return out


def align_clocks(
    t_mocap: np.ndarray,
    tip_mocap: np.ndarray,
    t_joint: np.ndarray,
    q_meas: np.ndarray,
    fk: Fk,
    *,
    base_pose: np.ndarray | None = None,
    coarse_offset_s: float | None = None,
    search_s: float = 0.25,
    grid_hz: float = 1000.0,
    refine: bool = True,
    threshold_m: float = 0.005,
    departure: bool = False,
) -> ClockAlignment:
    """Offset ``t_robot = t_mocap + offset_s`` from the fingertip seen by both (module docstring).

    Args:
        t_mocap: Mocap frame times, shape (m,) [s].
        tip_mocap: Fingertip (marker or cluster; or rope marker 0, less exact) in the mocap
            frame, shape (m, 3) [m]; NaN where lost.
        t_joint: Joint sample times, shape (n,) [s] (robot clock).
        q_meas: Measured joints, shape (n, 7) [rad].
        fk: Fingertip forward kinematics, q (n, 7) -> (n, 3) [m] in the robot base frame.
        base_pose: Robot base in the mocap frame (7,), for the residual; None: fitted.
        coarse_offset_s: Offset from a sync signal [s]; None: from the departures from the
            start pose (with ``base_pose``) or the start events (without).
        search_s: Half-width of the lag search around the coarse offset [s].
        grid_hz: Rate of the common grid of the cross-correlation [Hz].
        refine: Refine by minimising the position residual (step 3).
        threshold_m: Start-event displacement threshold [m].
        departure: The coarse offset from the departures from the start pose (needs
            ``base_pose`` and a fingertip track, not rope marker 0) instead of the start
            events.

    Raises:
        HardwareError: No motion to align on, or the tracks do not overlap.
    """
    tm = _times("t_mocap", t_mocap)
    pm = _track("tip_mocap", tip_mocap, tm.shape[0])
    tj = _times("t_joint", t_joint)
    pr = _fk_track(fk, q_meas)
    if pr.shape[0] != tj.shape[0]:
        raise ConfigError("q_meas", f"must have {tj.shape[0]} rows (t_joint), got {pr.shape[0]}")
    check_positive("search_s", search_s)
    check_positive("grid_hz", grid_hz)
    if coarse_offset_s is None:
        coarse = _coarse_offset(tm, pm, tj, pr, base_pose, departure, threshold_m)
    else:
        coarse = float(coarse_offset_s)
    h = 1.0 / grid_hz
    offset, peak = _correlated_offset(tm, pm, tj, pr, coarse, search_s, h)
    residual = _position_residual(tm, pm, tj, pr, base_pose)
    if refine:
        span = 2.0 * max(h, float(np.median(np.diff(tm))))
        res = minimize_scalar(
            lambda o: float(np.sqrt(np.mean(residual(o)[0] ** 2))),
            bounds=(offset - span, offset + span),
            method="bounded",
            options={"xatol": 1e-7},
        )
        offset = float(res.x)
    err, pose = residual(offset)
    if not np.all(np.isfinite(err)):
        raise HardwareError("clock alignment: too few mocap frames within the robot's time span")
    return ClockAlignment(
        offset_s=float(offset),
        coarse_offset_s=float(coarse),
        correlation=peak,
        residual_rms_m=float(np.sqrt(np.mean(err**2))),
        residual_max_m=float(err.max()),
        n_samples=int(err.shape[0]),
        base_pose=pose,
    )


def _coarse_offset(
    tm: np.ndarray,
    pm: np.ndarray,
    tj: np.ndarray,
    pr: np.ndarray,
    base_pose: np.ndarray | None,
    departure: bool,
    threshold_m: float,
) -> float:
    """Step 1 (module docstring): the offset [s] between the departures from the start pose
    (``departure``, in the mocap frame by ``base_pose``) or the start events of the robot's
    fingertip ``pr`` (n, 3) at ``tj`` and the mocap's ``pm`` (m, 3) at ``tm``."""
    if departure:
        if base_pose is None:
            raise ConfigError("departure", "needs base_pose (the start pose in the mocap frame)")
        rest = apply_pose(np.asarray(base_pose, dtype=float), pr[:1])[0]
        return departure_time(tj, pr, pr[0], threshold_m=threshold_m) - departure_time(
            tm, pm, rest, threshold_m=threshold_m
        )
    return start_event_time(tj, pr, threshold_m=threshold_m) - start_event_time(
        tm, pm, threshold_m=threshold_m
    )


def _correlated_offset(
    tm: np.ndarray,
    pm: np.ndarray,
    tj: np.ndarray,
    pr: np.ndarray,
    coarse: float,
    search_s: float,
    h: float,
) -> tuple[float, float]:
    """Step 2 (module docstring): the offset [s] within ``search_s`` of ``coarse`` that best
    correlates the two fingertip speeds on a grid of step ``h`` [s], refined by a parabola
    through the peak; and the peak's correlation.

    Speeds on a common grid of robot time, tau_k = grid[0] + k h. The mocap speed is sampled
    at mocap times tau_j - coarse (j from j0), so that for an offset coarse + L h the mocap
    sample matching tau_k is b[k - L - j0].
    """
    grid = np.arange(tj[0], tj[-1] + 0.5 * h, h)
    a = np.interp(grid, tj, fingertip_speed(tj, pr))
    s_m = fingertip_speed(tm, pm)
    ok = np.isfinite(s_m)
    if ok.sum() < 3:
        raise HardwareError("clock alignment: the mocap fingertip track has too few samples")
    j0 = int(np.ceil((tm[ok][0] + coarse - grid[0]) / h))
    j1 = int(np.floor((tm[ok][-1] + coarse - grid[0]) / h))
    b = np.interp(grid[0] + np.arange(j0, j1 + 1) * h - coarse, tm[ok], s_m[ok])
    n_lag = round(search_s / h)
    lags = np.arange(-n_lag, n_lag + 1)
    corr = _xcorr(a, b, lags + j0)
    if not np.any(np.isfinite(corr)):
        raise HardwareError("clock alignment: the mocap and robot tracks do not overlap")
    r = int(np.nanargmax(corr))
    frac = 0.0
    if 0 < r < len(lags) - 1 and np.all(np.isfinite(corr[r - 1 : r + 2])):
        c0, c1, c2 = corr[r - 1 : r + 2]
        den = c0 - 2 * c1 + c2
        frac = 0.5 * (c0 - c2) / den if den < 0 else 0.0
    return coarse + (lags[r] + frac) * h, float(corr[r])


def _position_residual(
    tm: np.ndarray, pm: np.ndarray, tj: np.ndarray, pr: np.ndarray, base_pose: np.ndarray | None
) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
    """Step 3's residual (module docstring): for an offset [s], the distances (k,) [m]
    between the mocap fingertip and the robot's (a cubic spline in time, placed by
    ``base_pose`` or by the rigid fit it returns with them) over the k mocap frames inside
    the robot's time span; inf when fewer than 3."""
    spline = CubicSpline(tj, pr, axis=0)
    valid = np.all(np.isfinite(pm), axis=1)

    def residual(off: float) -> tuple[np.ndarray, np.ndarray]:
        tr = tm + off
        use = valid & (tr >= tj[0]) & (tr <= tj[-1])
        if use.sum() < 3:
            return np.full(1, np.inf), np.full(7, np.nan)
        a = spline(tr[use])
        if base_pose is not None:
            pose = np.asarray(base_pose, dtype=float)
            return np.linalg.norm(apply_pose(pose, a) - pm[use], axis=1), pose
        R, t = rigid_fit(a, pm[use])
        return np.linalg.norm(a @ R.T + t - pm[use], axis=1), pose_from_rt(R, t)

    return residual

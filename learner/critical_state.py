"""The rope state at the critical time, from a trial's motion-capture markers.

The learner sees markers at 200 Hz with noise and with tracking lost (NaN) shortly after the
rope first touches itself. Position and velocity of each marker at ``t_c`` come from a local
quadratic least-squares fit (a Savitzky-Golay-style smoother) over the finite samples within
``half_window`` of ``t_c``; if tracking is lost right after ``t_c`` the fit is one-sided and
extrapolates at most ``max_extrapolation``. The fit's value and slope at ``t_c`` are the state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flyknot.constants import N_MARKERS
from flyknot.errors import ConfigError, RecordError, check_nonnegative, check_positive
from flyknot.geometry import quat_to_matrix
from flyknot.record import TrialRecord


@dataclass(frozen=True)
class MarkerFitParams:
    """How the critical-point state is estimated from markers.

    Attributes:
        half_window: Samples within t_c +- half_window are fitted [s].
        degree: Polynomial degree of the local fit (1 or 2).
        min_samples: Fewest finite samples a marker needs in the window.
        max_extrapolation: Largest gap between t_c and the nearest finite sample [s].
    """

    half_window: float = 0.025
    degree: int = 2
    min_samples: int = 4
    max_extrapolation: float = 0.015

    def __post_init__(self) -> None:
        check_positive("half_window", self.half_window)
        if self.degree not in (1, 2):
            raise ConfigError("degree", f"unsupported value {self.degree!r}", [1, 2])
        if not isinstance(self.min_samples, int) or self.min_samples < self.degree + 1:
            raise ConfigError(
                "min_samples", f"must be an integer >= degree + 1, got {self.min_samples!r}"
            )
        check_nonnegative("max_extrapolation", self.max_extrapolation)


def local_polyfit_state(
    t: np.ndarray, y: np.ndarray, t_c: float, params: MarkerFitParams = MarkerFitParams()
) -> tuple[np.ndarray, np.ndarray]:
    """Value and slope at ``t_c`` of a local least-squares polynomial through (t, y).

    y(t) ~= c0 + c1 (t - t_c) + c2 (t - t_c)^2 over finite samples with |t - t_c| <= h;
    returns (c0, c1).

    Args:
        t: Sample times, shape (m,) [s].
        y: Samples, shape (m, d) (NaN rows are skipped) [m].
        t_c: Time of the estimate [s].
        params: Window, degree and acceptance rules.

    Returns:
        Value (d,) [m] and velocity (d,) [m/s] at t_c.

    Raises:
        RecordError: too few finite samples, or the nearest one too far from t_c.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.all(np.isfinite(y), axis=1) & (np.abs(t - t_c) <= params.half_window + 1e-12)
    n_ok = int(ok.sum())
    if n_ok < params.min_samples:
        raise RecordError(
            f"only {n_ok} finite marker samples within {params.half_window} s of t_c = "
            f"{t_c:.3f} s (need {params.min_samples}): tracking lost before t_c"
        )
    dt = t[ok] - t_c
    gap = float(np.min(np.abs(dt)))
    if gap > params.max_extrapolation:
        raise RecordError(
            f"nearest finite marker sample is {gap * 1e3:.1f} ms from t_c = {t_c:.3f} s "
            f"(max {params.max_extrapolation * 1e3:.1f} ms)"
        )
    V = np.vander(dt, params.degree + 1, increasing=True)  # (n_ok, degree+1)
    coef, *_ = np.linalg.lstsq(V, y[ok], rcond=None)
    return coef[0], coef[1]


def markers_state_at(
    t_marker: np.ndarray,
    markers: np.ndarray,
    t_c: float,
    params: MarkerFitParams = MarkerFitParams(),
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities of all markers at ``t_c``.

    Args:
        t_marker: (m,) [s].
        markers: (m, 11, 3) [m], NaN where lost.
        t_c: Critical time on the markers' clock [s].
        params: Fit parameters.

    Returns:
        p (11, 3) [m] and v (11, 3) [m/s].
    """
    markers = np.asarray(markers, dtype=float)
    if markers.ndim != 3 or markers.shape[1:] != (N_MARKERS, 3):
        raise RecordError(f"markers must have shape (m, {N_MARKERS}, 3), got {markers.shape}")
    p = np.empty((N_MARKERS, 3))
    v = np.empty((N_MARKERS, 3))
    for i in range(N_MARKERS):
        try:
            p[i], v[i] = local_polyfit_state(t_marker, markers[:, i, :], t_c, params)
        except RecordError as e:
            raise RecordError(f"marker {i}: {e}") from None
    return p, v


def to_demo_frame(
    p: np.ndarray, v: np.ndarray, base_pose: np.ndarray, base_offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Express lab-frame marker states in the demonstration frame.

    p_demo = R_b^T (p - t_b) + b,   v_demo = R_b^T v,
    with (t_b, R_b) the robot base pose in the lab's mocap frame and b the command's base
    offset (the robot base's position in the demonstration frame).

    Args:
        p: Positions (..., 3) [m] in the lab frame.
        v: Velocities (..., 3) [m/s] in the lab frame.
        base_pose: (x, y, z, qw, qx, qy, qz) of the robot base in the lab frame.
        base_offset: (3,) [m].
    """
    t_b = np.asarray(base_pose[:3], dtype=float)
    R_b = quat_to_matrix(np.asarray(base_pose[3:], dtype=float))
    return (np.asarray(p) - t_b) @ R_b + base_offset, np.asarray(v) @ R_b


def critical_state_from_record(
    record: TrialRecord,
    t_c: float,
    base_offset: np.ndarray,
    params: MarkerFitParams = MarkerFitParams(),
) -> np.ndarray:
    """The measured rope state x(t_c) in the demonstration frame, shape (66,).

    x = [p_1..p_11 (33,) [m], v_1..v_11 (33,) [m/s]], the layout the inverse model uses.
    ``t_c`` is on the markers' clock, measured from the command start.
    """
    p, v = markers_state_at(record.t_marker, record.markers, t_c, params)
    p, v = to_demo_frame(p, v, record.base_pose, np.asarray(base_offset, dtype=float))
    return np.concatenate([p.ravel(), v.ravel()])

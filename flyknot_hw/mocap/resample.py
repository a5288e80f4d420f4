"""Labelled markers onto the record's uniform clock: linear interpolation that never bridges a gap.

A capture system's frames are nearly, but not exactly, uniform (live frames are stamped on
arrival; files may drop frames), and markers go missing. :func:`resample_uniform` puts any
such series onto ``t_k = t_start + k / rate_hz``:

* each channel (each coordinate of each marker) is interpolated linearly between its two
  valid (finite) samples bracketing ``t_k``;
* if those two samples are more than ``max_gap_s`` apart, the value at ``t_k`` is NaN: a
  marker lost for longer than the limit stays lost, it is never drawn as a straight line
  across the gap. With the default 0.025 s at 200 Hz that bridges at most 4 missing frames;
  the error of a bridge is at most a * gap^2 / 8 (a the acceleration: 20 mm at 250 m/s^2
  over 25 ms, the worst a whipping rope end shows in the simulated lab);
* a grid time outside the span of a channel's valid samples is NaN (no extrapolation);
* a grid time within ``TIME_TOL`` of a sample takes that sample.

Marker coordinates share their validity (a lost marker is NaN in x, y and z), so the three
coordinates of a marker come out valid or NaN together.
"""

from __future__ import annotations

import math

import numpy as np

from flyknot.constants import MARKER_RATE_HZ
from flyknot.errors import ConfigError, check_positive

__all__ = ["DEFAULT_MAX_GAP_S", "TIME_TOL", "resample_uniform", "uniform_grid"]

DEFAULT_MAX_GAP_S = 0.025
"""Longest interval between two valid samples that is bridged [s] (5 frames at 200 Hz)."""

TIME_TOL = 1e-9
"""Grid times this close to a sample take it, and the grid end is rounded by it [s]."""


def uniform_grid(t_start: float, t_end: float, rate_hz: float = MARKER_RATE_HZ) -> np.ndarray:
    """``t_start + k / rate_hz`` for k = 0, 1, ... up to ``t_end`` (inclusive), shape (n,) [s]."""
    check_positive("rate_hz", rate_hz)
    if not (math.isfinite(t_start) and math.isfinite(t_end)) or t_end < t_start:
        raise ConfigError("t_end", f"must be finite and >= t_start {t_start!r}, got {t_end!r}")
    n = math.floor((t_end - t_start) * rate_hz + TIME_TOL * rate_hz) + 1
    return t_start + np.arange(n) / rate_hz


def resample_uniform(
    times: np.ndarray,
    values: np.ndarray,
    rate_hz: float = MARKER_RATE_HZ,
    *,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    t_start: float | None = None,
    t_end: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a series with gaps onto a uniform clock (rules in the module docstring).

    Args:
        times: Sample times, shape (m,) [s], strictly increasing.
        values: Samples, shape (m, ...) (e.g. (m, 11, 3) markers [m]); NaN where missing.
        rate_hz: Rate of the output clock [Hz].
        max_gap_s: Longest interval between valid samples that is interpolated across [s].
        t_start: First output time [s]; None: ``times[0]``.
        t_end: Last output time at most [s]; None: ``times[-1]``.

    Returns:
        ``(t_grid, out)``: t_grid shape (n,) [s], out shape (n, ...) (the trailing shape of
        ``values``), NaN where no bridgeable pair of samples brackets the grid time.
    """
    t = np.asarray(times, dtype=float)
    v = np.asarray(values, dtype=float)
    if t.ndim != 1 or t.shape[0] < 1 or not np.all(np.isfinite(t)):
        raise ConfigError("times", f"must be finite with shape (m,), m >= 1, got {t.shape}")
    if np.any(np.diff(t) <= 0):
        raise ConfigError("times", "must increase strictly")
    if v.ndim < 1 or v.shape[0] != t.shape[0]:
        raise ConfigError("values", f"must have shape ({t.shape[0]}, ...), got {v.shape}")
    check_positive("max_gap_s", max_gap_s)
    t0 = float(t[0]) if t_start is None else float(t_start)
    t1 = float(t[-1]) if t_end is None else float(t_end)
    grid = uniform_grid(t0, t1, rate_hz)
    flat = v.reshape(t.shape[0], -1)
    out = np.full((grid.shape[0], flat.shape[1]), np.nan)
    valid_all = np.isfinite(flat)
    # Channels with the same validity pattern share the bracketing (the usual case: x, y, z).
    patterns: dict[bytes, list[int]] = {}
    for c in range(flat.shape[1]):
        patterns.setdefault(np.packbits(valid_all[:, c]).tobytes(), []).append(c)
    for cols in patterns.values():
        ok = valid_all[:, cols[0]]
        tv = t[ok]
        if tv.shape[0] == 0:
            continue
        yv = flat[ok][:, cols]
        # Index of the last valid sample at or before each grid time (within TIME_TOL).
        j = np.searchsorted(tv, grid + TIME_TOL, side="right") - 1
        inside = (j >= 0) & (grid <= tv[-1] + TIME_TOL)
        exact = inside & (np.abs(grid - tv[np.clip(j, 0, None)]) <= TIME_TOL)
        j1 = np.clip(j + 1, 0, tv.shape[0] - 1)
        j0 = np.clip(j, 0, tv.shape[0] - 1)
        gap = tv[j1] - tv[j0]
        between = inside & ~exact & (j + 1 < tv.shape[0]) & (gap <= max_gap_s + TIME_TOL)
        res = np.full((grid.shape[0], len(cols)), np.nan)
        res[exact] = yv[j0[exact]]
        if np.any(between):
            f = ((grid[between] - tv[j0[between]]) / gap[between])[:, None]
            res[between] = yv[j0[between]] * (1.0 - f) + yv[j1[between]] * f
        out[:, cols] = res
    return grid, out.reshape((grid.shape[0], *v.shape[1:]))

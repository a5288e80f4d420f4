"""Motion-capture emulation: what a Vicon would report for the rope's 11 markers.

The simulator knows the true marker positions at its own time steps. The lab's motion
capture sees them differently, and this module turns the one into the other with pure
functions (arrays in, arrays out; randomness only through a passed ``np.random.Generator``):

1. :func:`sample_times` -- the capture clock, ``rate_hz`` (200 Hz) frames.
2. :func:`resample_markers` -- the true positions at those frames (linear interpolation).
3. :func:`add_noise` -- independent zero-mean Gaussian noise on every coordinate.
4. :func:`apply_tracking_loss` -- NaN from ``loss_delay`` after the rope's first
   self-contact, when the markers crowd together and the capture loses or swaps them:

   * ``"all"``: every marker is lost in every frame from the loss onset on (what the paper
     reports: the learner only uses the rope state up to the critical time).
   * ``"random"``: from the onset on, each marker in each frame is lost independently with
     probability ``loss_fraction``. This stands in for marker misidentification: the capture
     drops a label it cannot match and may pick it up again a frame later. Swapped labels
     (a marker reported at another marker's position) are not emulated.
   * ``"none"``: no loss (an ideal capture, for checks).

:func:`emulate` chains the last three on a clock the caller chooses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flyknot.constants import MARKER_RATE_HZ
from flyknot.errors import ConfigError, RecordError, check_choice, check_nonnegative, check_positive

LOSS_MODES = ("all", "random", "none")

# Samples closer than this to the loss onset count as at or after it (float rounding of
# t_c + delay against k / rate) [s].
TIME_TOL = 1e-9


@dataclass(frozen=True)
class MocapParams:
    """Settings of the emulated motion capture.

    Attributes:
        rate_hz: Capture rate [Hz].
        noise_std: Standard deviation of the Gaussian noise on each coordinate [m].
        loss_delay: Time from the rope's first self-contact to the loss onset [s].
        loss_mode: "all", "random" or "none" (see the module docstring).
        loss_fraction: For "random": probability that a marker is lost in a frame at or
            after the onset, in [0, 1]. Ignored by the other modes.
    """

    rate_hz: float = MARKER_RATE_HZ
    noise_std: float = 0.001
    loss_delay: float = 0.02
    loss_mode: str = "all"
    loss_fraction: float = 0.3

    def __post_init__(self) -> None:
        check_positive("MocapParams.rate_hz", self.rate_hz)
        check_nonnegative("MocapParams.noise_std", self.noise_std)
        check_nonnegative("MocapParams.loss_delay", self.loss_delay)
        check_choice("MocapParams.loss_mode", self.loss_mode, LOSS_MODES)
        check_nonnegative("MocapParams.loss_fraction", self.loss_fraction)
        if self.loss_fraction > 1:
            raise ConfigError(
                "MocapParams.loss_fraction", f"must lie in [0, 1], got {self.loss_fraction!r}"
            )


def _check_rng(rng: object) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ConfigError("rng", f"must be a numpy.random.Generator, got {type(rng).__name__}")


def _check_times(name: str, t: np.ndarray) -> None:
    if t.ndim != 1 or t.shape[0] < 1:
        raise RecordError(f"{name} must have shape (k,) with k >= 1, got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise RecordError(f"{name} must be finite everywhere")


def _check_markers(name: str, markers: np.ndarray, k: int | None = None) -> None:
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise RecordError(f"{name} must have shape (k, n, 3), got {markers.shape}")
    if k is not None and markers.shape[0] != k:
        raise RecordError(f"{name} must have {k} frames to match its times, got {markers.shape[0]}")


def sample_times(t_end: float, rate_hz: float, t_start: float = 0.0) -> np.ndarray:
    """Frame times of a capture running at ``rate_hz`` from ``t_start`` up to ``t_end``.

    t_i = t_start + i / rate_hz,  i = 0 .. floor((t_end - t_start) * rate_hz)

    (a frame that lands within 1e-9 s of ``t_end`` is included).

    Args:
        t_end: Last admissible time [s], >= ``t_start``.
        rate_hz: Capture rate [Hz].
        t_start: Time of the first frame [s].

    Returns:
        Frame times, shape (m,) [s], m >= 1.

    Raises:
        ConfigError: ``rate_hz`` not > 0, times not finite or ``t_end < t_start``.
    """
    check_positive("rate_hz", rate_hz)
    for name, v in (("t_start", t_start), ("t_end", t_end)):
        if not np.isfinite(v):
            raise ConfigError(name, f"must be finite, got {v!r}")
    if t_end < t_start:
        raise ConfigError("t_end", f"must be >= t_start = {t_start!r}, got {t_end!r}")
    m = int(np.floor((t_end - t_start) * rate_hz + TIME_TOL * rate_hz)) + 1
    return t_start + np.arange(m) / rate_hz


def resample_markers(t_sim: np.ndarray, markers_sim: np.ndarray, t_out: np.ndarray) -> np.ndarray:
    """True marker positions at the capture frames, by linear interpolation in time.

    x(t) = (1 - w) x_j + w x_{j+1},  w = (t - t_j) / (t_{j+1} - t_j),  t_j <= t <= t_{j+1}

    Args:
        t_sim: Simulator times, shape (k,) [s], strictly increasing.
        markers_sim: True positions, shape (k, n, 3) [m] (n = 11 for the rope), finite.
        t_out: Frame times, shape (m,) [s], inside [t_sim[0], t_sim[-1]].

    Returns:
        Positions at ``t_out``, shape (m, n, 3) [m].

    Raises:
        RecordError: Bad shapes, non-increasing ``t_sim``, non-finite positions or frame
            times outside the simulated span.
    """
    t_sim = np.asarray(t_sim, dtype=float)
    markers_sim = np.asarray(markers_sim, dtype=float)
    t_out = np.asarray(t_out, dtype=float)
    _check_times("t_sim", t_sim)
    _check_markers("markers_sim", markers_sim, t_sim.shape[0])
    if t_out.ndim != 1:
        raise RecordError(f"t_out must have shape (m,), got {t_out.shape}")
    if not np.all(np.isfinite(t_out)):
        raise RecordError("t_out must be finite everywhere")
    if np.any(np.diff(t_sim) <= 0):
        raise RecordError("t_sim must be strictly increasing")
    if not np.all(np.isfinite(markers_sim)):
        raise RecordError("markers_sim must be finite everywhere")
    if t_out.size and (t_out.min() < t_sim[0] - TIME_TOL or t_out.max() > t_sim[-1] + TIME_TOL):
        raise RecordError(
            f"t_out spans [{t_out.min()}, {t_out.max()}] s, outside the simulated "
            f"[{t_sim[0]}, {t_sim[-1]}] s"
        )
    if t_sim.shape[0] == 1:
        return np.repeat(markers_sim, t_out.shape[0], axis=0)
    j = np.clip(np.searchsorted(t_sim, t_out, side="right") - 1, 0, t_sim.shape[0] - 2)
    w = np.clip((t_out - t_sim[j]) / (t_sim[j + 1] - t_sim[j]), 0.0, 1.0)[:, None, None]
    return (1.0 - w) * markers_sim[j] + w * markers_sim[j + 1]


def add_noise(markers: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Independent zero-mean Gaussian noise on every coordinate.

    y = x + e,  e ~ N(0, std^2) i.i.d. per frame, marker and axis;  NaN stays NaN.

    Args:
        markers: Positions, shape (m, n, 3) [m].
        std: Noise standard deviation [m], >= 0.
        rng: Source of randomness.

    Returns:
        Noisy positions, shape (m, n, 3) [m] (a new array).
    """
    markers = np.asarray(markers, dtype=float)
    _check_markers("markers", markers)
    check_nonnegative("std", std)
    _check_rng(rng)
    return markers + rng.normal(0.0, std, size=markers.shape) if std > 0 else markers.copy()


def loss_onset(first_contact_time: float | None, loss_delay: float) -> float | None:
    """Time from which markers are lost: t_loss = t_contact + loss_delay [s], or None."""
    if first_contact_time is None:
        return None
    if not np.isfinite(first_contact_time):
        raise ConfigError(
            "first_contact_time", f"must be a finite time or None, got {first_contact_time!r}"
        )
    return float(first_contact_time) + float(loss_delay)


def apply_tracking_loss(
    t: np.ndarray,
    markers: np.ndarray,
    first_contact_time: float | None,
    params: MocapParams,
    rng: np.random.Generator,
) -> np.ndarray:
    """Blank the markers the capture loses after the rope first touches itself.

    lost(i, j) = [t_i >= t_contact + loss_delay] * L_ij, with L_ij = 1 ("all"),
    L_ij ~ Bernoulli(loss_fraction) i.i.d. ("random") or L_ij = 0 ("none").

    Args:
        t: Frame times, shape (m,) [s].
        markers: Positions, shape (m, n, 3) [m].
        first_contact_time: Time of the rope's first self-contact [s], or None (no contact,
            nothing is lost).
        params: Capture settings (``loss_delay``, ``loss_mode``, ``loss_fraction``).
        rng: Source of randomness (drawn from only in "random" mode).

    Returns:
        Positions, shape (m, n, 3) [m], NaN where lost (a new array).
    """
    t = np.asarray(t, dtype=float)
    markers = np.array(markers, dtype=float, copy=True)
    if t.ndim != 1:
        raise RecordError(f"t must have shape (m,), got {t.shape}")
    _check_markers("markers", markers, t.shape[0])
    _check_rng(rng)
    onset = loss_onset(first_contact_time, params.loss_delay)
    if onset is None or params.loss_mode == "none":
        return markers
    after = t >= onset - TIME_TOL
    if params.loss_mode == "all":
        markers[after] = np.nan
    else:
        lost = rng.random((int(after.sum()), markers.shape[1])) < params.loss_fraction
        block = markers[after]
        block[lost] = np.nan
        markers[after] = block
    return markers


def emulate(
    t_sim: np.ndarray,
    markers_sim: np.ndarray,
    t_out: np.ndarray,
    first_contact_time: float | None,
    params: MocapParams,
    rng: np.random.Generator,
) -> np.ndarray:
    """What the capture reports for a simulated motion: resample, add noise, lose markers.

    y_i = x(t_i) + e_i, then NaN where :func:`apply_tracking_loss` loses the marker.

    Args:
        t_sim: Simulator times, shape (k,) [s], strictly increasing.
        markers_sim: True marker positions, shape (k, n, 3) [m].
        t_out: Capture frame times, shape (m,) [s], inside [t_sim[0], t_sim[-1]]; usually
            ``sample_times(t_sim[-1], params.rate_hz)`` (the caller owns the clock, so it can
            add a start offset).
        first_contact_time: The rope's first self-contact [s] or None (same clock).
        params: Capture settings.
        rng: Source of randomness (noise first, then random loss).

    Returns:
        Reported positions, shape (m, n, 3) [m], NaN where tracking is lost.
    """
    if not isinstance(params, MocapParams):
        raise ConfigError("params", f"must be a MocapParams, got {type(params).__name__}")
    t_out = np.asarray(t_out, dtype=float)
    true = resample_markers(t_sim, markers_sim, t_out)
    noisy = add_noise(true, params.noise_std, rng)
    return apply_tracking_loss(t_out, noisy, first_contact_time, params, rng)

"""Ready-made joint commands for showcases, benchmarks and tests (not learned ones)."""

from __future__ import annotations

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ
from flyknot.errors import check_positive
from flyknot.record import JointCommand

HOME_Q = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])  # [rad], UFACTORY home
HOME_Q.setflags(write=False)

# Amplitudes [rad] of the showcase swing: with duration 0.8 s they give a peak joint
# speed of 2.7 rad/s and acceleration of 29 rad/s^2, inside the paper's limits.
SWING_AMPLITUDE = np.array([0.6, 0.45, 0.6, -0.7, 0.6, -0.7, 0.7])
SWING_AMPLITUDE.setflags(write=False)


def smooth_bump(s: np.ndarray) -> np.ndarray:
    """A bump b(s) on s in [0, 1] rising from 0 to 1 at s = 0.5 and back to 0.

    b(s) = 64 s^3 (1 - s)^3: value, first and second derivative vanish at both ends.
    Shape (m,) -> (m,), dimensionless.
    """
    s = np.clip(s, 0.0, 1.0)
    return 64.0 * s**3 * (1.0 - s) ** 3


def swing_command(
    duration: float = 0.8,
    amplitude: np.ndarray = SWING_AMPLITUDE,
    q0: np.ndarray = HOME_Q,
    rate_hz: float = COMMAND_RATE_HZ,
) -> JointCommand:
    """A fast out-and-back swing of all joints from ``q0``, starting and ending at rest.

    q(t) = q0 + amplitude * b(t / duration), t in [0, duration]; shape (n, 7) [rad].
    """
    check_positive("duration", duration)
    t = np.arange(round(duration * rate_hz) + 1) / rate_hz
    q = (
        np.asarray(q0)[None, :]
        + np.asarray(amplitude)[None, :] * smooth_bump(t / duration)[:, None]
    )
    return JointCommand(q, rate_hz)

"""The joint velocities that play a position command in the controller's velocity mode.

Servo mode (``set_servo_angle_j``, mode 1) faults with C60 when the controller's TCP moves
faster than 1.2 m/s (UFACTORY's code table in the SDK, ``x_code.py``: "Linear speed exceeded
limit in servo_j mode"); the learned throws move the fingertip at 2.4-2.8 m/s (flange
2.0-2.3 m/s). Velocity mode (``vc_set_joint_velocity``, mode 4) has no such code, so a command
q (n, 7) [rad] sampled every dt [s] is played there as

    v_i = (q_{i+1} - q_i) / dt + k (q_{i-1} - q_meas),   v_{n-1} = k (q_{n-2} - q_meas),

clipped to the joint speed limits: the forward difference makes the integrated velocity pass
through every sample, and the proportional term (gain k [1/s]) pulls the measured joints back
onto the command. The reference of the correction is the previous sample, because the newest
measured joints are about one tick old when tick i is sent (200 Hz report). Without a
measurement the term is left out (feed-forward only).
"""

from __future__ import annotations

import numpy as np

from flyknot.errors import CommandError, ConfigError, check_nonnegative, check_positive

__all__ = ["VelocityStream"]


class VelocityStream:
    """Velocities of one command, tick by tick (module docstring).

    Args:
        q: Joint command, shape (n, 7) [rad], n >= 2, finite.
        dt: Tick [s], > 0.
        gain: Position gain k [1/s], >= 0.
        qd_max: Joint speed limits (7,) [rad/s] the velocities are clipped to, or None.

    Raises:
        CommandError: ``q`` is not a finite (n, 7) array with n >= 2.
        ConfigError: ``dt``, ``gain`` or ``qd_max`` out of range.
    """

    def __init__(
        self, q: np.ndarray, dt: float, gain: float, qd_max: np.ndarray | None = None
    ) -> None:
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 7 or q.shape[0] < 2 or not np.all(np.isfinite(q)):
            raise CommandError(f"q must be a finite (n >= 2, 7) array, got shape {q.shape}")
        check_positive("dt", dt)
        check_nonnegative("gain", gain)
        if qd_max is not None:
            qd_max = np.asarray(qd_max, dtype=float)
            if qd_max.shape != (7,) or not np.all(qd_max > 0):
                raise ConfigError("qd_max", f"must be 7 speeds > 0, got {qd_max!r}")
        self.q, self.dt, self.gain, self.qd_max = q, float(dt), float(gain), qd_max
        ff = np.zeros_like(q)
        ff[:-1] = np.diff(q, axis=0) / dt
        self.feed_forward = ff
        """(q_{i+1} - q_i) / dt, shape (n, 7) [rad/s]; zero at the last sample."""

    @property
    def n(self) -> int:
        """Number of ticks."""
        return self.q.shape[0]

    def at(self, i: int, q_meas: np.ndarray | None) -> np.ndarray:
        """The velocity (7,) [rad/s] to send at tick ``i`` given the newest measured joints.

        Raises:
            CommandError: ``i`` outside ``[0, n)``.
        """
        if not 0 <= i < self.n:
            raise CommandError(f"tick {i} outside the command's 0..{self.n - 1}")
        v = self.feed_forward[i].copy()
        if q_meas is not None and self.gain > 0:
            q_meas = np.asarray(q_meas, dtype=float)
            if q_meas.shape == (7,) and np.all(np.isfinite(q_meas)):
                v += self.gain * (self.q[max(i - 1, 0)] - q_meas)
        if self.qd_max is not None:
            v = np.clip(v, -self.qd_max, self.qd_max)
        return v

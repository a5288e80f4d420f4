"""Joint limits a command must respect, shared by the simulated controller and the learner.

Defaults are the paper's (appendix tables); hardware mode takes the elementwise stricter of
these and the connected robot's own (:meth:`JointLimits.stricter`). The velocity and
acceleration a limit applies to are those the controllers compute from a command's samples
(:func:`command_derivatives`): the simulated controller faults on them, the hardware preflight
refuses on them, and the learner bounds them (:func:`difference_matrices`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flyknot.constants import N_JOINTS, Q_MAX, Q_MIN, QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import CommandError, ConfigError, check_positive


def _readonly(field_name: str, a: object) -> np.ndarray:
    arr = np.array(a, dtype=float, copy=True)
    if arr.shape != (N_JOINTS,):
        raise ConfigError(field_name, f"must have shape ({N_JOINTS},), got {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ConfigError(
            field_name, f"must be finite; joint {bad[0] + 1} is {float(arr[bad[0]])!r}"
        )
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class JointLimits:
    """Limits a command must respect on every joint (default: the paper's).

    Attributes:
        q_min: Lower position limits, shape (7,) [rad].
        q_max: Upper position limits, shape (7,) [rad]; q_min < q_max.
        qd_max: Speed limits |qd| <= qd_max, shape (7,) [rad/s]; > 0.
        qdd_max: Acceleration limits |qdd| <= qdd_max, shape (7,) [rad/s^2]; > 0.
        tau_max: Torque limits |tau| <= tau_max, shape (7,) [N m]; > 0.
    """

    q_min: np.ndarray = field(default_factory=lambda: Q_MIN.copy())
    q_max: np.ndarray = field(default_factory=lambda: Q_MAX.copy())
    qd_max: np.ndarray = field(default_factory=lambda: QD_MAX.copy())
    qdd_max: np.ndarray = field(default_factory=lambda: QDD_MAX.copy())
    tau_max: np.ndarray = field(default_factory=lambda: TAU_MAX.copy())

    def __post_init__(self) -> None:
        for name in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max"):
            object.__setattr__(self, name, _readonly(f"limits.{name}", getattr(self, name)))
        for name in ("qd_max", "qdd_max", "tau_max"):
            a = getattr(self, name)
            bad = np.flatnonzero(a <= 0)
            if bad.size:
                j = bad[0]
                raise ConfigError(
                    f"limits.{name}", f"must be > 0; joint {j + 1} is {float(a[j])!r}"
                )
        bad = np.flatnonzero(self.q_min >= self.q_max)
        if bad.size:
            j = bad[0]
            lo, hi = float(self.q_min[j]), float(self.q_max[j])
            raise ConfigError(
                "limits.q_min", f"must be < limits.q_max; joint {j + 1} has {lo!r} >= {hi!r}"
            )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, JointLimits):
            return NotImplemented
        return all(
            np.array_equal(getattr(self, n), getattr(other, n))
            for n in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max")
        )

    __hash__ = None  # type: ignore[assignment]

    def with_margins(
        self,
        position: float = 0.0,
        velocity: float = 0.0,
        acceleration: float = 0.0,
        torque: float = 0.0,
    ) -> JointLimits:
        """The limits a command may use when a fraction m of each is kept free.

            |x| <= (1 - m) x_max  (velocity, acceleration, torque),
            |q - c| <= (1 - m) h  (position; c, h the range's middle and half width),

        what the hardware preflight allows under its safety margins.

        Args:
            position: Fraction of the position half range kept free, in [0, 1) [-].
            velocity: Fraction of the velocity limit kept free, in [0, 1) [-].
            acceleration: Fraction of the acceleration limit kept free, in [0, 1) [-].
            torque: Fraction of the torque limit kept free, in [0, 1) [-].
        """
        keep = {}
        for name, m in (
            ("position", position),
            ("velocity", velocity),
            ("acceleration", acceleration),
            ("torque", torque),
        ):
            if isinstance(m, bool) or not isinstance(m, (int, float)) or not 0.0 <= m < 1.0:
                raise ConfigError(f"margin.{name}", f"must lie in [0, 1), got {m!r}")
            keep[name] = 1.0 - float(m)
        c, h = 0.5 * (self.q_min + self.q_max), 0.5 * (self.q_max - self.q_min)
        return JointLimits(
            q_min=c - keep["position"] * h,
            q_max=c + keep["position"] * h,
            qd_max=keep["velocity"] * self.qd_max,
            qdd_max=keep["acceleration"] * self.qdd_max,
            tau_max=keep["torque"] * self.tau_max,
        )

    @classmethod
    def stricter(cls, a: JointLimits, b: JointLimits) -> JointLimits:
        """Elementwise stricter of two limit sets (hardware mode: paper vs connected robot).

            q_min = max(a.q_min, b.q_min),  q_max = min(a.q_max, b.q_max),
            qd_max, qdd_max, tau_max = elementwise min.

        Raises:
            ConfigError: If the two position ranges do not overlap on some joint.
        """
        return cls(
            q_min=np.maximum(a.q_min, b.q_min),
            q_max=np.minimum(a.q_max, b.q_max),
            qd_max=np.minimum(a.qd_max, b.qd_max),
            qdd_max=np.minimum(a.qdd_max, b.qdd_max),
            tau_max=np.minimum(a.tau_max, b.tau_max),
        )


def difference_matrices(n: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The controllers' central differences of n samples as matrices: qd = D1 q, qdd = D2 q.

        qd_i  = (q_{i+1} - q_{i-1}) / (2 dt)
        qdd_i = (q_{i+1} - 2 q_i + q_{i-1}) / dt^2,     i = 0 .. n-1,

    with the rest padding q_{-1} = q_0 (at rest before) and q_n = q_{n-1} (holds after), so a
    command that starts or stops moving shows its jump in qd_0, qdd_0 and qdd_{n-1}.

    Args:
        n: Number of samples (>= 1).
        dt: Sample period [s] (> 0).

    Returns:
        ``(D1, D2)``, each (n, n), [1/s] and [1/s^2].
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError("n", f"must be an integer >= 1, got {n!r}")
    check_positive("dt", dt)
    lo, hi = np.maximum(np.arange(n) - 1, 0), np.minimum(np.arange(n) + 1, n - 1)
    rows = np.arange(n)
    d1 = np.zeros((n, n))
    np.add.at(d1, (rows, hi), 0.5 / dt)
    np.add.at(d1, (rows, lo), -0.5 / dt)
    d2 = np.zeros((n, n))
    np.add.at(d2, (rows, hi), 1.0 / dt**2)
    np.add.at(d2, (rows, rows), -2.0 / dt**2)
    np.add.at(d2, (rows, lo), 1.0 / dt**2)
    return d1, d2


def check_joint_samples(q: object, name: str = "q") -> np.ndarray:
    """``q`` as a finite float array of shape (n, 7), n >= 1.

    Raises:
        CommandError: Naming ``name``, the shape, or the first non-finite sample and joint.
    """
    arr = np.asarray(q, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != N_JOINTS or arr.shape[0] < 1:
        raise CommandError(f"{name} must have shape (n, {N_JOINTS}) with n >= 1, got {arr.shape}")
    if not np.isfinite(arr).all():
        i, j = np.argwhere(~np.isfinite(arr))[0]
        raise CommandError(f"{name} is not finite at sample {i}, joint {j + 1}")
    return arr


def command_derivatives(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Joint velocity and acceleration of a command as the controllers compute them.

    The central differences with rest padding of :func:`difference_matrices`, applied to
    every joint.

    Args:
        q: Command, shape (n, 7) [rad].
        dt: Sample period [s].

    Returns:
        ``(qd, qdd)``, shapes (n, 7) [rad/s] and (n, 7) [rad/s^2].

    Raises:
        CommandError: If ``q`` is not a finite (n, 7) array.
        ConfigError: If ``dt`` is not a finite number > 0.
    """
    return central_differences(check_joint_samples(q), dt)


def central_differences(x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`difference_matrices` applied to every column of samples ``x`` (n, k), n >= 1,
    without forming the matrices: ``(D1 x, D2 x)`` [1/s, 1/s^2 times x's unit]."""
    check_positive("dt", dt)
    x = np.asarray(x, dtype=float)
    p = np.concatenate([x[:1], x, x[-1:]], axis=0)  # (n + 2, k)
    return (p[2:] - p[:-2]) / (2.0 * dt), (p[2:] - 2.0 * p[1:-1] + p[:-2]) / dt**2

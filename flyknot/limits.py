"""Joint limits a command must respect, shared by the simulated controller and the learner.

Defaults are the paper's (appendix tables); hardware mode takes the elementwise stricter of
these and the connected robot's own (:meth:`JointLimits.stricter`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flyknot.constants import N_JOINTS, Q_MAX, Q_MIN, QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import ConfigError


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

"""The xArm controller's fault checks on a joint command.

A command ``q`` (n, 7) [rad] is played at a fixed rate (250 Hz); the robot is at rest at
``q[0]`` before the first sample and holds ``q[-1]`` after the last. The controller faults
mid-motion at the first sample whose position, velocity, acceleration or torque leaves the
limits; :func:`first_fault` finds that sample the same way on a whole command (pure
functions), :class:`StreamCheck` sample by sample as a stream arrives (tick-level play).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from flyknot.constants import N_JOINTS
from flyknot.errors import CommandError, ConfigError, check_choice, check_positive
from flyknot.limits import JointLimits, check_joint_samples, command_derivatives

__all__ = [
    "QUANTITIES",
    "UNITS",
    "Fault",
    "JointLimits",
    "StreamCheck",
    "check_sample",
    "command_derivatives",
    "command_torques",
    "first_fault",
]

QUANTITIES = ("position", "velocity", "acceleration", "torque")  # also the tie-break order
UNITS = {"position": "rad", "velocity": "rad/s", "acceleration": "rad/s^2", "torque": "N m"}


def _fmt(x: float) -> str:
    s = f"{x:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


@dataclass(frozen=True)
class Fault:
    """The first limit violation of a command.

    Attributes:
        tick: Index of the command sample [-].
        time: Time of that sample, tick / rate [s].
        joint: Joint number, 1..7 (as on the robot's pendant, not a 0-based index).
        quantity: One of ``QUANTITIES``.
        value: The offending value [rad, rad/s, rad/s^2 or N m].
        limit: The bound it crossed, signed (e.g. -3.14 for a too fast negative speed).
    """

    tick: int
    time: float
    joint: int
    quantity: str
    value: float
    limit: float

    def __post_init__(self) -> None:
        check_choice("fault.quantity", self.quantity, QUANTITIES)
        check_choice("fault.joint", self.joint, range(1, N_JOINTS + 1))

    @property
    def reason(self) -> str:
        """One line for the trial record.

        Example: ``joint 4 velocity 3.52 rad/s exceeds limit 3.14 rad/s at t=0.412 s``.
        """
        u = UNITS[self.quantity]
        return (
            f"joint {self.joint} {self.quantity} {_fmt(self.value)} {u} exceeds limit "
            f"{_fmt(self.limit)} {u} at t={self.time:.3f} s"
        )


def command_torques(
    model: mujoco.MjModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """Rigid-body inverse dynamics along a command (MuJoCo's recursive Newton-Euler).

        tau_i = M(q_i) qdd_i + C(q_i, qd_i) qd_i + g(q_i)        [N m]

    Links only: no rotor inertia (armature), joint damping or friction, no rope; this is the
    torque the paper's limits apply to.

    Args:
        model: Robot-only model, nq = nv = 7, gravity on (``robot.load_robot_model()``).
        q: Positions, shape (n, 7) [rad].
        qd: Velocities, shape (n, 7) [rad/s].
        qdd: Accelerations, shape (n, 7) [rad/s^2].

    Returns:
        Joint torques, shape (n, 7) [N m].

    Raises:
        ConfigError: If ``model`` is not a 7-DoF robot-only model.
        CommandError: If the arrays are not finite (n, 7) arrays of the same shape.
    """
    if model.nq != N_JOINTS or model.nv != N_JOINTS:
        raise ConfigError(
            "model",
            f"must be the robot alone (nq = nv = {N_JOINTS}), got nq={model.nq}, nv={model.nv}",
        )
    q, qd, qdd = (
        check_joint_samples(q),
        check_joint_samples(qd, "qd"),
        check_joint_samples(qdd, "qdd"),
    )
    if not (q.shape == qd.shape == qdd.shape):
        raise CommandError(f"q, qd, qdd shapes differ: {q.shape}, {qd.shape}, {qdd.shape}")
    data = mujoco.MjData(model)
    tau = np.empty_like(q)
    row = np.empty(N_JOINTS)
    for i in range(q.shape[0]):
        tau[i] = _rne(model, data, q[i], qd[i], qdd[i], row)
    return tau


def _rne(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:
    """tau = M(q) qdd + C(q, qd) qd + g(q) of one sample into ``out`` (7,) [N m]."""
    data.qpos[:] = q
    data.qvel[:] = qd
    data.qacc[:] = qdd
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    mujoco.mj_comVel(model, data)
    mujoco.mj_rne(model, data, 1, out)
    return out


def _first(value: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[int, int, float] | None:
    """Earliest (tick, joint index, crossed bound) with value outside [lo, hi], or None."""
    bad = (value < lo) | (value > hi)  # (n, 7)
    rows = np.flatnonzero(bad.any(axis=1))
    if rows.size == 0:
        return None
    i = int(rows[0])
    j = int(np.flatnonzero(bad[i])[0])
    bound = lo[j] if value[i, j] < lo[j] else hi[j]
    return i, j, float(bound)


def first_fault(
    q: np.ndarray,
    dt: float,
    *,
    limits: JointLimits | None = None,
    torques: np.ndarray | None = None,
) -> Fault | None:
    """The earliest limit violation of a command, as the xArm controller would fault on it.

    A sample i faults if, on any joint j (strict inequalities, no tolerance),

        q_ij < q_min_j or q_ij > q_max_j,  |qd_ij| > qd_max_j,
        |qdd_ij| > qdd_max_j,  or |tau_ij| > tau_max_j,

    with qd, qdd from :func:`command_derivatives`. The earliest sample wins; on the same sample
    the order is position, velocity, acceleration, torque, then the lowest joint.

    Args:
        q: Command, shape (n, 7) [rad].
        dt: Sample period [s] (0.004 at 250 Hz).
        limits: Limits to check; the paper's if None.
        torques: Joint torques along the command, shape (n, 7) [N m] (see
            :func:`command_torques`); torque is not checked if None.

    Returns:
        The first :class:`Fault`, or None if the command stays inside every limit.

    Raises:
        CommandError: If ``q`` or ``torques`` is malformed.
        ConfigError: If ``dt`` is not a finite number > 0.
    """
    limits = JointLimits() if limits is None else limits
    qd, qdd = command_derivatives(q, dt)
    q = np.asarray(q, dtype=float)
    checks: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = [
        ("position", q, limits.q_min, limits.q_max),
        ("velocity", qd, -limits.qd_max, limits.qd_max),
        ("acceleration", qdd, -limits.qdd_max, limits.qdd_max),
    ]
    if torques is not None:
        tau = check_joint_samples(torques, "torques")
        if tau.shape != q.shape:
            raise CommandError(f"torques must have the shape of q {q.shape}, got {tau.shape}")
        checks.append(("torque", tau, -limits.tau_max, limits.tau_max))
    best: Fault | None = None
    for quantity, value, lo, hi in checks:
        hit = _first(value, lo, hi)
        if hit is not None and (best is None or hit[0] < best.tick):
            i, j, bound = hit
            best = Fault(i, i * dt, j + 1, quantity, float(value[i, j]), bound)
    return best


class StreamCheck:
    """The controller's checks on a command that arrives one sample at a time.

    The derivatives are those of :func:`command_derivatives`, centred on a sample, so sample
    i's velocity, acceleration and torque are known when sample i + 1 arrives (or the stream
    ends: q_n = q_{n-1}, the hold); its position as it arrives. Before the first sample the
    arm rests at ``q_start`` (q_{-1} = ``q_start``; a stream that starts at its own first
    sample, as a whole command does, pads exactly like :func:`command_derivatives`).

    So :meth:`push` of sample i checks sample i - 1's velocity, acceleration and torque, then
    sample i's position; :meth:`close` checks the last sample's. The first :class:`Fault` is
    the one :func:`first_fault` finds on the samples pushed so far (same values, same order:
    the earliest sample, then position, velocity, acceleration, torque, then the lowest
    joint), reported as soon as the controller can know it: at the same sample for a
    position, one sample later for the rest. After a fault the check is over: further pushes
    are refused.
    """

    def __init__(
        self,
        q_start: np.ndarray,
        dt: float,
        *,
        limits: JointLimits | None = None,
        torque_model: mujoco.MjModel | None = None,
    ):
        """Check a stream at period ``dt`` [s] from rest at ``q_start`` (7,) [rad] against
        ``limits`` (the paper's if None); torques too with ``torque_model`` (the robot alone,
        as for :func:`command_torques`)."""
        check_positive("dt", dt)
        self.dt = float(dt)
        self.limits = JointLimits() if limits is None else limits
        self._model = torque_model
        if torque_model is not None:
            if torque_model.nq != N_JOINTS or torque_model.nv != N_JOINTS:
                raise ConfigError(
                    "torque_model",
                    f"must be the robot alone (nq = nv = {N_JOINTS}), got nq={torque_model.nq}",
                )
            self._data = mujoco.MjData(torque_model)
            self._row = np.empty(N_JOINTS)
        self._prev = check_sample(q_start)  # q_{i-2} when sample i arrives
        self._last: np.ndarray | None = None  # q_{i-1}
        self._closed = False
        self.n = 0
        """Samples pushed."""
        self.fault: Fault | None = None
        """The first fault, once found."""

    def _derivatives(self, q_next: np.ndarray) -> Fault | None:
        """Velocity, acceleration and torque of the last sample, now that q_next is known."""
        i, lim = self.n - 1, self.limits
        p0, p1, p2 = self._prev, self._last, q_next
        qd = (p2 - p0) / (2.0 * self.dt)
        qdd = (p2 - 2.0 * p1 + p0) / self.dt**2
        checks = [
            ("velocity", qd, -lim.qd_max, lim.qd_max),
            ("acceleration", qdd, -lim.qdd_max, lim.qdd_max),
        ]
        if self._model is not None:
            tau = _rne(self._model, self._data, p1, qd, qdd, self._row)
            checks.append(("torque", tau, -lim.tau_max, lim.tau_max))
        return self._first_of(i, checks)

    def _first_of(self, i: int, checks) -> Fault | None:
        for quantity, value, lo, hi in checks:
            hit = _first(value[None, :], lo, hi)
            if hit is not None:
                _, j, bound = hit
                return Fault(i, i * self.dt, j + 1, quantity, float(value[j]), bound)
        return None

    def push(self, q: np.ndarray) -> Fault | None:
        """Take the next sample (7,) [rad]; the first fault if this sample reveals it.

        Raises:
            CommandError: The sample is not 7 finite numbers, or the stream has already
                faulted or been closed (nothing changes then).
        """
        if self.fault is not None:
            raise CommandError(f"the stream faulted at sample {self.fault.tick}: {self.fault}")
        if self._closed:
            raise CommandError("the stream is closed")
        q = check_sample(q)
        fault = None
        if self._last is not None:
            fault = self._derivatives(q)
            self._prev = self._last
        if fault is None:
            lim = self.limits
            fault = self._first_of(self.n, [("position", q, lim.q_min, lim.q_max)])
        self._last = q
        self.n += 1
        self.fault = fault
        return fault

    def close(self) -> Fault | None:
        """End the stream (the arm holds the last sample); the last sample's fault, if any.

        Closing again, or after a fault, finds nothing more.
        """
        if self._closed or self.fault is not None or self._last is None:
            self._closed = True
            return None
        self._closed = True
        self.fault = self._derivatives(self._last)
        return self.fault


def check_sample(q: object) -> np.ndarray:
    """``q`` as a new (7,) float array [rad]; :class:`CommandError` unless 7 finite numbers."""
    arr = np.array(q, dtype=float, copy=True)
    if arr.shape != (N_JOINTS,):
        raise CommandError(f"sample must have shape ({N_JOINTS},), got {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise CommandError(f"sample is not finite at joint {bad[0] + 1}")
    return arr

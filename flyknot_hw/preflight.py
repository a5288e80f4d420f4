"""Check a whole command against the limits before anything moves.

A :class:`~flyknot.record.JointCommand` ``q`` (n, 7) [rad] at its rate (250 Hz) is checked,
sample by sample, against the stricter of the paper's limits and the robot's own
(:func:`effective_limits`), each shrunk by its safety margin
(:class:`~flyknot_hw.config.Margins`):

* position: ``|q - c| <= (1 - m) h`` with c, h the middle and half-width of the range;
* velocity, acceleration (by finite differences, :func:`command_derivatives`) and, when the
  application supplies them, torques (n, 7) [N m]: ``|x| <= (1 - m) x_max``;
* when fingertip positions (n, 3) [m, base frame] are supplied: inside the workspace box.

The *use* of a limit is the value as a fraction of the raw (unshrunk) limit, so a command
passes when every use is at most ``1 - margin``. A failing command raises
:class:`PreflightError` naming the joint (1-based), the sample and its time, the value and the
limit; a passing one returns a :class:`PreflightReport` of the peak use of every limit.

The robot's own ranges: read from the connected robot (``flyknot_hw.xarm_cell``), or the
published ones (:func:`published_robot_limits`) when no robot is connected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flyknot.constants import N_JOINTS, Q4_MIN_NEW_SERIALS, QDD_MAX, TAU_MAX
from flyknot.errors import CommandError, ConfigError, HardwareError, check_positive
from flyknot.limits import JointLimits, central_differences, command_derivatives
from flyknot.record import JointCommand
from flyknot_hw.config import Margins, Workspace

__all__ = [
    "QUANTITIES",
    "UNITS",
    "PreflightError",
    "PreflightReport",
    "check_pose",
    "command_derivatives",
    "effective_limits",
    "preflight",
    "published_robot_limits",
]

QUANTITIES = ("position", "velocity", "acceleration", "torque", "workspace", "tip_speed")
"""What is checked, in the order that breaks ties on the same sample."""
UNITS = {
    "position": "rad",
    "velocity": "rad/s",
    "acceleration": "rad/s^2",
    "torque": "N m",
    "workspace": "m",
    "tip_speed": "m/s",
}
AXES = ("x", "y", "z")

# Published xArm 7 joint ranges [rad]: UFACTORY's xarm_ros description (xarm7 joint limits);
# newer serials (SN digits 2..5 >= 1305, xarm-python-sdk 1.18.4 XCONF.Robot.JOINT_LIMITS
# type 71305) have joint 2 in [-2.042035, 2.024581] and joint 4's lower limit at -0.10472.
_TWO_PI = 2.0 * math.pi
PUBLISHED_Q_MIN = np.array([-_TWO_PI, -2.059, -_TWO_PI, -0.19198, -_TWO_PI, -1.69297, -_TWO_PI])
PUBLISHED_Q_MAX = np.array([_TWO_PI, 2.0944, _TWO_PI, 3.927, _TWO_PI, 3.14159, _TWO_PI])
NEW_SERIAL_Q2 = (-2.042035, 2.024581)
ROBOT_QD_MAX = math.pi  # [rad/s] xArm 7 maximum joint speed (180 deg/s)
for _a in (PUBLISHED_Q_MIN, PUBLISHED_Q_MAX):
    _a.setflags(write=False)


def published_robot_limits(newer_serial: bool = True) -> JointLimits:
    """The xArm 7's own limits as published, for checks without a connected robot.

    Positions from the published ranges; speed ``pi`` rad/s on every joint. The robot
    publishes no acceleration or torque limits for streamed targets, so those are the paper's
    (``JointLimits.stricter`` then keeps the paper's).

    Args:
        newer_serial: Use the newer serials' stricter joint 2 and joint 4 ranges (the safe
            choice when the serial is unknown).
    """
    q_min, q_max = PUBLISHED_Q_MIN.copy(), PUBLISHED_Q_MAX.copy()
    if newer_serial:
        q_min[1], q_max[1] = NEW_SERIAL_Q2
        q_min[3] = Q4_MIN_NEW_SERIALS
    return JointLimits(
        q_min=q_min,
        q_max=q_max,
        qd_max=np.full(N_JOINTS, ROBOT_QD_MAX),
        qdd_max=QDD_MAX.copy(),
        tau_max=TAU_MAX.copy(),
    )


def effective_limits(robot: JointLimits | None = None) -> JointLimits:
    """The stricter of the paper's limits and ``robot``'s (published ones if None)."""
    return JointLimits.stricter(JointLimits(), robot or published_robot_limits())


def _fmt(x: float) -> str:
    s = f"{x:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


class PreflightError(HardwareError):
    """A command (or a pose) that breaks a limit; nothing was sent to the robot.

    Attributes:
        quantity: One of :data:`QUANTITIES`.
        joint: Joint number 1..7, or None for the workspace.
        axis: ``"x"``, ``"y"`` or ``"z"`` for the workspace, else None.
        sample: Command sample index, or None for a single pose.
        time: Time of the sample [s], or None.
        value: The offending value [rad, rad/s, rad/s^2, N m or m].
        limit: The bound it crossed, margin included (signed).
        raw_limit: The same bound without the margin (signed).
    """

    def __init__(
        self,
        quantity: str,
        value: float,
        limit: float,
        raw_limit: float,
        *,
        joint: int | None = None,
        axis: str | None = None,
        sample: int | None = None,
        time: float | None = None,
        what: str = "command",
    ):
        self.quantity, self.joint, self.axis = quantity, joint, axis
        self.sample, self.time = sample, time
        self.value, self.limit, self.raw_limit = value, limit, raw_limit
        u = UNITS[quantity]
        where = "" if sample is None else f" at sample {sample} (t = {time:.3f} s)"
        if quantity == "tip_speed":
            msg = (
                f"{what}: fingertip speed {_fmt(value)} m/s exceeds {_fmt(limit)} m/s "
                f"(safety.tip_speed_max {_fmt(raw_limit)} m/s, the controller's servo-mode "
                f"TCP speed limit (C60), with the safety margin){where}; streaming joint "
                'velocities instead (robot.stream = "velocity") has no such limit'
            )
        elif quantity == "workspace":
            side = "min" if value < limit else "max"
            msg = (
                f"{what}: fingertip {axis} = {_fmt(value)} m leaves the workspace box "
                f"(safety.workspace.{side} {axis} = {_fmt(limit)} m, base frame){where}"
            )
        else:
            verb = "is below" if value < limit else "exceeds"
            msg = (
                f"{what}: joint {joint} {quantity} {_fmt(value)} {u} {verb} {_fmt(limit)} {u} "
                f"(the limit {_fmt(raw_limit)} {u} with the safety margin){where}"
            )
        super().__init__(msg + "; nothing was sent to the robot")


@dataclass(frozen=True)
class PreflightReport:
    """How close a passing command came to each limit.

    Attributes:
        n: Samples checked.
        rate_hz: Command rate [Hz].
        peak_use: For each checked quantity, the peak use per joint (per axis for the
            workspace), shape (7,) or (3,) [-]; 1.0 is the raw limit.
        peak_sample: Sample index of each peak, same shapes.
        allowed: Largest allowed use per quantity, ``1 - margin`` (1.0 for the workspace).
        limits: The effective limits the command was checked against (before margins).
        tip_speed_peak: Peak fingertip speed [m/s] (central differences) when fingertip
            positions were given, else None. Not limited here; for comparison with the
            controller's servo_j TCP speed limit (C60 above 1.2 m/s at its TCP).
    """

    n: int
    rate_hz: float
    peak_use: dict[str, np.ndarray]
    peak_sample: dict[str, np.ndarray]
    allowed: dict[str, float]
    limits: JointLimits = field(repr=False)
    tip_speed_peak: float | None = None

    @property
    def checked(self) -> tuple[str, ...]:
        """The quantities that were checked (torque and workspace only when supplied)."""
        return tuple(q for q in QUANTITIES if q in self.peak_use)

    def worst(self) -> tuple[str, int, float]:
        """(quantity, joint number or axis index + 1, use) of the highest use relative to
        what is allowed."""
        best = ("position", 1, -1.0)
        score = -math.inf
        for q in self.checked:
            u = self.peak_use[q]
            k = int(np.argmax(u))
            s = float(u[k]) / self.allowed[q]
            if s > score:
                score, best = s, (q, k + 1, float(u[k]))
        return best

    def as_metadata(self) -> dict[str, Any]:
        """Plain data for a trial record's metadata."""
        return {
            "n": self.n,
            "rate_hz": self.rate_hz,
            "checked": list(self.checked),
            "peak_use": {k: [round(float(x), 4) for x in v] for k, v in self.peak_use.items()},
            "peak_sample": {k: [int(x) for x in v] for k, v in self.peak_sample.items()},
            "allowed": dict(self.allowed),
            "tip_speed_peak_m_s": self.tip_speed_peak,
            "limits": {
                name: [float(x) for x in getattr(self.limits, name)]
                for name in ("q_min", "q_max", "qd_max", "qdd_max", "tau_max")
            },
        }


def _as_samples(name: str, a: object, n: int, width: int) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.shape != (n, width):
        raise CommandError(f"{name} must have shape ({n}, {width}), got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise CommandError(f"{name} is not finite at sample {i}, column {j + 1}")
    return arr


def _centred(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _first_over(use: np.ndarray, allowed: float) -> tuple[int, int] | None:
    bad = use > allowed
    rows = np.flatnonzero(bad.any(axis=1))
    if rows.size == 0:
        return None
    i = int(rows[0])
    return i, int(np.flatnonzero(bad[i])[0])


_Check = tuple[str, np.ndarray, np.ndarray, float, Any, Any]
"""(quantity, value (n, k), use (n, k), allowed use, centre (k,), half range (k,))."""


def _checks(
    command: JointCommand,
    limits: JointLimits,
    margins: Margins,
    torques: np.ndarray | None,
    fingertip: np.ndarray | None,
    workspace: Workspace | None,
    tip_speed_max: float | None,
) -> list[_Check]:
    """Every quantity :func:`preflight` checks, as the use of its limit at every sample."""
    q = np.asarray(command.q, dtype=float)
    n, dt = command.n, command.dt
    qd, qdd = command_derivatives(q, dt)
    c, h = _centred(limits.q_min, limits.q_max)
    checks: list[_Check] = [("position", q, np.abs(q - c) / h, margins.allowed("position"), c, h)]
    for name, x, x_max in (("velocity", qd, limits.qd_max), ("acceleration", qdd, limits.qdd_max)):
        checks.append((name, x, np.abs(x) / x_max, margins.allowed(name), 0, x_max))
    if torques is not None:
        tau = _as_samples("torques", torques, n, N_JOINTS)
        allowed = margins.allowed("torque")
        checks.append(("torque", tau, np.abs(tau) / limits.tau_max, allowed, 0, limits.tau_max))
    if fingertip is not None:
        if workspace is None:
            raise ConfigError("workspace", "is required to check fingertip positions")
        p = _as_samples("fingertip", fingertip, n, 3)
        wc, wh = _centred(workspace.lo, workspace.hi)
        checks.append(("workspace", p, np.abs(p - wc) / wh, 1.0, wc, wh))
        if tip_speed_max is not None:
            check_positive("tip_speed_max", tip_speed_max)
            v = np.linalg.norm(central_differences(p, dt)[0], axis=1)[:, None]
            allowed = margins.allowed("velocity")
            checks.append(("tip_speed", v, v / tip_speed_max, allowed, 0, tip_speed_max))
    return checks


def _raise_first_violation(checks: list[_Check], dt: float) -> None:
    """Raise :class:`PreflightError` for the earliest sample over its allowed use (on one
    sample: the first check in order, then the lowest column); return if there is none."""
    first: tuple[int, int, int] | None = None  # (sample, check index, column)
    for k, (_, _, use, allowed, _, _) in enumerate(checks):
        hit = _first_over(use, allowed)
        if hit is not None and (first is None or hit[0] < first[0]):
            first = (hit[0], k, hit[1])
    if first is None:
        return
    i, k, j = first
    quantity, value, _, allowed, centre, half = checks[k]
    v = float(value[i, j])
    centre_j = float(np.broadcast_to(centre, (value.shape[1],))[j])
    half_j = float(np.broadcast_to(half, (value.shape[1],))[j])
    sign = 1.0 if v >= centre_j else -1.0
    raise PreflightError(
        quantity,
        v,
        centre_j + sign * allowed * half_j,
        centre_j + sign * half_j,
        joint=None if quantity in ("workspace", "tip_speed") else j + 1,
        axis=AXES[j] if quantity == "workspace" else None,
        sample=i,
        time=i * dt,
    )


def preflight(
    command: JointCommand,
    limits: JointLimits,
    *,
    margins: Margins | None = None,
    torques: np.ndarray | None = None,
    fingertip: np.ndarray | None = None,
    workspace: Workspace | None = None,
    tip_speed_max: float | None = None,
) -> PreflightReport:
    """Check every sample of ``command``; raise on the first violation.

    The earliest sample wins; on the same sample the order is :data:`QUANTITIES`, then the
    lowest joint (axis).

    Args:
        command: The command, q (n, 7) [rad] at ``command.rate_hz``.
        limits: Effective limits (:func:`effective_limits`), before margins.
        margins: Safety margins; the default 5 % on every quantity.
        torques: Joint torques along the command, shape (n, 7) [N m], or None (not checked).
        fingertip: Fingertip positions along the command in the base frame, shape (n, 3)
            [m], or None (not checked).
        workspace: The box ``fingertip`` must stay in; required with ``fingertip``.
        tip_speed_max: Largest fingertip speed [m/s] (the controller faults with C60 above
            its TCP speed limit in servo mode), checked with the velocity margin when
            ``fingertip`` is given; None: not checked.

    Returns:
        The peak use of each limit.

    Raises:
        PreflightError: On the first sample that breaks a limit.
        CommandError: If ``torques`` or ``fingertip`` is malformed.
        ConfigError: If ``fingertip`` is given without ``workspace``.
    """
    if not isinstance(command, JointCommand):
        raise CommandError(f"command must be a JointCommand, got {type(command).__name__}")
    if not isinstance(limits, JointLimits):
        raise ConfigError("limits", f"must be a JointLimits, got {type(limits).__name__}")
    margins = Margins() if margins is None else margins
    checks = _checks(command, limits, margins, torques, fingertip, workspace, tip_speed_max)
    _raise_first_violation(checks, command.dt)
    tip_speed = None
    if fingertip is not None:
        p = np.asarray(fingertip, dtype=float)
        tip_speed = float(np.max(np.linalg.norm(central_differences(p, command.dt)[0], axis=1)))
    return PreflightReport(
        n=command.n,
        rate_hz=float(command.rate_hz),
        peak_use={name: use.max(axis=0) for name, _, use, _, _, _ in checks},
        peak_sample={name: use.argmax(axis=0) for name, _, use, _, _, _ in checks},
        allowed={name: allowed for name, _, _, allowed, _, _ in checks},
        limits=limits,
        tip_speed_peak=tip_speed,
    )


def check_pose(
    q: np.ndarray, limits: JointLimits, margins: Margins | None = None, what: str = "pose"
) -> None:
    """Raise :class:`PreflightError` if the joint pose ``q`` (7,) [rad] is outside the
    position limits with their margin (e.g. the robot's current pose before a move)."""
    margins = Margins() if margins is None else margins
    q = np.asarray(q, dtype=float)
    if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
        raise CommandError(f"{what} must be a finite array of shape ({N_JOINTS},), got {q!r}")
    c, h = _centred(limits.q_min, limits.q_max)
    use = np.abs(q - c) / h
    allowed = margins.allowed("position")
    bad = np.flatnonzero(use > allowed)
    if bad.size:
        j = int(bad[0])
        sign = 1.0 if q[j] >= c[j] else -1.0
        raise PreflightError(
            "position",
            float(q[j]),
            float(c[j] + sign * allowed * h[j]),
            float(c[j] + sign * h[j]),
            joint=j + 1,
            what=what,
        )

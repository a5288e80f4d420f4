"""The calibration tour, planned and checked before anything moves (``flyknot calibrate``).

:func:`plan_calibration` checks every pose against the position limits with the margin, then
every move of the tour start -> pose 1 -> ... -> pose k -> start, planned as the controller
moves in position mode (:func:`planned_move`: straight in joint space at the lab file's
``robot.start_speed`` and ``robot.start_acc``), with the same
:func:`~flyknot_hw.preflight.preflight` a throw gets: positions, speeds, accelerations,
torques (when the application supplies its inverse dynamics), the fingertip in the workspace
box and under ``safety.tip_speed_max``. A failure raises
:class:`~flyknot_hw.preflight.PreflightError` naming the pose or the move.
:func:`dry_run_plan` does it without a robot (the published limits, the tour from
``calibration.start``). The plan reports the fit's conditioning
(:func:`~flyknot_hw.mocap.calibration.fit_conditioning`) of the poses' fingertips.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError
from flyknot.limits import JointLimits
from flyknot.record import JointCommand
from flyknot_hw.config import LabConfig
from flyknot_hw.mocap.calibration import FitConditioning, fit_conditioning
from flyknot_hw.preflight import (
    PreflightError,
    PreflightReport,
    check_pose,
    effective_limits,
    preflight,
)

__all__ = [
    "DEFAULT_OFFSETS",
    "CalibrationPlan",
    "Kinematics",
    "PlannedMove",
    "TorqueModel",
    "as_poses",
    "default_poses",
    "dry_run_plan",
    "plan_calibration",
    "planned_move",
]

DEFAULT_OFFSETS = np.array(
    [  # joint offsets from calibration.start [rad]; joints 1, 2, 4, 6 (3, 5, 7 unchanged)
        [-0.4, -0.4, 0, 0.0, 0, +0.5, 0],
        [-0.4, -0.4, 0, 0.6, 0, -0.5, 0],
        [-0.4, +0.1, 0, 0.6, 0, +0.5, 0],
        [-0.4, +0.1, 0, 0.0, 0, -0.5, 0],
        [+0.4, +0.1, 0, 0.0, 0, -0.5, 0],
        [+0.4, +0.1, 0, 0.6, 0, +0.5, 0],
        [+0.4, -0.4, 0, 0.6, 0, -0.5, 0],
        [+0.4, -0.4, 0, 0.0, 0, +0.5, 0],
    ]
)
"""The default calibration poses as offsets from ``calibration.start`` [rad]: the 8 corners of
a box in joints 1 (base yaw +-0.4), 2 (shoulder -0.4 back / +0.1 forward) and 4 (elbow 0 /
+0.6 more bent), with the wrist (joint 6) tilted +-0.5 to add depth, in Gray-code order
(consecutive poses differ in one of joints 1, 2, 4, and the wrist). From UFACTORY's home
pose the fingertip covers x 0.24..0.45 m, y -0.19..0.19 m, z 0.31..0.85 m in the base
frame: spread 208 / 149 / 71 mm rms along the principal axes, rotation condition 1.55
(:func:`~flyknot_hw.mocap.calibration.fit_conditioning`)."""
DEFAULT_OFFSETS.setflags(write=False)

Kinematics = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""q (k, 7) [rad] -> fingertip positions (k, 3) [m] (base frame) and quaternions (k, 4)."""
TorqueModel = Callable[[JointCommand], np.ndarray]
"""A command -> joint torques along it (n, 7) [N m] (the learner's inverse dynamics)."""


def default_poses(start: np.ndarray) -> np.ndarray:
    """The default calibration poses (k, 7) [rad]: ``start`` + :data:`DEFAULT_OFFSETS`."""
    q = np.asarray(start, dtype=float)
    if q.shape != (7,) or not np.all(np.isfinite(q)):
        raise ConfigError("calibration.start", f"must be 7 finite joint angles, got {q!r}")
    return q[None, :] + DEFAULT_OFFSETS


def planned_move(
    q_from: np.ndarray, q_to: np.ndarray, speed: float, acc: float, rate_hz: float
) -> JointCommand:
    """A slow joint move as the controller plans it, sampled at ``rate_hz``: straight in joint
    space, the joint that moves furthest on a trapezoidal speed profile (``speed`` [rad/s],
    ``acc`` [rad/s^2]), the others in proportion; at rest at both ends."""
    a, b = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
    dist = float(np.max(np.abs(b - a)))
    if dist < 1e-9:
        return JointCommand(np.vstack([b, b]), rate_hz=rate_hz)
    t_acc = speed / acc
    if dist < speed * t_acc:  # never reaches full speed: a triangle
        t_acc = float(np.sqrt(dist / acc))
    v = acc * t_acc
    t_end = 2.0 * t_acc + (dist - v * t_acc) / v
    t = np.append(np.arange(0.0, t_end, 1.0 / rate_hz), t_end)
    s = np.where(
        t < t_acc,
        0.5 * acc * t**2,
        np.where(
            t <= t_end - t_acc,
            0.5 * v * t_acc + v * (t - t_acc),
            dist - 0.5 * acc * np.clip(t_end - t, 0.0, None) ** 2,
        ),
    )
    q = a + np.clip(s / dist, 0.0, 1.0)[:, None] * (b - a)[None, :]
    return JointCommand(np.vstack([q, b]), rate_hz=rate_hz)


@dataclass(frozen=True)
class PlannedMove:
    """One checked move of the tour.

    Attributes:
        target: What it goes to (``"calibration pose 3"``, ``"the start pose"``).
        duration_s: Its planned duration [s].
        report: The preflight's report (peak use of every limit).
    """

    target: str
    duration_s: float
    report: PreflightReport


@dataclass(frozen=True)
class CalibrationPlan:
    """The poses, their fingertips and the checked moves, before anything moves.

    Attributes:
        poses: The calibration poses, shape (k, 7) [rad].
        q_start: Where the tour starts and ends (7,) [rad].
        tips: Fingertips at the poses by forward kinematics, base frame, shape (k, 3) [m].
        moves: Start -> pose 1 -> ... -> pose k -> start, each preflighted.
        conditioning: Of a fit to ``tips``.
        limits_note: Which limits the preflight used.
    """

    poses: np.ndarray
    q_start: np.ndarray
    tips: np.ndarray
    moves: tuple[PlannedMove, ...]
    conditioning: FitConditioning
    limits_note: str

    def describe(self) -> list[str]:
        """The plan as lines of text."""
        k = len(self.poses)
        total = sum(m.duration_s for m in self.moves)
        lines = [
            f"calibration plan: {k} poses, {len(self.moves)} moves ({total:.1f} s of motion); "
            f"preflight against {self.limits_note}",
            f"  start: joints [deg] {deg(self.q_start)}",
        ]
        for i, (q, tip, move) in enumerate(zip(self.poses, self.tips, self.moves, strict=False)):
            lines.append(
                f"  pose {i + 1}: joints [deg] {deg(q)}; fingertip (base frame) "
                f"{xyz(tip)} m; move {move.duration_s:.1f} s, {_worst(move.report)}"
            )
        lines.append(f"  back to the start: {self.moves[-1].duration_s:.1f} s")
        lines.append(f"  conditioning: {self.conditioning.summary()}")
        return lines


def _worst(report: PreflightReport) -> str:
    quantity, j, use = report.worst()
    if quantity == "workspace":
        where = " " + "xyz"[j - 1]
    else:
        where = "" if quantity == "tip_speed" else f" joint {j}"
    return f"highest use {use:.2f} of a limit ({quantity}{where})"


def deg(q: np.ndarray) -> str:
    """Joint angles as ``(a, b, ...)`` in degrees, for messages."""
    return "(" + ", ".join(f"{np.degrees(x):.1f}" for x in q) + ")"


def xyz(p: np.ndarray) -> str:
    """A position as ``(x, y, z)`` in metres (3 decimals), for messages."""
    return "(" + ", ".join(f"{x:.3f}" for x in p) + ")"


def as_poses(poses: object) -> np.ndarray:
    """``poses`` as a (k, 7) array [rad], k >= 1, finite (else :class:`ConfigError`)."""
    q = np.asarray(poses, dtype=float)
    if q.ndim != 2 or q.shape[1] != 7 or q.shape[0] < 1 or not np.all(np.isfinite(q)):
        raise ConfigError("poses", f"must be finite joint poses of 7 joints, (k, 7), got {q.shape}")
    return q


def plan_calibration(
    config: LabConfig,
    poses: np.ndarray,
    fingertip: Kinematics,
    *,
    limits: JointLimits,
    q_start: np.ndarray,
    torques: TorqueModel | None = None,
    limits_note: str = "the connected robot's limits",
    what_start: str = "the robot's current pose",
) -> CalibrationPlan:
    """Check every pose and every move of the tour (module docstring, step 3).

    Raises:
        ConfigError: Fewer poses than ``calibration.min_poses``, or malformed poses.
        PreflightError: A pose or a move breaks a limit (the message names it).
    """
    q = as_poses(poses)
    need = config.calibration.min_poses
    if len(q) < need:
        raise ConfigError(
            "poses", f"needs at least calibration.min_poses = {need} poses, got {len(q)}"
        )
    safety = config.safety
    q0 = np.asarray(q_start, dtype=float)
    check_pose(q0, limits, safety.margins, what=what_start)
    for i, row in enumerate(q):
        check_pose(row, limits, safety.margins, what=f"calibration pose {i + 1}")
    stops = [q0, *q, q0]
    robot = config.robot
    moves = []
    for i in range(len(stops) - 1):
        target = f"calibration pose {i + 1}" if i < len(q) else "the start pose"
        origin = "the start" if i == 0 else f"pose {i}"
        cmd = planned_move(
            stops[i], stops[i + 1], robot.start_speed, robot.start_acc, robot.servo_rate_hz
        )
        try:
            report = preflight(
                cmd, limits, margins=safety.margins,
                torques=None if torques is None else torques(cmd),
                fingertip=np.asarray(fingertip(np.asarray(cmd.q))[0]),
                workspace=safety.workspace, tip_speed_max=safety.tip_speed_max,
            )  # fmt: skip
        except PreflightError as e:
            raise PreflightError(
                e.quantity, e.value, e.limit, e.raw_limit, joint=e.joint, axis=e.axis,
                sample=e.sample, time=e.time, what=f"the move to {target} (from {origin})",
            ) from None  # fmt: skip
        moves.append(PlannedMove(target, cmd.duration, report))
    tips = np.asarray(fingertip(q)[0], dtype=float)
    return CalibrationPlan(q, q0, tips, tuple(moves), fit_conditioning(tips), limits_note)


def dry_run_plan(
    config: LabConfig,
    fingertip: Kinematics,
    *,
    poses: np.ndarray | None = None,
    torques: TorqueModel | None = None,
) -> CalibrationPlan:
    """The plan without a robot: the published limits, the tour from ``calibration.start``."""
    start = config.calibration.start
    return plan_calibration(
        config,
        default_poses(start) if poses is None else poses,
        fingertip,
        limits=effective_limits(),
        q_start=start,
        torques=torques,
        limits_note="the published xArm 7 limits (dry run: no robot asked)",
        what_start="calibration.start",
    )

"""Connecting to the xArm and moving it slowly, checked: shared by the cell and the calibration.

:class:`~flyknot_hw.xarm_cell.XArmCell` (the move to a command's start pose) and
:mod:`flyknot_hw.calibrate_driver` (the moves through the calibration poses) use the same
pieces, so that both stop the same way:

* :func:`connect_arm`: the SDK connection of the lab file's ``[robot]`` and the effective
  limits (the stricter of the paper's and the connected robot's own);
* :func:`check_controller`: refuse, naming the code, while the controller reports an error or
  a warning (:func:`controller_codes` asks it now);
* :func:`check_move_path`: the current pose within the position limits (with the margin) and
  the fingertip within the workspace box along the straight joint-space path to a goal;
* :func:`position_mode`, :func:`move_joints`: a joint move in position mode at the lab file's
  ``robot.start_speed`` / ``robot.start_acc``, polled until the goal is reached; every poll
  checks Ctrl-C (a :class:`~flyknot_hw.timing.SigintLatch`) and the controller's error and
  warning flags, and raises (the caller stops the arm: :func:`flyknot_hw.xarm_sdk.stop_arm`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from flyknot.errors import HardwareError
from flyknot.limits import JointLimits
from flyknot_hw import xarm_sdk
from flyknot_hw.config import RobotConfig, SafetyConfig
from flyknot_hw.preflight import PreflightError, check_pose
from flyknot_hw.timing import SigintLatch

__all__ = [
    "REACH_POLL_S",
    "START_TOLERANCE",
    "LostConnectionError",
    "check_controller",
    "check_move_path",
    "connect_arm",
    "controller_codes",
    "move_joints",
    "position_mode",
    "read_joints",
]

START_TOLERANCE = 5e-3
"""[rad] a joint move's goal is reached when every joint is this close (and the controller no
longer reports motion)."""
REACH_POLL_S = 0.01  # [s]

Positions = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""Fingertip kinematics: q (k, 7) [rad] -> positions (k, 3) [m] (base frame), quaternions."""


class LostConnectionError(Exception):
    """The controller did not answer (callers report it as a :class:`HardwareError`)."""


def connect_arm(robot: RobotConfig) -> tuple[Any, JointLimits, JointLimits, dict[str, Any]]:
    """Connect to the controller of ``robot`` and read its limits.

    Returns:
        ``(api, robot_limits, limits, info)``: the SDK object, the robot's own limits, the
        effective ones (stricter of the paper's and the robot's) and where they came from
        (serial, reduced mode, firmware).

    Raises:
        ConfigError: ``robot.port`` is not the SDK's port.
        HardwareError: No controller answers, or it is not an xArm 7.
    """
    api = xarm_sdk.connect(robot)
    robot_limits, info = xarm_sdk.read_robot_limits(api)
    limits = JointLimits.stricter(JointLimits(), robot_limits)
    return api, robot_limits, limits, {**info, "firmware": str(api.version)}


def controller_codes(api: Any) -> tuple[int, int]:
    """The controller's (error, warning) codes, asked now.

    Raises:
        LostConnectionError: The controller did not answer.
    """
    code, codes = api.get_err_warn_code()
    if code in xarm_sdk.CONNECTION_LOST_CODES or not isinstance(codes, (list, tuple)):
        raise LostConnectionError(f"no reply from the controller (SDK code {code})")
    return int(codes[0]), int(codes[1])


def check_controller(api: Any, what: str) -> None:
    """Raise :class:`HardwareError` naming the code if the controller reports an error or a
    warning (``what`` says when, e.g. ``"before the trial"``), or does not answer."""
    try:
        err, warn = controller_codes(api)
    except LostConnectionError as e:
        raise HardwareError(f"{e} {what}") from None
    for kind, c in (("error", err), ("warn", warn)):
        if c:
            info = xarm_sdk.controller_code(kind, c)
            raise HardwareError(
                f"the controller reports {info['label']} {info['title']} {what}; check the "
                "robot, then clear it (XArmCell.recover())"
            )


def read_joints(api: Any) -> np.ndarray:
    """The measured joints now (7,) [rad] (``get_servo_angle``)."""
    code, q = api.get_servo_angle(is_radian=True)
    if code != 0:
        raise HardwareError(f"cannot read the joints: SDK code {code}")
    return np.asarray(q, dtype=float)[:7]


def check_move_path(
    q_now: np.ndarray,
    q_goal: np.ndarray,
    fk: Positions,
    limits: JointLimits,
    safety: SafetyConfig,
    *,
    what_now: str = "the robot's current pose",
    what: str = "the move to the start pose",
) -> None:
    """Refuse (:class:`~flyknot_hw.preflight.PreflightError`) a move from ``q_now`` whose start
    breaks the position limits (with the margin) or whose straight joint-space path to
    ``q_goal`` takes the fingertip out of the workspace box (51 samples)."""
    check_pose(q_now, limits, safety.margins, what=what_now)
    path = q_now + np.linspace(0.0, 1.0, 51)[:, None] * (q_goal - q_now)[None, :]
    tip, _ = fk(path)
    ws = safety.workspace
    bad = np.argwhere((tip < ws.lo) | (tip > ws.hi))
    if bad.size:
        k, a = (int(x) for x in bad[0])
        limit = ws.lo[a] if tip[k, a] < ws.lo[a] else ws.hi[a]
        raise PreflightError(
            "workspace", float(tip[k, a]), float(limit), float(limit), axis="xyz"[a], what=what
        )


def position_mode(api: Any) -> None:
    """Enable the motors, position mode (mode 0), ready (state 0); raise if it stays stopped."""
    api.motion_enable(True)
    api.set_mode(0)
    api.set_state(0)
    code, state = api.get_state()
    if code != 0 or state == 4:
        raise HardwareError(f"the controller does not get ready (state {state}, code {code})")


def move_joints(
    api: Any,
    robot: RobotConfig,
    q_goal: np.ndarray,
    q_now: np.ndarray,
    latch: SigintLatch,
    target: str = "the start pose",
) -> None:
    """Move to ``q_goal`` (7,) [rad] in position mode at ``robot.start_speed`` and
    ``robot.start_acc`` and wait until it is reached (module docstring).

    Raises:
        KeyboardInterrupt: Ctrl-C (through ``latch``).
        HardwareError: A controller error or warning (its code and title), a refused move,
            or the goal not reached in time (twice the nominal duration plus 5 s).
    """
    code = api.set_servo_angle(
        angle=np.asarray(q_goal, dtype=float).tolist(), speed=robot.start_speed,
        mvacc=robot.start_acc, is_radian=True, wait=False,
    )  # fmt: skip
    if code != 0:
        check_controller(api, f"during the move to {target}")
        raise HardwareError(f"the move to {target} was refused: SDK code {code}")
    dist = float(np.max(np.abs(q_goal - q_now)))
    timeout = 2.0 * dist / robot.start_speed + robot.start_speed / robot.start_acc + 5.0
    end = time.perf_counter() + timeout
    while True:
        latch.check()
        if api.has_err_warn:
            check_controller(api, f"during the move to {target}")
        q = read_joints(api)
        if np.max(np.abs(q - q_goal)) < START_TOLERANCE and api.get_state()[1] != 1:
            return
        if time.perf_counter() > end:
            raise HardwareError(
                f"{target} was not reached within {timeout:.1f} s (off by "
                f"{np.max(np.abs(q - q_goal)):.4f} rad)"
            )
        time.sleep(REACH_POLL_S)

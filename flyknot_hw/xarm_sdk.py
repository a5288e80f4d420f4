"""The xArm SDK (xarm-python-sdk >= 1.18) as the cell uses it, imported lazily.

Facts relied on (xarm-python-sdk 1.18.4): ``XArmAPI(address, is_radian=True)`` connects to
TCP 502 (``XCONF.SocketConf.TCP_CONTROL_PORT``, not configurable) and to a report port (rich
report 30002 by default); ``forbid_uds=True`` keeps it from using a local Unix socket
``/tmp/xarmcontroller_uds_<port>`` instead of the address. ``api.sn``/``device_type``/``axis``
come from the version string; the SDK's own joint-range table is
``XCONF.Robot.JOINT_LIMITS[axis][type]`` with type 71305 for serials whose digits 2..5 are
in [1305, 8500) (``x3/xarm.py``, ``_is_out_of_joint_range``). Controller error and warning
texts are ``ControllerErrorCodeMap`` / ``ControllerWarnCodeMap`` in
``core/config/x_code.py``; the SDK's return codes are ``x3/code.py: APIState``.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from flyknot.constants import N_JOINTS, QDD_MAX, TAU_MAX
from flyknot.errors import ConfigError, HardwareError
from flyknot.limits import JointLimits
from flyknot_hw.config import RobotConfig
from flyknot_hw.preflight import ROBOT_QD_MAX, published_robot_limits

__all__ = [
    "CONNECTION_LOST_CODES",
    "api_code_name",
    "connect",
    "controller_code",
    "default_timeout",
    "read_robot_limits",
    "sdk_version",
    "stop_arm",
]

CONNECTION_LOST_CODES = (-1, 3, 8)
"""SDK return codes meaning no reply: NOT_CONNECTED, ERR_TOUT (timeout), ERR_NOTTCP (send)."""


SDK_LOG_DIR = os.path.join(os.path.expanduser("~"), ".UFACTORY", "log", "xarm", "sdk")
"""Where the SDK logs (``xarm/core/utils/log.py``). Its import creates the directory after an
``exists`` check, without ``exist_ok``: two processes importing it at once on a machine that
has none (pytest's workers, two commands started together) race, and the loser raises
``FileExistsError``."""


def prepare_sdk_log_dir() -> None:
    """Create the SDK's log directory before the SDK's import does, safely in parallel."""
    os.makedirs(SDK_LOG_DIR, exist_ok=True)


def _sdk():
    prepare_sdk_log_dir()
    try:
        import xarm  # noqa: F401
        from xarm.wrapper import XArmAPI
    except ImportError as e:
        raise HardwareError(
            "the xArm SDK is not installed: pip install 'flyknot[hardware]' "
            "(xarm-python-sdk >= 1.18)"
        ) from e
    return XArmAPI


def sdk_version() -> str:
    """The installed xarm-python-sdk version."""
    _sdk()
    from xarm.version import __version__

    return str(__version__)


def control_port() -> int:
    """The command port the SDK connects to (502 unless a test patched it)."""
    _sdk()
    from xarm.core.config.x_config import XCONF

    return int(XCONF.SocketConf.TCP_CONTROL_PORT)


def default_timeout() -> float:
    """The SDK's default reply timeout [s] (``XCONF.UxbusConf.SET_TIMEOUT``)."""
    from xarm.core.config.x_config import XCONF

    return XCONF.UxbusConf.SET_TIMEOUT / 1000.0


def connect(robot: RobotConfig) -> Any:
    """Connect an ``XArmAPI`` (radians, rich report, no Unix socket) and check it is a 7-axis
    arm.

    Raises:
        ConfigError: If ``robot.port`` is not the port the SDK uses.
        HardwareError: If the controller does not answer or is not an xArm 7.
    """
    XArmAPI = _sdk()
    port = control_port()
    if robot.port != port:
        raise ConfigError(
            "robot.port", f"the xArm SDK connects to port {port} only, got {robot.port}", [port]
        )
    try:
        api = XArmAPI(robot.address, is_radian=True, forbid_uds=True, report_type="rich")
    except Exception as e:  # the SDK raises a bare Exception when the socket fails
        raise HardwareError(f"robot.address: cannot connect to {robot.address}: {e}") from e
    if not api.connected:
        raise HardwareError(f"robot.address: no controller answers at {robot.address}")
    if api.axis != N_JOINTS:
        api.disconnect()
        raise HardwareError(f"the robot at {robot.address} has {api.axis} axes, not 7")
    return api


def controller_code(kind: str, code: int) -> dict[str, Any]:
    """A controller error (``kind="error"``, shown Cxx) or warning (``"warn"``, Wxx) with
    its title and description from the SDK's tables."""
    _sdk()
    from xarm.core.config.x_code import ControllerError, ControllerWarn

    entry = (ControllerError if kind == "error" else ControllerWarn)(code, status=0)
    prefix = "C" if kind == "error" else "W"
    return {
        "kind": kind,
        "code": int(code),
        "label": f"{prefix}{code}",
        "title": entry.title["en"],
        "description": entry.description["en"],
    }


def api_code_name(code: int) -> str:
    """The SDK's name of one of its return codes (``x3/code.py: APIState``)."""
    _sdk()
    from xarm.x3.code import APIState

    names = [k for k, v in vars(APIState).items() if k.isupper() and v == code]
    return names[0] if names else "unknown"


def _serial_type_key(sn: str, device_type: int) -> int:
    if sn[2:6].isdigit() and 1305 <= int(sn[2:6]) < 8500:
        return int(f"{N_JOINTS}1305")
    return int(device_type)


def read_robot_limits(api: Any) -> tuple[JointLimits, dict[str, Any]]:
    """The connected robot's own limits and where they came from.

    Positions: the SDK's table for the robot's serial and type, narrowed to the reduced-mode
    joint ranges when reduced mode is on; speed: pi rad/s (narrowed to the reduced-mode joint
    speed). Acceleration and torque: the robot reports none, so the paper's values stand in
    (they leave :meth:`JointLimits.stricter` unchanged).
    """
    from xarm.core.config.x_config import XCONF

    sn = str(api.sn or "")
    key = _serial_type_key(sn, api.device_type)
    table = XCONF.Robot.JOINT_LIMITS.get(N_JOINTS, {}).get(key)
    info: dict[str, Any] = {"serial": sn, "device_type": int(api.device_type), "type_key": key}
    if table is None:
        base = published_robot_limits(newer_serial=True)
        q_min, q_max = base.q_min.copy(), base.q_max.copy()
        info["ranges"] = "published (type not in the SDK table)"
    else:
        ranges = np.array(table, dtype=float)
        q_min, q_max = ranges[:, 0].copy(), ranges[:, 1].copy()
        info["ranges"] = "sdk table"
    qd = np.full(N_JOINTS, ROBOT_QD_MAX)
    code, st = api.get_reduced_states()
    reduced = bool(code == 0 and st and st[0])
    info["reduced_mode"] = reduced
    if reduced:
        speed = float(st[3])
        if math.isfinite(speed) and speed > 0:
            qd = np.minimum(qd, speed)
        jr = st[4] if len(st) > 4 and isinstance(st[4], (list, tuple)) else []
        if len(jr) == 2 * N_JOINTS:
            lo, hi = np.array(jr[0::2], dtype=float), np.array(jr[1::2], dtype=float)
            use = np.isfinite(lo) & np.isfinite(hi) & (lo < hi)
            q_min = np.where(use, np.maximum(q_min, lo), q_min)
            q_max = np.where(use, np.minimum(q_max, hi), q_max)
        info["reduced_joint_speed"] = speed
    limits = JointLimits(
        q_min=q_min, q_max=q_max, qd_max=qd, qdd_max=QDD_MAX.copy(), tau_max=TAU_MAX.copy()
    )
    return limits, info


def stop_arm(api: Any) -> dict[str, Any]:
    """Stop the arm (``set_state(4)``) and read the state back; never raises."""
    out: dict[str, Any] = {"stop_sent": False, "state": None}
    try:
        code = api.set_state(4)
        out["stop_sent"] = code == 0
        out["stop_code"] = int(code)
        code, state = api.get_state()
        if code == 0:
            out["state"] = int(state)
    except Exception as e:  # a dead connection must not hide the original problem
        out["stop_error"] = repr(e)
    return out

"""The lab file: one TOML file describing the real lab, parsed into frozen dataclasses.

Every field is validated when the file is read; an error names the field as it is written in
the file (``robot.address: ...``) and, where there is a finite set, lists the valid choices.
Unknown keys are errors too (a misspelt key must not silently fall back to a default).
``assets/lab_example.toml`` documents every field. Sections::

    [robot]     the xArm controller: address, ports, servo rate, start move, joint source
    [mocap]     the motion-capture system: live or file, system, address, file, marker set
    [rope]      the rope in use: id (the paper's 1..7) or name, optional ropes file
    [base]      the robot base in the mocap frame: pose = [x, y, z, qw, qx, qy, qz]
    [safety]    margins on the joint limits, fingertip workspace box (base frame)
    [settle]    how the lab waits for the rope to hang still: seconds, markers or operator
    [calibration] the driven base-pose calibration: start pose, averaging, outlier rule
"""

from __future__ import annotations

import ipaddress
import math
import numbers
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import COMMAND_RATE_HZ
from flyknot.errors import ConfigError, check_choice, check_nonnegative, check_positive
from flyknot.geometry import readonly
from flyknot.limits import JointLimits

__all__ = [
    "JOINT_SOURCES",
    "MOCAP_KINDS",
    "SETTLE_MODES",
    "UFACTORY_HOME",
    "CalibrationConfig",
    "LabConfig",
    "Margins",
    "MocapConfig",
    "RobotConfig",
    "RopeConfig",
    "SafetyConfig",
    "SettleConfig",
    "Workspace",
    "load_lab_config",
    "parse_lab_config",
]

JOINT_SOURCES = ("auto", "report", "poll")
STREAM_MODES = ("servo", "velocity")
"""How a command is streamed: ``servo`` = ``set_servo_angle_j`` in mode 1 (the controller
faults with C60 when its TCP moves faster than 1.2 m/s); ``velocity`` = joint velocities with
``vc_set_joint_velocity`` in mode 4 (C60 is a servo_j code; unverified on a real arm)."""
"""Where measured joints come from: the controller's 30000 report stream (``report``), one
``get_servo_angle`` request per tick (``poll``), or the report when it connects (``auto``)."""
VELOCITY_GAIN_MAX = 50.0
"""Largest position gain of the velocity stream [1/s]: with ~10 ms from a measured joint to
the velocity it corrects (200 Hz report, one 4 ms tick, the network), gain x delay = 0.5 rad
keeps the loop well damped."""
MOCAP_KINDS = ("live", "file")
SETTLE_MODES = ("seconds", "markers", "operator")
MARGIN_QUANTITIES = ("position", "velocity", "acceleration", "torque")
UFACTORY_HOME = readonly([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
"""The xArm 7's home pose (UFACTORY's) [rad]: the default ``calibration.start``, and the start
of the simulated lab's commands."""


def _number(field_name: str, value: object) -> float:
    real = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
    if not real or not math.isfinite(value):  # type: ignore[arg-type]
        raise ConfigError(field_name, f"must be a finite number, got {value!r}")
    return float(value)


def _port(field_name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        raise ConfigError(field_name, f"must be a TCP port, an integer in 1..65535, got {value!r}")
    return value


def _text(field_name: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(field_name, f"must be a non-empty string, got {value!r}")
    return value


def _vector(field_name: str, value: object, n: int) -> np.ndarray:
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != n:
        raise ConfigError(field_name, f"must be a list of {n} numbers, got {value!r}")
    return readonly([_number(f"{field_name}[{i}]", v) for i, v in enumerate(value)])


@dataclass(frozen=True)
class RobotConfig:
    """The xArm 7 controller.

    Attributes:
        address: The controller's IPv4 address (the SDK opens a serial port for anything
            that is not a dotted IPv4 address or ``localhost``).
        port: Command port; the SDK always uses 502 (``XCONF.SocketConf.TCP_CONTROL_PORT``).
        report_port: Real-time report port (firmware >= 2.1: 200 Hz, timestamped joints).
        servo_rate_hz: Rate of the ``set_servo_angle_j`` stream [Hz]; commands must match.
        start_speed: Joint speed of the slow move to a command's start pose [rad/s].
        start_acc: Joint acceleration of that move [rad/s^2].
        joint_source: Measured joints from the report stream, by polling, or ``auto``
            (:data:`JOINT_SOURCES`).
        reply_timeout_s: Longest wait for the controller's reply to one streamed target [s].
        max_late_s: Abort a stream whose tick is sent later than this after its deadline [s].
        stream: :data:`STREAM_MODES`: ``servo`` (default, the SDK's documented path) or
            ``velocity`` (for throws faster than servo mode's 1.2 m/s TCP limit).
        velocity_gain: In ``velocity`` mode, the joint velocity sent at tick i is the
            command's forward difference (q[i+1] - q[i]) / dt plus this gain times the
            position error q[i] - q_measured [1/s]; 0 = feed-forward only. At most
            :data:`VELOCITY_GAIN_MAX`.
    """

    address: str
    port: int = 502
    report_port: int = 30000
    servo_rate_hz: float = COMMAND_RATE_HZ
    start_speed: float = 0.35
    start_acc: float = 1.0
    joint_source: str = "auto"
    reply_timeout_s: float = 0.2
    max_late_s: float = 0.02
    stream: str = "servo"
    velocity_gain: float = 10.0

    def __post_init__(self) -> None:
        address = _text("robot.address", self.address)
        if address != "localhost":
            try:
                ipaddress.IPv4Address(address)
            except ValueError:
                raise ConfigError(
                    "robot.address",
                    "must be a dotted IPv4 address such as 192.168.1.185 (the SDK opens a "
                    f"serial port for anything else), got {address!r}",
                ) from None
        _port("robot.port", self.port)
        _port("robot.report_port", self.report_port)
        if self.report_port == self.port:
            raise ConfigError("robot.report_port", f"must differ from robot.port ({self.port})")
        check_positive("robot.servo_rate_hz", self.servo_rate_hz)
        check_positive("robot.start_speed", self.start_speed)
        if self.start_speed > 1.0:
            raise ConfigError(
                "robot.start_speed",
                f"must be at most 1.0 rad/s (a slow move), got {self.start_speed}",
            )
        check_positive("robot.start_acc", self.start_acc)
        if self.start_acc > 20.0:
            raise ConfigError(
                "robot.start_acc",
                f"must be at most 20 rad/s^2 (the SDK's cap), got {self.start_acc}",
            )
        check_choice("robot.joint_source", self.joint_source, JOINT_SOURCES)
        check_positive("robot.reply_timeout_s", self.reply_timeout_s)
        check_positive("robot.max_late_s", self.max_late_s)
        check_choice("robot.stream", self.stream, STREAM_MODES)
        check_nonnegative("robot.velocity_gain", self.velocity_gain)
        if self.velocity_gain > VELOCITY_GAIN_MAX:
            raise ConfigError(
                "robot.velocity_gain",
                f"must be at most {VELOCITY_GAIN_MAX:g} 1/s (the loop closes over the "
                f"report's ~5 ms delay), got {self.velocity_gain}",
            )


@dataclass(frozen=True)
class MocapConfig:
    """The motion-capture system (read by ``flyknot_hw.mocap``).

    Attributes:
        kind: ``live`` (stream from the system) or ``file`` (read the lab software's files).
        system: Name of the system or its software (e.g. ``vicon``, ``optitrack``, ``c3d``).
        address: Host (and port) of a live system, ``"host"`` or ``"host:port"``; None for
            files.
        file: A file path or glob pattern (e.g. ``captures/trial_*.c3d``) for ``file``;
            None for live.
        marker_set: Name of the rope's marker set (subject) in the mocap software.
    """

    kind: str = "live"
    system: str = "vicon"
    address: str | None = None
    file: str | None = None
    marker_set: str = "rope"

    def __post_init__(self) -> None:
        check_choice("mocap.kind", self.kind, MOCAP_KINDS)
        _text("mocap.system", self.system)
        _text("mocap.marker_set", self.marker_set)
        if self.address is not None:
            _text("mocap.address", self.address)
        if self.file is not None:
            _text("mocap.file", self.file)
        if self.kind == "live" and self.address is None:
            raise ConfigError("mocap.address", 'is required when mocap.kind = "live"')
        if self.kind == "file" and self.file is None:
            raise ConfigError("mocap.file", 'is required when mocap.kind = "file"')


@dataclass(frozen=True)
class RopeConfig:
    """The rope in use: exactly one of ``id`` and ``name``.

    Attributes:
        id: The paper's rope id (1..7), or None.
        name: A rope's name (the paper's or one of ``ropes``), or None.
        ropes: A user's ropes file (``assets/ropes_example.toml`` format), or None.
    """

    id: int | None = None
    name: str | None = None
    ropes: str | None = None

    def __post_init__(self) -> None:
        if (self.id is None) == (self.name is None):
            raise ConfigError("rope", "give exactly one of rope.id and rope.name")
        if self.id is not None and (
            isinstance(self.id, bool) or not isinstance(self.id, int) or not 1 <= self.id <= 7
        ):
            raise ConfigError(
                "rope.id", f"must be the paper's rope id, got {self.id!r}", range(1, 8)
            )
        if self.name is not None:
            _text("rope.name", self.name)
        if self.ropes is not None:
            _text("rope.ropes", self.ropes)

    @property
    def key(self) -> int | str:
        """The rope as a scenario names it: its id or its name."""
        return self.id if self.id is not None else str(self.name)


@dataclass(frozen=True)
class Margins:
    """Safety margins: a command may use at most ``1 - margin`` of each limit.

    Velocity, acceleration and torque: ``|x| <= (1 - m) x_max``. Position: the distance from
    the middle of the joint's range is at most ``(1 - m)`` of the half-range, i.e. the range
    shrinks by ``m / 2`` of its width at each end.

    Attributes:
        position: Fraction in [0, 1) [-].
        velocity: Fraction in [0, 1) [-].
        acceleration: Fraction in [0, 1) [-].
        torque: Fraction in [0, 1) [-].
    """

    position: float = 0.05
    velocity: float = 0.05
    acceleration: float = 0.05
    torque: float = 0.05

    def __post_init__(self) -> None:
        for name in MARGIN_QUANTITIES:
            v = _number(f"safety.margin.{name}", getattr(self, name))
            if not 0.0 <= v < 1.0:
                raise ConfigError(f"safety.margin.{name}", f"must lie in [0, 1), got {v!r}")
            object.__setattr__(self, name, v)

    def allowed(self, quantity: str) -> float:
        """The largest allowed use of ``quantity``'s limit, ``1 - margin`` [-]."""
        check_choice("quantity", quantity, MARGIN_QUANTITIES)
        return 1.0 - getattr(self, quantity)

    def apply(self, limits: JointLimits) -> JointLimits:
        """``limits`` less these margins: what a command may use
        (:meth:`flyknot.limits.JointLimits.with_margins`)."""
        return limits.with_margins(self.position, self.velocity, self.acceleration, self.torque)


@dataclass(frozen=True, eq=False)
class Workspace:
    """An axis-aligned box the fingertip must stay in, in the robot base frame.

    Attributes:
        lo: Lower corner (x, y, z), shape (3,) [m].
        hi: Upper corner, shape (3,) [m]; hi > lo on every axis.
    """

    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self) -> None:
        lo = _vector("safety.workspace.min", self.lo, 3)
        hi = _vector("safety.workspace.max", self.hi, 3)
        bad = np.flatnonzero(hi <= lo)
        if bad.size:
            k = int(bad[0])
            raise ConfigError(
                "safety.workspace.max",
                f"must exceed safety.workspace.min on every axis; {'xyz'[k]} has "
                f"{float(hi[k])!r} <= {float(lo[k])!r}",
            )
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Workspace):
            return NotImplemented
        return bool(np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class SafetyConfig:
    """Margins on the joint limits and the fingertip's workspace.

    Attributes:
        margins: Fractions of each limit kept in reserve.
        workspace: The fingertip's box in the base frame [m].
        tip_speed_max: Largest fingertip speed [m/s]: the controller faults with C60 when
            its TCP moves faster than 1.2 m/s in servo mode (UFACTORY's error-code table);
            with the TCP set at the fingertip that is this speed.
    """

    margins: Margins
    workspace: Workspace
    tip_speed_max: float = 1.2

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "tip_speed_max", _number("safety.tip_speed_max", self.tip_speed_max)
        )
        if self.tip_speed_max <= 0:
            raise ConfigError("safety.tip_speed_max", f"must be > 0, got {self.tip_speed_max!r}")


@dataclass(frozen=True)
class SettleConfig:
    """How the lab waits for the rope to hang still, before a throw and before the verdict.

    Attributes:
        mode: ``seconds`` (fixed waits), ``markers`` (the motion capture's rest check, given
            by the application) or ``operator`` (a person confirms).
        before_s: Wait before a throw in ``seconds`` mode [s].
        after_s: Wait after the command before the knot is judged [s] (in every mode the
            lab records at least this long after the command).
        timeout_s: Longest wait for the rope in ``markers`` mode [s].
    """

    mode: str = "seconds"
    before_s: float = 5.0
    after_s: float = 1.5
    timeout_s: float = 60.0

    def __post_init__(self) -> None:
        check_choice("settle.mode", self.mode, SETTLE_MODES)
        check_nonnegative("settle.before_s", self.before_s)
        check_nonnegative("settle.after_s", self.after_s)
        check_positive("settle.timeout_s", self.timeout_s)


@dataclass(frozen=True, eq=False)
class CalibrationConfig:
    """The driven calibration of the base pose (``flyknot calibrate``,
    :mod:`flyknot_hw.calibrate_driver`).

    Attributes:
        start: The pose the default calibration poses are derived from, shape (7,) [rad]
            (default :data:`UFACTORY_HOME`).
        window_s: Averaging window at each pose [s]: the measured joints and the fingertip
            marker cluster (frames without it dropped).
        still_s: The arm counts as still when no joint moved more than ``still_rad`` over
            this long [s] (the wait before the window).
        still_rad: See ``still_s`` [rad]; also the largest joint motion allowed within the
            window.
        min_poses: Fewest poses whose fingertip the motion capture saw for a fit (>= 4).
        outlier_mm: A pose is an outlier, and the fit refused, when its fingertip is further
            than this from the fit of the other poses (and 4 times their median) [mm].
    """

    start: np.ndarray = field(default_factory=lambda: UFACTORY_HOME.copy())
    window_s: float = 0.5
    still_s: float = 0.3
    still_rad: float = 5e-4
    min_poses: int = 6
    outlier_mm: float = 5.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vector("calibration.start", self.start, 7))
        for name in ("window_s", "still_s", "still_rad", "outlier_mm"):
            value = _number(f"calibration.{name}", getattr(self, name))
            check_positive(f"calibration.{name}", value)
            object.__setattr__(self, name, value)
        n = self.min_poses
        if isinstance(n, bool) or not isinstance(n, int) or n < 4:
            raise ConfigError(
                "calibration.min_poses",
                f"must be an integer >= 4 (6 parameters, and one pose to spare to find an "
                f"outlier), got {n!r}",
            )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CalibrationConfig):
            return NotImplemented
        return bool(np.array_equal(self.start, other.start)) and all(
            getattr(self, k) == getattr(other, k) for k in CALIBRATION_KEYS if k != "start"
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class LabConfig:
    """The whole lab file.

    Attributes:
        robot: The xArm controller.
        mocap: The motion-capture system.
        rope: The rope in use.
        base_pose: Robot base in the mocap frame, (x, y, z, qw, qx, qy, qz), shape (7,)
            [m, -]; the quaternion is normalised here.
        safety: Margins and workspace.
        settle: The rope-settling wait.
        source: The file it was read from ("" when parsed from a mapping).
        calibration: The driven base-pose calibration's settings.
    """

    robot: RobotConfig
    mocap: MocapConfig
    rope: RopeConfig
    base_pose: np.ndarray
    safety: SafetyConfig
    settle: SettleConfig = field(default_factory=SettleConfig)
    source: str = ""
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def __post_init__(self) -> None:
        pose = _vector("base.pose", self.base_pose, 7)
        norm = float(np.linalg.norm(pose[3:]))
        if abs(norm - 1.0) > 1e-3:
            raise ConfigError(
                "base.pose",
                f"quaternion (qw, qx, qy, qz) must have norm 1 (within 1e-3), got {norm:.6g}",
            )
        pose = np.concatenate([pose[:3], pose[3:] / norm])
        object.__setattr__(self, "base_pose", readonly(pose))


# --- parsing -------------------------------------------------------------------------------
_SECTIONS = ("robot", "mocap", "rope", "base", "safety", "settle", "calibration")
SETTLE_KEYS = ("mode", "before_s", "after_s", "timeout_s")
CALIBRATION_KEYS = ("start", "window_s", "still_s", "still_rad", "min_poses", "outlier_mm")


def _table(
    doc: Mapping[str, Any], key: str, allowed: tuple[str, ...], required: bool = True, at: str = ""
) -> dict[str, Any]:
    name = f"{at}{key}"
    if key not in doc:
        if required:
            raise ConfigError(name, "section is missing")
        return {}
    table = doc[key]
    if not isinstance(table, Mapping):
        raise ConfigError(name, f"must be a table, got {table!r}")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(f"{name}.{unknown[0]}", "unknown key", allowed)
    return dict(table)


def _robot(doc: Mapping[str, Any]) -> RobotConfig:
    keys = tuple(f for f in RobotConfig.__dataclass_fields__)
    table = _table(doc, "robot", keys)
    if "address" not in table:
        raise ConfigError("robot.address", "is required")
    return RobotConfig(**table)


def _mocap(doc: Mapping[str, Any]) -> MocapConfig:
    return MocapConfig(**_table(doc, "mocap", tuple(MocapConfig.__dataclass_fields__)))


def _rope(doc: Mapping[str, Any]) -> RopeConfig:
    return RopeConfig(**_table(doc, "rope", ("id", "name", "ropes")))


def _safety(doc: Mapping[str, Any]) -> SafetyConfig:
    table = _table(doc, "safety", ("margin", "workspace", "tip_speed_max"))
    margin = table.get("margin", 0.05)
    if isinstance(margin, Mapping):
        unknown = sorted(set(margin) - set(MARGIN_QUANTITIES))
        if unknown:
            raise ConfigError(f"safety.margin.{unknown[0]}", "unknown key", MARGIN_QUANTITIES)
        margins = Margins(**margin)
    else:
        m = _number("safety.margin", margin)
        margins = Margins(m, m, m, m)
    ws = _table(table, "workspace", ("min", "max"), at="safety.")
    for k in ("min", "max"):
        if k not in ws:
            raise ConfigError(f"safety.workspace.{k}", "is required")
    return SafetyConfig(margins, Workspace(ws["min"], ws["max"]), table.get("tip_speed_max", 1.2))


def parse_lab_config(doc: Mapping[str, Any], source: str = "") -> LabConfig:
    """Validate a parsed lab file (a mapping as :mod:`tomllib` returns it).

    Raises:
        ConfigError: Naming the first bad field, e.g. ``robot.address: ...``.
    """
    unknown = sorted(set(doc) - set(_SECTIONS))
    if unknown:
        raise ConfigError(unknown[0], "unknown section", _SECTIONS)
    base = _table(doc, "base", ("pose",))
    if "pose" not in base:
        raise ConfigError("base.pose", "is required: [x, y, z, qw, qx, qy, qz]")
    return LabConfig(
        robot=_robot(doc),
        mocap=_mocap(doc),
        rope=_rope(doc),
        base_pose=base["pose"],
        safety=_safety(doc),
        settle=SettleConfig(**_table(doc, "settle", SETTLE_KEYS, required=False)),
        source=source,
        calibration=CalibrationConfig(
            **_table(doc, "calibration", CALIBRATION_KEYS, required=False)
        ),
    )


def load_lab_config(path: str | Path) -> LabConfig:
    """Read and validate a lab file (``assets/lab_example.toml`` documents the format).

    Raises:
        ConfigError: If the file is missing, not TOML, or a field is invalid.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("lab file", f"{str(path)!r} does not exist")
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(path), f"not valid TOML: {e}") from None
    return parse_lab_config(doc, source=str(path))

"""A fake xArm 7 controller on loopback, spoken to by the real, unmodified xarm-python-sdk.

Wire protocol (read from xarm-python-sdk 1.18.4, ``core/comm/base.py``,
``core/wrapper/uxbus_cmd_tcp.py``, ``core/wrapper/uxbus_cmd.py``, ``x3/base.py``):

* Port 502, request: ``trans_id u16 | prot_id u16 | length u16 | register u8 | payload``
  (big-endian header, ``length = 1 + len(payload)``; prot_id 2, the SDK switches to 3 for
  firmware >= 1.8.6). Reply: ``trans_id | prot_id | length | register | state u8 | data`` with
  ``length = 2 + len(data)``; state bits 0x40 error, 0x20 warning, 0x10 not ready to move,
  0x08 invalid. Floats are little-endian fp32, integers big-endian.
* Reports: a big-endian u32 frame size, then the frame. 30001 (normal, 145 bytes), 30002
  (rich, 587; the SDK's default), 30003 (real, 135) are opened by ``XArmAPI``; 30000 (804 bytes,
  timestamp u64 [us], targets and actual joints, firmware >= 2.1) is opened by the cell. The
  byte offsets below follow UFACTORY's published tables (ufactory_docs
  ``firmware/report/ReadMe_en.md`` for 30000) and the SDK's own parser for 30001-30003,
  written here with ``struct`` independently of the SDK's ctypes structures.

Registers served: 1 version, 2 serial, 11 motion enable, 12/13 set/get state, 14 cmdnum,
15 error/warn, 16/17 clean error/warn, 19 set mode, 23 joint move (position mode), 29 servo_j,
41 TCP pose, 42 joint positions (and states), 53 reduced-mode states, 81 joint velocity (mode 4:
integrated into the target, for its duration). Anything else is answered
"invalid" and logged in :attr:`FakeXArm.unknown`.

The arm: ``arm="mujoco"`` (default) is the simulated lab's xArm 7 (``flyknot_sim.robot``:
our MJCF, its joint position servos, 1 ms steps, advanced to wall-clock time whenever the fake
is asked anything); ``arm="exact"`` puts the joints exactly at the latest target; or an object
with the same interface as ``_Arm`` (``q``, ``qd``, ``tau``, ``advance``, ``tcp_pose``,
``stamp``), e.g. the whole simulated lab of ``fake_lab.py``.

Firmware behaviour modelled: the joint ranges of ``xarm.core.config.x_config.XCONF`` for the
fake's serial (C23 when a target leaves them), a joint speed limit of pi rad/s on the implied
speed of consecutive servo targets at the nominal 4 ms (C24), injectable errors/warnings at the
k-th servo target (e.g. C31 collision), a dropped connection (closed or silent), and, when
``servo_tcp_speed_max`` is given, C60 for servo targets whose implied flange speed exceeds it
(the firmware's 1.2 m/s; off by default); velocities above pi rad/s give C24. An error
stops the arm (state 4, targets ignored) until ``clean_error`` + ``motion_enable`` +
``set_state(0)``; ``set_mode`` takes effect at the next ``set_state(0)``.

Ports: the SDK hard-codes 502 and 30001-30003 (``XCONF.SocketConf``) and takes only an address.
Every fake binds the real port numbers on its own random loopback alias 127.a.b.c (Linux routes
all of 127/8 to loopback), so fakes never collide and the SDK needs no change. Port 502 is
privileged: without root (or CAP_NET_BIND_SERVICE) the fake takes an ephemeral port for it and
:meth:`FakeXArm.sdk_port_overrides` names the one constant a test then patches,
``XCONF.SocketConf.TCP_CONTROL_PORT`` (the report ports cannot be patched: the SDK also picks
its report parser by their numbers). Set FLYKNOT_FAKE_XARM_EPHEMERAL=1 to force that path.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import socket
import struct
import threading
import time
from dataclasses import dataclass

import mujoco
import numpy as np

from flyknot_sim.robot import FINGERTIP_BODY, actuator_ids, load_robot_model

HOME = np.array([0.0, -0.247, 0.0, 0.909, 0.0, 1.15644, 0.0])
SDK_PORT_NAMES = {
    502: "TCP_CONTROL_PORT",
    30000: "TCP_REPORT_RT_PORT",
    30001: "TCP_REPORT_NORM_PORT",
    30002: "TCP_REPORT_RICH_PORT",
    30003: "TCP_REPORT_REAL_PORT",
}
REPORT_HZ = {30000: 200.0, 30001: 5.0, 30002: 5.0, 30003: 100.0}
FRAME_SIZE = {30000: 804, 30001: 145, 30002: 587, 30003: 135}
SERVO_PERIOD = 0.004  # [s] the firmware's nominal servo_j period
QD_MAX_FW = math.pi  # [rad/s]
FORCE_EPHEMERAL_ENV = "FLYKNOT_FAKE_XARM_EPHEMERAL"


def firmware_ranges(serial: str, device_type: int = 7) -> np.ndarray:
    """Joint ranges (7, 2) [rad] the SDK's table gives this serial (same rule as the SDK)."""
    from xarm.core.config.x_config import XCONF

    key = device_type
    if serial[2:6].isdigit() and 1305 <= int(serial[2:6]) < 8500:
        key = 71305
    return np.array(XCONF.Robot.JOINT_LIMITS[7][key], dtype=float)


@dataclass
class ServoEntry:
    """One servo_j request as the fake received it."""

    t: float  # perf_counter at receipt [s]
    q: np.ndarray  # target (7,) [rad], fp32 precision
    mode: int
    state: int
    applied: bool


class _Arm:
    """The seven joints: MuJoCo servos or exact tracking, advanced to wall-clock time."""

    def __init__(self, kind: str, q0: np.ndarray):
        if kind not in ("mujoco", "exact"):
            raise ValueError(f"arm must be 'mujoco' or 'exact', got {kind!r}")
        self.kind = kind
        self.model = load_robot_model()
        self.model.opt.timestep = 0.001
        self.data = mujoco.MjData(self.model)
        self.act = actuator_ids(self.model)
        self.data.qpos[:] = q0
        self.data.ctrl[self.act] = q0
        mujoco.mj_forward(self.model, self.data)
        self.body = self.model.body(FINGERTIP_BODY).id
        self.t = time.perf_counter()
        self.qd = np.zeros(7)

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[:7].copy()

    @property
    def tau(self) -> np.ndarray:
        return self.data.actuator_force[self.act].copy()

    def stamp(self, now: float) -> float:
        """Time of the state the properties report, on ``perf_counter`` [s]: now (the arm
        was advanced to it)."""
        return now

    def advance(self, now: float, ctrl_at) -> None:
        """Step to ``now``; ``ctrl_at(t)`` is the joint target at time t."""
        dt = self.model.opt.timestep
        if now - self.t > 0.5:  # idle for long: jump (the arm holds its target anyway)
            self.t = now - 0.5
        if self.kind == "exact":
            if now > self.t:
                q_new = ctrl_at(now)
                self.qd = (q_new - self.data.qpos[:7]) / max(now - self.t, 1e-6)
                self.data.qpos[:7] = q_new
                self.t = now
            return
        while self.t + dt <= now:
            self.t += dt
            self.data.ctrl[self.act] = ctrl_at(self.t)
            mujoco.mj_step(self.model, self.data)
        self.qd = self.data.qvel[:7].copy()

    def flange(self, q: np.ndarray) -> np.ndarray:
        """Flange position [m] at joints ``q`` (forward kinematics only; the state is kept)."""
        keep = self.data.qpos[:7].copy()
        self.data.qpos[:7] = q
        mujoco.mj_kinematics(self.model, self.data)
        p = self.data.xpos[self.body].copy()
        self.data.qpos[:7] = keep
        return p

    def tcp_pose(self) -> np.ndarray:
        """Flange pose (x, y, z [mm], roll, pitch, yaw [rad])."""
        mujoco.mj_kinematics(self.model, self.data)
        p = self.data.xpos[self.body] * 1000.0
        r = self.data.xmat[self.body].reshape(3, 3)
        rpy = [math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1, min(1, r[2, 0]))),
               math.atan2(r[1, 0], r[0, 0])]  # fmt: skip
        return np.concatenate([p, rpy])


class FakeXArm:
    """A fake controller; start with :meth:`start` (or ``with``), stop with :meth:`stop`.

    Args:
        arm: ``"mujoco"`` (default), ``"exact"`` or an arm object (module docstring).
        serial: Robot serial; its digits 2..5 >= 1305 select the newer joint ranges.
        version: Firmware version string (>= 2.1 serves the 30000 report).
        q0: Initial joints (7,) [rad].
        initial_error: Controller error present at start-up (state 4), or 0.
        report_hz: Report rates per port [Hz] (defaults: the real controller's).
        rt_epoch_s: Offset of the 30000 timestamps from this process's perf_counter [s].
        reduced: Reduced mode as (joint speed [rad/s], ranges (7, 2) [rad]), or None (off).
    """

    def __init__(
        self,
        *,
        arm: str | object = "mujoco",
        serial: str = "XI1305FAKE0001",
        version: str = "2.5.0",
        q0: np.ndarray = HOME,
        initial_error: int = 0,
        report_hz: dict[int, float] | None = None,
        rt_epoch_s: float = 1234.5,
        reduced: tuple[float, np.ndarray] | None = None,
        servo_tcp_speed_max: float | None = None,
    ):
        self.serial, self.version = serial, version
        self.ranges = firmware_ranges(serial)
        self.arm = _Arm(arm, np.asarray(q0, dtype=float)) if isinstance(arm, str) else arm
        self.report_hz = {**REPORT_HZ, **(report_hz or {})}
        self.rt_epoch_s = rt_epoch_s
        self.reduced = reduced
        self._tcp_max = servo_tcp_speed_max
        self._fk = _Arm("exact", self.arm.q) if servo_tcp_speed_max is not None else None
        self._vel: tuple[float, np.ndarray, np.ndarray, float] | None = None
        self._lock = threading.RLock()
        self.enabled = True
        self.state = 4 if initial_error else 2
        self.mode = self.pending_mode = 0
        self.error_code, self.warn_code = initial_error, 0
        self._target = self.arm.q  # servo target / plan goal [rad]
        self._plan: tuple[float, np.ndarray, np.ndarray, float] | None = None
        self._last_servo: np.ndarray | None = None
        self._last_servo_t = -1.0
        # logs
        self.requests: list[tuple[float, int, bytes]] = []
        self.servo: list[ServoEntry] = []
        self.events: list[tuple[float, str, object]] = []
        self.unknown: list[int] = []
        # scripted trouble
        self._inject: dict[int, tuple[str, int]] = {}
        self._drop: tuple[int, str] | None = None
        self._silent = False
        # sockets
        self.host = ""
        self.ports: dict[int, int] = {}
        self._servers: list[socket.socket] = []
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._running = False

    # --- life cycle ------------------------------------------------------------------------
    def start(self) -> FakeXArm:
        """Bind the five ports on a fresh loopback alias and start serving."""
        ephemeral_502 = os.environ.get(FORCE_EPHEMERAL_ENV, "") != ""
        rng = random.Random()
        for _ in range(50):
            host = f"127.{rng.randint(1, 254)}.{rng.randint(0, 254)}.{rng.randint(1, 254)}"
            ports = {p: p for p in SDK_PORT_NAMES}
            if ephemeral_502:
                ports[502] = 0
            try:
                self._bind(host, ports)
                break
            except PermissionError:  # port 502 is privileged: take any port for it
                ephemeral_502 = True
            except OSError:
                continue
        else:
            raise OSError("no free loopback alias for the fake xArm")
        self._running = True
        for sdk_port, srv in zip(SDK_PORT_NAMES, self._servers, strict=True):
            th = threading.Thread(target=self._accept, args=(sdk_port, srv), daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def _bind(self, host: str, ports: dict[int, int]) -> None:
        servers = []
        try:
            for sdk_port, port in ports.items():
                srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                srv.bind((host, port))
                srv.listen(4)
                srv.settimeout(0.1)
                servers.append(srv)
                self.ports[sdk_port] = srv.getsockname()[1]
        except OSError:
            for s in servers:
                s.close()
            self.ports.clear()
            raise
        self.host, self._servers = host, servers

    def stop(self) -> None:
        """Close every socket and join the threads."""
        self._running = False
        for s in self._servers + self._conns:
            _close(s)
        for th in self._threads:
            th.join(timeout=2.0)

    def __enter__(self) -> FakeXArm:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def uses_sdk_ports(self) -> bool:
        """True when the fake listens on the SDK's own port numbers (no patch needed)."""
        return all(self.ports[p] == p for p in SDK_PORT_NAMES)

    def sdk_port_overrides(self) -> dict[str, int]:
        """``XCONF.SocketConf`` attribute -> port, for a test to patch when 502 was not
        available (only the command port: the SDK also uses the report port numbers to pick
        its report parser, so those are always the real ones)."""
        return {} if self.ports[502] == 502 else {"TCP_CONTROL_PORT": self.ports[502]}

    # --- scripted trouble ------------------------------------------------------------------
    def inject(self, code: int, after_servo: int, *, warn: bool = False) -> None:
        """Raise controller error (or warning) ``code`` at the ``after_servo``-th servo_j."""
        self._inject[after_servo] = ("warn" if warn else "error", code)

    def drop(self, after_servo: int, how: str = "close") -> None:
        """At that servo_j: close all connections (``close``) or stop answering (``silent``)."""
        if how not in ("close", "silent"):
            raise ValueError(how)
        self._drop = (after_servo, how)

    # --- observations ----------------------------------------------------------------------
    @property
    def q(self) -> np.ndarray:
        """Actual joints now (7,) [rad]."""
        with self._lock:
            self._advance()
            return self.arm.q

    def registers(self) -> list[int]:
        """Registers of every request received, in order."""
        return [r for _, r, _ in self.requests]

    def servo_targets(self, applied_only: bool = True) -> np.ndarray:
        """Servo targets received, (k, 7) [rad]."""
        rows = [e.q for e in self.servo if e.applied or not applied_only]
        return np.array(rows).reshape(-1, 7)

    def wait_for(self, predicate, timeout: float = 5.0) -> bool:
        """Poll ``predicate()`` every ms until true or ``timeout`` [s]."""
        end = time.perf_counter() + timeout
        while time.perf_counter() < end:
            if predicate():
                return True
            time.sleep(0.001)
        return bool(predicate())

    # --- the arm ---------------------------------------------------------------------------
    def _ctrl_at(self, t: float) -> np.ndarray:
        if self._vel is not None:
            t0, q0, v, dur = self._vel
            return q0 + v * min(max(t - t0, 0.0), dur if dur > 0 else math.inf)
        if self._plan is None:
            return self._target
        t0, qa, qb, dur = self._plan
        s = min(max((t - t0) / dur, 0.0), 1.0)
        s = s**3 * (10 - 15 * s + 6 * s * s)  # quintic, zero speed at both ends
        return qa + (qb - qa) * s

    def _advance(self) -> None:
        now = time.perf_counter()
        self.arm.advance(now, self._ctrl_at)
        if self.state in (1, 2) and self.error_code == 0:
            busy = self._plan is not None and now < self._plan[0] + self._plan[3]
            busy = busy or (self.mode == 1 and now - self._last_servo_t < 0.05)
            busy = busy or (self._vel is not None and now - self._vel[0] < self._vel[3])
            self.state = 1 if busy or np.max(np.abs(self.arm.qd)) > 1e-2 else 2
            if not busy and self._plan is not None:
                self._target, self._plan = self._plan[2], None
        q = self.arm.q
        lo, hi = self.ranges[:, 0] - 1e-3, self.ranges[:, 1] + 1e-3
        if self.error_code == 0 and np.any((q < lo) | (q > hi)):
            self._fault(23)

    def _fault(self, code: int) -> None:
        self.error_code = code
        self.state = 4
        self._plan = self._vel = None
        self._target = self.arm.q
        self.events.append((time.perf_counter(), "error", code))

    def _ready(self) -> bool:
        return self.enabled and self.state not in (4, 5)

    # --- port 502 ----------------------------------------------------------------------------
    def _accept(self, sdk_port: int, srv: socket.socket) -> None:
        while self._running:
            try:
                conn, _ = srv.accept()
            except (TimeoutError, OSError):
                continue
            conn.settimeout(None)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns.append(conn)
            target = self._serve_main if sdk_port == 502 else self._serve_report
            th = threading.Thread(target=target, args=(conn, sdk_port), daemon=True)
            th.start()
            self._threads.append(th)

    def _serve_main(self, conn: socket.socket, _port: int) -> None:
        buf = b""
        while self._running:
            try:
                chunk = conn.recv(4096)
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            while len(buf) >= 6:
                length = struct.unpack(">H", buf[4:6])[0] + 6
                if len(buf) < length:
                    break
                frame, buf = buf[:length], buf[length:]
                reply = self._handle(frame)
                if reply is None:
                    continue
                try:
                    conn.sendall(reply)
                except OSError:
                    return
        _close(conn)

    def _handle(self, frame: bytes) -> bytes | None:
        tid, pid, _ = struct.unpack(">HHH", frame[:6])
        reg, payload = frame[6], frame[7:]
        now = time.perf_counter()
        with self._lock:
            if self._silent:
                return None
            self.requests.append((now, reg, payload))
            self._advance()
            if reg == 29 and self._drop is not None and len(self.servo) + 1 >= self._drop[0]:
                self.servo.append(
                    ServoEntry(now, _floats(payload, 7), self.mode, self.state, False)
                )
                self.events.append((now, "drop", self._drop[1]))
                if self._drop[1] == "silent":
                    self._silent = True
                else:
                    self._running = False
                    for s in self._conns + self._servers:
                        _close(s)
                return None
            handler = getattr(self, f"_r{reg}", None)
            invalid = False
            if handler is None:
                self.unknown.append(reg)
                data, invalid = b"", True
            else:
                data = handler(payload, now) or b""
            flags = (0x40 if self.error_code else 0) | (0x20 if self.warn_code else 0)
            flags |= 0 if self._ready() else 0x10
            flags |= 0x08 if invalid else 0
        head = struct.pack(">HHH", tid, pid, len(data) + 2)
        return head + bytes([reg, flags]) + data

    def _r1(self, p: bytes, now: float) -> bytes:  # version
        return f"7,7,{self.serial},AC130300001,v{self.version}".encode().ljust(40, b"\0")

    def _r2(self, p: bytes, now: float) -> bytes:  # robot serial \0 control box serial
        return f"{self.serial}\0AC130300001".encode().ljust(40, b"\0")

    def _r11(self, p: bytes, now: float) -> None:  # motion enable (axis 8 = all)
        self.enabled = bool(p[1])
        self.events.append((now, "motion_enable", self.enabled))
        if not self.enabled:
            self.state = 4

    def _r12(self, p: bytes, now: float) -> None:  # set state
        want = p[0]
        self.events.append((now, "set_state", want))
        if want == 0:
            if self.error_code == 0 and self.enabled:
                self.mode = self.pending_mode
                self._plan, self._vel, self._target = None, None, self.arm.q
                self._last_servo = None
                self.state = 2
        elif want in (3, 4, 6):
            self.state = 4 if want in (4, 6) else 3
            self._plan, self._vel, self._target = None, None, self.arm.q

    def _r13(self, p: bytes, now: float) -> bytes:
        return bytes([self.state])

    def _r14(self, p: bytes, now: float) -> bytes:
        return struct.pack(">H", 0)

    def _r15(self, p: bytes, now: float) -> bytes:
        return bytes([self.error_code, self.warn_code])

    def _r16(self, p: bytes, now: float) -> None:
        self.error_code = 0
        self.events.append((now, "clean_error", None))

    def _r17(self, p: bytes, now: float) -> None:
        self.warn_code = 0
        self.events.append((now, "clean_warn", None))

    def _r19(self, p: bytes, now: float) -> None:  # set mode (applied at set_state(0))
        self.pending_mode = p[0]
        self.events.append((now, "set_mode", p[0]))

    def _r23(self, p: bytes, now: float) -> None:  # joint move: 7 joints, speed, acc, time
        vals = _floats(p, 10)
        goal, speed = vals[:7], float(vals[7])
        self.events.append((now, "move_joint", goal.copy()))
        if not self._ready() or self.mode != 0:
            return
        if np.any((goal < self.ranges[:, 0]) | (goal > self.ranges[:, 1])):
            self._fault(23)
            return
        start = self._ctrl_at(now)
        dist = float(np.max(np.abs(goal - start)))
        dur = max(1.875 * dist / max(speed, 1e-6), 0.01)
        self._plan = (now, start, goal, dur)
        self.state = 1

    def _r29(self, p: bytes, now: float) -> None:  # servo_j: 7 joints, speed, acc, time
        q = _floats(p, 10)[:7]
        n = len(self.servo) + 1
        applied = self._ready() and self.mode == 1 and self.error_code == 0
        self.servo.append(ServoEntry(now, q, self.mode, self.state, applied))
        if n in self._inject:
            kind, code = self._inject[n]
            if kind == "warn":  # a warning does not stop the arm
                self.warn_code = code
                self.events.append((now, "warn", code))
            else:
                self.servo[-1].applied = False
                self._fault(code)
                return
        if not applied:
            return
        if np.any((q < self.ranges[:, 0]) | (q > self.ranges[:, 1])):
            self.servo[-1].applied = False
            self._fault(23)
            return
        prev = self.arm.q if self._last_servo is None else self._last_servo
        if np.max(np.abs(q - prev)) / SERVO_PERIOD > QD_MAX_FW * (1 + 1e-6):
            self.servo[-1].applied = False
            self._fault(24)
            return
        if self._tcp_max is not None and self._tcp_speed(prev, q) > self._tcp_max:
            self.servo[-1].applied = False
            self._fault(60)
            return
        self._last_servo, self._last_servo_t = q, now
        self._target = q
        self.state = 1

    def _tcp_speed(self, qa: np.ndarray, qb: np.ndarray) -> float:
        """Flange speed implied by two servo targets one nominal period apart [m/s]."""
        pa, pb = (self._fk.flange(q) for q in (qa, qb))
        return float(np.linalg.norm(pb - pa)) / SERVO_PERIOD

    def _r81(self, p: bytes, now: float) -> None:  # joint velocity: 7 floats, sync, duration
        v = _floats(p, 7).astype(float)
        dur = struct.unpack("<f", p[29:33])[0] if len(p) >= 33 else -1.0
        self.events.append((now, "velocity", v))
        if not (self._ready() and self.mode == 4 and self.error_code == 0):
            return
        if np.max(np.abs(v)) > QD_MAX_FW * (1 + 1e-6):
            self._fault(24)
            return
        self._vel = (now, self._ctrl_at(now), v, float(dur))
        self.state = 1

    def _r41(self, p: bytes, now: float) -> bytes:
        return struct.pack("<6f", *self.arm.tcp_pose())

    def _r42(self, p: bytes, now: float) -> bytes:  # joints; with [num]: pos, vel, effort
        num = (p[0] & 0x0F) if p else 1
        rows = [self.arm.q, self.arm.qd, self.arm.tau][: max(1, num)]
        return b"".join(struct.pack("<7f", *r) for r in rows)

    def _r53(self, p: bytes, now: float) -> bytes:  # reduced states (79 bytes)
        on = self.reduced is not None
        speed, ranges = self.reduced if on else (QD_MAX_FW, np.zeros((7, 2)))
        out = bytes([int(on)]) + struct.pack(">6h", *([0] * 6))
        out += struct.pack("<2f", 1000.0, speed) + struct.pack("<14f", *np.ravel(ranges))
        return out + bytes([0, 0])

    # --- reports -----------------------------------------------------------------------------
    def _serve_report(self, conn: socket.socket, port: int) -> None:
        period = 1.0 / self.report_hz[port]
        nxt = time.perf_counter()
        counter = 0
        while self._running:
            with self._lock:
                self._advance()
                frame = self._frame(port, counter)
            try:
                conn.sendall(frame)
            except OSError:
                break
            counter += 1
            nxt += period
            time.sleep(max(0.0, nxt - time.perf_counter()))
        _close(conn)

    def _frame(self, port: int, counter: int) -> bytes:
        size = FRAME_SIZE[port]
        b = bytearray(size)
        struct.pack_into(">I", b, 0, size)
        q, qd, tau = self.arm.q, self.arm.qd, self.arm.tau
        state_mode = (self.state & 0x0F) | (self.mode << 4)
        if port == 30000:
            ts = int((self.arm.stamp(time.perf_counter()) + self.rt_epoch_s) * 1e6)
            struct.pack_into(">QBH", b, 4, ts, state_mode, 0)
            target = self._ctrl_at(time.perf_counter())
            for off, vals in ((32, target), (116, q), (144, qd), (228, tau)):
                struct.pack_into("<7f", b, off, *vals)
            struct.pack_into("<6f", b, 472, *self.arm.tcp_pose())
            return bytes(b)
        b[4] = state_mode
        struct.pack_into("<7f", b, 7, *q)
        struct.pack_into("<6f", b, 35, *self.arm.tcp_pose())
        struct.pack_into("<7f", b, 59, *tau)
        if port == 30003:
            return bytes(b)
        mt = 0xFF if self.enabled else 0
        b[87:91] = bytes([mt, mt, self.error_code, self.warn_code])
        b[131:133] = bytes([3, 3])  # collision / teach sensitivity
        struct.pack_into("<3f", b, 133, 0.0, 0.0, -1.0)
        if port == 30001:
            return bytes(b)
        b[145:151] = bytes([7, 7, 0, 0, 0, 0])
        b[151:181] = f"v{self.version}".encode().ljust(30, b"\0")
        struct.pack_into("<5f", b, 181, 1000.0, 1.0, 50000.0, 0.1, 1000.0)
        struct.pack_into("<5f", b, 201, 20.0, 0.01, 20.0, 0.0001, QD_MAX_FW)
        struct.pack_into("<2f", b, 221, 2.3, 2.7)
        b[245:252] = bytes([30] * 7)
        struct.pack_into("<8f", b, 252, 0.0, *qd)
        struct.pack_into(">I", b, 284, counter)
        b[495] = int(self.reduced is not None)
        if self.reduced is not None:
            struct.pack_into("<f", b, 512, self.reduced[0])
            struct.pack_into("<14f", b, 516, *np.ravel(self.reduced[1]))
        return bytes(b)


def _floats(payload: bytes, n: int) -> np.ndarray:
    return np.array(struct.unpack(f"<{n}f", payload[: 4 * n]), dtype=float)


def _close(s: socket.socket) -> None:
    with contextlib.suppress(OSError):
        s.shutdown(socket.SHUT_RDWR)
    with contextlib.suppress(OSError):
        s.close()

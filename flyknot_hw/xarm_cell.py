"""The real lab as a :class:`~flyknot.record.Cell`: an xArm 7 streamed at 250 Hz.

One trial (:meth:`XArmCell.run`):

1. connect (once), read the robot's serial and limits; **preflight** the whole command
   against the stricter of the paper's and the robot's limits with the safety margins, the
   torques and the fingertip workspace (:mod:`flyknot_hw.preflight`). A failing command raises
   :class:`~flyknot_hw.preflight.PreflightError` before anything is sent that moves the arm;
2. refuse to start while the controller reports an error or warning, or while the robot's
   current pose or the joint-space path to the start pose breaks a limit;
3. move slowly to the command's first sample (position mode, ``robot.start_speed``);
4. wait for the rope to hang still (the injected settle check, the live markers' check for
   ``settle.mode = "markers"``, an operator's confirmation, or ``settle.before_s``);
5. start the motion capture, switch to servo mode (mode 1, state 0) and stream every sample
   with ``set_servo_angle_j`` on absolute deadlines; hold the last target for
   ``settle.after_s`` while recording, then wait for the rope again (the settle check);
6. on ANY controller error or warning, an SDK refusal, or Ctrl-C: stop streaming and stop
   the arm (state 4). A controller fault ends the trial with ``record.fault`` (its code and
   meaning from the SDK's tables); Ctrl-C re-raises :class:`KeyboardInterrupt`; a lost
   connection or a late stream raises :class:`~flyknot.errors.HardwareError`;
7. back to position mode; the motion capture's recording becomes the record's markers;
   the knot is judged by the injected judge (an operator by default).

The connection, the controller checks and the slow move of steps 1-3 are
:mod:`flyknot_hw.xarm_motion`'s, shared with the base-pose calibration
(:mod:`flyknot_hw.calibrate_driver`).

Measured joints come from the controller's real-time report (port 30000, timestamped at
200 Hz, interpolated onto the 250 Hz ticks) or, without it, from one ``get_servo_angle`` per
tick; ``metadata["joint_source"]`` says which. ``metadata["timing"]``: the stream's
lateness (send time - deadline), period error and reply round trip (mean / p99 / max [ms]),
and per tick ``lateness_us`` and ``round_trip_us``; ``t0_perf_counter_s``, the first command
sample's deadline on this host's ``time.perf_counter``. Times: ``t_joint`` is 0 at the first
command sample.

Markers: the motion capture (a :class:`~flyknot_hw.mocap.stream.MocapSource`: injected, or
built from the lab file's ``[mocap]`` by :func:`flyknot_hw.mocap.trial.open_source`) records
one :class:`~flyknot_hw.mocap.stream.RawStream` per trial, on its own clock; after the stream
it is labelled, aligned to the robot clock on the fingertip and resampled to 200 Hz
(:func:`flyknot_hw.mocap.trial.trial_capture`, with the measured joints, the injected
fingertip kinematics and the lab file's base pose). ``metadata["mocap"]`` holds the source,
the clock offset (``t_robot = t_mocap + offset_s``) and the alignment residual, or the
``error`` that left the trial without markers.
"""

from __future__ import annotations

import contextlib
import gc
import platform
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from flyknot import __version__
from flyknot.errors import CommandError, ConfigError, HardwareError
from flyknot.geometry import matrix_to_quat, quat_to_matrix
from flyknot.judge import KnotJudge, OperatorJudge
from flyknot.limits import JointLimits
from flyknot.record import JointCommand, TrialRecord
from flyknot.verdict import Verdict
from flyknot_hw import xarm_motion, xarm_sdk
from flyknot_hw.config import LabConfig
from flyknot_hw.mocap.stream import MocapSource, RawStream
from flyknot_hw.mocap.trial import (
    CapturedMarkers,
    MarkerSettle,
    gravity_in_mocap,
    open_source,
    trial_capture,
)
from flyknot_hw.preflight import PreflightReport, preflight
from flyknot_hw.rt_report import RealtimeReport
from flyknot_hw.timing import DeadlineClock, SigintLatch, timing_stats
from flyknot_hw.velocity_stream import VelocityStream

__all__ = ["XArmCell", "console_ask", "console_confirm"]

FingertipFK = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""q (k, 7) [rad] -> fingertip position (k, 3) [m] and quaternion (w, x, y, z) (k, 4), in the
robot base frame (the application's kinematics)."""
TorqueModel = Callable[[JointCommand], np.ndarray]
"""A command -> joint torques along it (n, 7) [N m] (the learner's inverse dynamics)."""
SettleCheck = Callable[[str], Mapping[str, Any] | None]
"""Called with ``"before"`` (the throw) and ``"after"`` (the verdict); returns when the rope
hangs still (or raises to abort); may return plain data for the record's metadata."""

SERVO_MODE_TIMEOUT_S = 1.0  # [s]
STREAM_CONTROLLER_MODE = {"servo": 1, "velocity": 4}
"""The controller mode of each ``robot.stream``."""
VELOCITY_WATCHDOG_TICKS = 5
"""In velocity mode each velocity lasts this many ticks unless replaced (the controller then
stops the joints itself: a stalled host cannot leave the arm moving)."""


def console_ask(record: TrialRecord, suggestion: Verdict | None) -> str | None:
    """Ask the operator at the terminal what the rope holds: ``"knot"`` (an overhand knot in
    the hanging rope), ``"wrapped"`` (looped round the held end or the tube), ``"floor"`` (a
    knot lying on the floor), ``"none"``, or None (cannot tell)."""
    hint = f" (the markers suggest: {suggestion.describe()})" if suggestion else ""
    answer = input(
        f"Trial done{hint}. [k]not in the hanging rope / [w]rapped at the grip / "
        "knot on the [f]loor / [n]one / [?] can't tell: "
    ).strip()
    return {
        "k": "knot",
        "knot": "knot",
        "w": "wrapped",
        "wrapped": "wrapped",
        "f": "floor",
        "floor": "floor",
        "n": "none",
        "none": "none",
    }.get(answer.lower())


def console_confirm(phase: str) -> None:
    """Wait for the operator to confirm at the terminal that the rope hangs still."""
    what = "before the throw" if phase == "before" else "before the verdict"
    input(f"Rope hanging still {what}? Press Enter to go on (Ctrl-C aborts): ")


_LostConnectionError = xarm_motion.LostConnectionError


@contextlib.contextmanager
def _no_gc():
    """Python's cyclic garbage collector off while streaming: a full collection in a process
    holding the learner takes tens of milliseconds (73 ms measured), a late tick that stops
    the arm. Collected once before, re-enabled after."""
    was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


class XArmCell:
    """The real lab (see the module docstring).

    Args:
        config: The lab file (:func:`flyknot_hw.config.load_lab_config`).
        fingertip: Fingertip kinematics (:data:`FingertipFK`), base frame.
        judge: Knot judge; default an operator at the terminal (:func:`console_ask`).
        torques: Inverse dynamics for the torque check (:data:`TorqueModel`), or None.
        mocap: The motion capture (:class:`~flyknot_hw.mocap.stream.MocapSource`); None: the
            lab file's (:func:`flyknot_hw.mocap.trial.open_source`).
        settle: The rope-settled check (:data:`SettleCheck`); default for ``markers``: the
            live markers' (:class:`~flyknot_hw.mocap.trial.MarkerSettle`, which needs a live
            source), for ``operator``: :func:`console_confirm`.
        on_tick: Called after every tick (streaming, then holding the last target) with
            (tick, time [s]), e.g. for a progress display.
        trial_index: Index of the next trial.
        brake_s: How long the record runs on after a fault [s].
    """

    def __init__(
        self,
        config: LabConfig,
        *,
        fingertip: FingertipFK,
        judge: KnotJudge | None = None,
        torques: TorqueModel | None = None,
        mocap: MocapSource | None = None,
        settle: SettleCheck | None = None,
        on_tick: Callable[[int, float], None] | None = None,
        trial_index: int = 0,
        brake_s: float = 0.3,
    ):
        if not isinstance(config, LabConfig):
            raise ConfigError("config", f"must be a LabConfig, got {type(config).__name__}")
        if not callable(fingertip):
            raise ConfigError("fingertip", "the cell needs the fingertip kinematics")
        if mocap is None:
            mocap = open_source(config)
        for attr in ("start", "stop"):
            if not callable(getattr(mocap, attr, None)):
                raise ConfigError("mocap", f"a motion-capture source needs {attr}()")
        self.config = config
        self.base_pose = np.array(config.base_pose)
        if settle is None and config.settle.mode == "markers":
            settle = MarkerSettle(
                mocap, self._fingertip_now, gravity_in_mocap(self.base_pose),
                timeout_s=config.settle.timeout_s,
            )  # fmt: skip
        if settle is None and config.settle.mode == "operator":
            settle = console_confirm
        self.trial_index = int(trial_index)
        self._fk, self._torques, self._mocap = fingertip, torques, mocap
        self._settle_check, self._on_tick = settle, on_tick
        self.judge = judge if judge is not None else OperatorJudge(ask=console_ask)
        self.brake_s = brake_s
        self._api: Any = None
        self.robot_limits: JointLimits | None = None
        self.limits: JointLimits | None = None
        self.robot_info: dict[str, Any] = {}

    # --- connection ------------------------------------------------------------------------
    def connect(self) -> None:
        """Connect (if not yet) and read the robot's own limits."""
        if self._api is not None:
            if self._api.connected:
                return
            with contextlib.suppress(Exception):
                self._api.disconnect()
        self._api, self.robot_limits, self.limits, self.robot_info = xarm_motion.connect_arm(
            self.config.robot
        )

    def command_limits(self) -> JointLimits:
        """The limits a command may use here (connects to read them): the stricter of the
        paper's and the robot's less the lab file's safety margins, what the preflight allows."""
        self.connect()
        return self.config.safety.margins.apply(self.limits)  # type: ignore[arg-type]

    def close(self) -> None:
        """Disconnect from the controller."""
        if self._api is not None:
            self._api.disconnect()
            self._api = None

    def __enter__(self) -> XArmCell:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def recover(self) -> int:
        """After a fault and a look at the robot: clear errors and warnings, enable the
        motors, position mode, ready. Returns the controller state."""
        self.connect()
        api = self._api
        api.clean_error()
        api.clean_warn()
        api.motion_enable(True)
        api.set_mode(0)
        api.set_state(0)
        return int(api.get_state()[1])

    # --- checks ----------------------------------------------------------------------------
    def preflight(self, command: JointCommand) -> PreflightReport:
        """Check ``command`` against the effective limits (connects to read them).

        Raises:
            PreflightError: On the first violation.
            ConfigError: If the command's rate is not the lab's servo rate.
        """
        if not isinstance(command, JointCommand):
            raise CommandError(f"command must be a JointCommand, got {type(command).__name__}")
        rate = self.config.robot.servo_rate_hz
        if abs(command.rate_hz - rate) > 1e-6 * rate:
            raise ConfigError(
                "robot.servo_rate_hz",
                f"the command plays at {command.rate_hz:g} Hz, the lab streams at {rate:g} Hz",
            )
        self.connect()
        tau = None if self._torques is None else self._torques(command)
        tip, _ = self._fk(np.asarray(command.q))
        safety = self.config.safety
        return preflight(
            command,
            self.limits,  # type: ignore[arg-type]
            margins=safety.margins,
            torques=tau,
            fingertip=tip,
            workspace=safety.workspace,
            # C60 is servo_j's TCP speed limit: checked only when streaming in servo mode.
            tip_speed_max=safety.tip_speed_max if self.config.robot.stream == "servo" else None,
        )

    def _codes(self) -> tuple[int, int]:
        """The controller's (error, warning) codes, asked now."""
        return xarm_motion.controller_codes(self._api)

    def _joints(self) -> np.ndarray:
        return xarm_motion.read_joints(self._api)

    def _fingertip_now(self) -> np.ndarray:
        """The fingertip now, mocap frame (3,) [m] (for the live markers' settle check)."""
        p, _ = self._fk(self._joints()[None, :])
        r_base = quat_to_matrix(self.base_pose[3:])
        return r_base @ np.asarray(p, dtype=float)[0] + self.base_pose[:3]

    # --- one trial -------------------------------------------------------------------------
    def run(self, command: JointCommand) -> TrialRecord:
        """Play ``command`` once from rest and return what was measured (module docstring)."""
        report = self.preflight(command)
        api = self._api
        xarm_motion.check_controller(api, "before the trial")
        q_now = self._joints()
        q0 = np.asarray(command.q[0], dtype=float)
        limits: JointLimits = self.limits  # type: ignore[assignment]
        xarm_motion.check_move_path(q_now, q0, self._fk, limits, self.config.safety)
        ready = getattr(self._mocap, "ready", None)
        if callable(ready):
            ready()  # the motion capture can record, before anything moves
        rt, src_note = self._open_report()
        latch = SigintLatch()
        mocap_on = False
        settle_meta: dict[str, Any] = {}
        try:
            with latch:
                xarm_motion.position_mode(api)
                xarm_motion.move_joints(api, self.config.robot, q0, q_now, latch)
            settle_meta["before"] = self._settle("before")
            self._mocap.start()
            mocap_on = True
            with latch, _no_gc():
                s = self._stream(command, rt, latch)
            api.set_timeout(xarm_sdk.default_timeout())
            if s["fault"] is None:
                settle_meta["after"] = self._settle("after")
                api.set_mode(0)
                api.set_state(0)
            mocap_on = False
            try:
                stream: object = self._mocap.stop()
            except HardwareError as e:  # no recording: the trial keeps its joints
                stream = e
        except BaseException as e:
            stop = xarm_sdk.stop_arm(api)  # with the stream's short reply timeout
            if api.connected:
                api.set_timeout(xarm_sdk.default_timeout())
            if mocap_on:
                with contextlib.suppress(Exception):
                    self._mocap.stop()
            if rt is not None:
                rt.close()
            if isinstance(e, _LostConnectionError):
                raise HardwareError(f"{e}; stop: {stop}") from None
            raise
        s["joint_source"] = src_note
        q_meas = self._measured(s, rt, command)
        if rt is not None:
            rt.close()
        captured = self._capture(stream, s, q_meas, command)
        record = self._record(command, s, q_meas, captured, report, settle_meta)
        if record.fault is None:
            verdict = self.judge(record)
            knot = None if verdict is None else verdict.knot
            record = replace(record, knot=knot, verdict=verdict)
        self.trial_index += 1
        return record

    def _open_report(self) -> tuple[RealtimeReport | None, str]:
        robot = self.config.robot
        if robot.joint_source == "poll":
            return None, "poll:get_servo_angle"
        rt = RealtimeReport(robot.address, robot.report_port)
        try:
            rt.open()
        except HardwareError:
            if robot.joint_source == "report":
                raise
            return None, "poll:get_servo_angle (report port refused)"
        return rt, f"report{robot.report_port}"

    def _settle(self, phase: str) -> dict[str, Any]:
        cfg = self.config.settle
        t = time.perf_counter()
        extra: Mapping[str, Any] | None = None
        if self._settle_check is not None:
            extra = self._settle_check(phase)
        elif phase == "before":
            time.sleep(cfg.before_s)
        return {"mode": cfg.mode, "waited_s": round(time.perf_counter() - t, 3), **(extra or {})}

    def _servo_mode(self, rt: RealtimeReport | None) -> None:
        """Enter the streaming mode of ``robot.stream``: 1 (servo) or 4 (joint velocity)."""
        api = self._api
        mode = STREAM_CONTROLLER_MODE[self.config.robot.stream]
        api.set_mode(mode)
        api.set_state(0)
        end = time.perf_counter() + SERVO_MODE_TIMEOUT_S
        ok = rt is None or rt.wait_for(lambda s, m: m == mode and s != 4, SERVO_MODE_TIMEOUT_S)
        # The SDK's own idea of the mode (rich report, 5 Hz) must catch up too, or it warns
        # "the mode may be incorrect" on every target.
        while ok and api.mode != mode and time.perf_counter() < end:
            time.sleep(0.005)
        if not ok or api.mode != mode:
            raise HardwareError(
                f"the controller did not enter {self.config.robot.stream} mode (mode {mode}) "
                "within 1 s"
            )

    @staticmethod
    def _latest_q(rt: RealtimeReport | None, q_poll: np.ndarray, i: int) -> np.ndarray | None:
        """The newest measured joints before tick ``i`` (report, or the last poll), or None."""
        if rt is not None:
            return rt.latest_q()
        if i > 0 and np.all(np.isfinite(q_poll[i - 1])):
            return q_poll[i - 1]
        return None

    def _fault_text(self, code: int) -> tuple[str | None, dict[str, Any]]:
        api = self._api
        err, warn = self._codes()
        if err:
            info = xarm_sdk.controller_code("error", err)
            return f"controller error {info['label']} {info['title']}", info
        if warn:
            info = xarm_sdk.controller_code("warn", warn)
            return f"controller warning {info['label']} {info['title']}", info
        if code != 0:
            name = xarm_sdk.api_code_name(code)
            state = api.get_state()[1]
            text = f"the target was refused: SDK code {code} ({name}), controller state {state}"
            return text, {"sdk_code": int(code), "sdk_name": name, "state": int(state)}
        return None, {}

    def _stream(
        self, command: JointCommand, rt: RealtimeReport | None, latch: SigintLatch
    ) -> dict[str, Any]:
        api, robot = self._api, self.config.robot
        q, n, dt = np.asarray(command.q, dtype=float), command.n, command.dt
        self._servo_mode(rt)
        velocity = None
        if robot.stream == "velocity":
            velocity = VelocityStream(q, dt, robot.velocity_gain, self.limits.qd_max)
        end = n + round(self.config.settle.after_s / dt)
        poll = rt is None
        q_poll = np.full((end + round(self.brake_s / dt) + 1, 7), np.nan)
        sent, replied = np.zeros(n), np.zeros(n)
        fault: str | None = None
        info: dict[str, Any] = {}
        fault_tick: int | None = None
        api.set_timeout(robot.reply_timeout_s)
        clock = DeadlineClock(dt)
        t0 = clock.start(lead_s=0.005)
        i = 0
        while i < end:
            latch.check()
            t = clock.wait(i)
            code = 0
            if fault is None and i < n:
                if t - clock.deadline(i) > robot.max_late_s:
                    raise HardwareError(
                        f"tick {i} was sent {1e3 * (t - clock.deadline(i)):.1f} ms late "
                        f"(robot.max_late_s = {1e3 * robot.max_late_s:g} ms); the arm "
                        "was stopped"
                    )
                sent[i] = t
                if velocity is None:
                    code = api.set_servo_angle_j(q[i].tolist(), is_radian=True)
                else:
                    code = api.vc_set_joint_velocity(
                        velocity.at(i, self._latest_q(rt, q_poll, i)).tolist(),
                        is_radian=True,
                        is_sync=True,
                        duration=VELOCITY_WATCHDOG_TICKS * dt,
                    )
                replied[i] = time.perf_counter()
            elif velocity is not None and i == n and fault is None:
                code = api.vc_set_joint_velocity([0.0] * 7, is_radian=True, is_sync=True)
            if code in xarm_sdk.CONNECTION_LOST_CODES or not api.connected:
                raise _LostConnectionError(
                    f"connection to the controller lost at tick {i} (t = {i * dt:.3f} s, "
                    f"SDK code {code} {xarm_sdk.api_code_name(code)})"
                )
            if poll:
                c, qq = api.get_servo_angle(is_radian=True)
                if c == 0:
                    q_poll[i] = qq[:7]
            stopped = rt is not None and (rt.latest() or (0, 0))[0] == 4
            if fault is None and (code != 0 or api.has_err_warn or stopped):
                fault, info = self._fault_text(code)
                if fault is None and stopped:
                    fault = "the controller stopped the arm (state 4)"
                if fault is not None:
                    fault_tick = i
                    info["stop"] = xarm_sdk.stop_arm(api)
                    end = i + 1 + round(self.brake_s / dt)
            if self._on_tick is not None:
                self._on_tick(i, i * dt)
            i += 1
        k = n if fault_tick is None else min(fault_tick + 1, n)
        deadlines = t0 + dt * np.arange(k)
        timing = timing_stats(deadlines, sent[:k], replied[:k], dt)
        timing["lateness_us"] = np.round(1e6 * (sent[:k] - deadlines)).astype(int).tolist()
        timing["round_trip_us"] = np.round(1e6 * (replied[:k] - sent[:k])).astype(int).tolist()
        timing["t0_perf_counter_s"] = t0
        return {
            "t0": t0, "n_ticks": end, "fault": fault, "fault_tick": fault_tick,
            "controller": info, "q_poll": q_poll[:end],
            "timing": timing,
        }  # fmt: skip

    def _capture(self, stream: object, s: dict[str, Any], q_meas, cmd) -> CapturedMarkers:
        """The recording -> the record's markers (:func:`~flyknot_hw.mocap.trial.trial_capture`)."""
        if isinstance(stream, HardwareError):
            return CapturedMarkers.empty({"error": f"no recording: {stream}"})
        if not isinstance(stream, RawStream):
            what = type(stream).__name__
            return CapturedMarkers.empty(
                {"error": f"mocap.stop() returned a {what}, not a RawStream"}
            )
        host = bool(getattr(self._mocap, "host_clock", False))
        return trial_capture(
            stream,
            t_joint=cmd.dt * np.arange(s["n_ticks"]),
            q_meas=q_meas,
            fk=lambda q: np.asarray(self._fk(q)[0]),
            base_pose=self.base_pose,
            coarse_offset_s=-s["t0"] if host else None,
        )

    def _measured(self, s: dict[str, Any], rt: RealtimeReport | None, cmd: JointCommand):
        """Measured joints at the ticks, (N, 7) [rad]; NaN where nothing was measured."""
        if rt is None:
            return s["q_poll"]
        t_tick = s["t0"] + cmd.dt * np.arange(s["n_ticks"])
        fr = rt.frames(since=s["t0"] - 1.0)
        out = np.full((t_tick.size, 7), np.nan)
        if fr.k < 2:
            return out
        inside = (t_tick >= fr.t[0]) & (t_tick <= fr.t[-1] + 2.0 / 200.0)
        for j in range(7):
            out[inside, j] = np.interp(t_tick[inside], fr.t, fr.q[:, j])
        return out

    def _record(self, cmd, s, q_meas, cap, report, settle_meta) -> TrialRecord:
        n, big_n, dt = cmd.n, s["n_ticks"], cmd.dt
        q_cmd = np.asarray(cmd.q, dtype=float)[np.minimum(np.arange(big_n), n - 1)]
        k = s["fault_tick"]
        if k is not None:  # after a fault the arm holds where it stopped
            hold = q_meas[k] if np.all(np.isfinite(q_meas[k])) else q_cmd[k]
            q_cmd[k:] = hold
        tip_pos = np.full((big_n, 3), np.nan)
        tip_quat = np.full((big_n, 4), np.nan)
        ok = np.all(np.isfinite(q_meas), axis=1)
        if ok.any():
            p, quat = self._fk(q_meas[ok])
            r_base = quat_to_matrix(self.base_pose[3:])
            tip_pos[ok] = np.asarray(p) @ r_base.T + self.base_pose[:3]
            tip_quat[ok] = matrix_to_quat(r_base @ quat_to_matrix(np.asarray(quat)))
        robot = self.config.robot
        meta = {
            "cell": "xarm",
            "lab_file": self.config.source,
            "rope": self.config.rope.key,
            "ropes": self.config.rope.ropes,
            "trial_index": self.trial_index,
            "command_duration_s": cmd.duration,
            "servo_rate_hz": robot.servo_rate_hz,
            "joint_source": s["joint_source"],
            "timing": s["timing"],
            "preflight": report.as_metadata(),
            "robot": self.robot_info,
            "controller": s["controller"],
            "settle": settle_meta,
            "mocap": cap.metadata,
            "versions": {
                "flyknot": __version__,
                "xarm_sdk": xarm_sdk.sdk_version(),
                "python": platform.python_version(),
            },
        }
        return TrialRecord(
            t_joint=dt * np.arange(big_n),
            q_cmd=q_cmd,
            q_meas=q_meas,
            t_marker=cap.t_marker,
            markers=cap.markers,
            fingertip_pos=tip_pos,
            fingertip_quat=tip_quat,
            base_pose=self.base_pose,
            fault=None if k is None else f"{s['fault']} at t={k * dt:.3f} s (tick {k})",
            fault_time=None if k is None else k * dt,
            metadata=meta,
        )

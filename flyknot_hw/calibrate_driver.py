"""The driven base-pose calibration: the arm visits joint poses, the motion capture sees its
fingertip at each, a rigid fit gives the robot base in the mocap frame (``flyknot calibrate``).

:func:`run_calibration`, in this order:

1. **Poses**: the user's, or the default ones of the lab file's ``calibration.start``
   (:func:`~flyknot_hw.calibrate_plan.default_poses`); at least ``calibration.min_poses``.
2. **Connect** as the cell does (:func:`~flyknot_hw.xarm_motion.connect_arm`: the robot's own
   limits), refuse while the controller reports an error or a warning, read the current pose
   (the arm's start pose: it returns there at the end).
3. **Preflight every move before anything moves**
   (:func:`~flyknot_hw.calibrate_plan.plan_calibration`): each pose within the position
   limits with the margin; then every move of the tour, start -> pose 1 -> ... -> pose k ->
   start, planned as the controller moves (straight in joint space at ``robot.start_speed``
   and ``robot.start_acc``) and checked by the same :func:`~flyknot_hw.preflight.preflight`
   a throw gets (positions, speeds, accelerations, torques when the application supplies
   them, the fingertip in the workspace box and under ``safety.tip_speed_max``). A failure
   raises :class:`~flyknot_hw.preflight.PreflightError` naming the pose; nothing was sent
   that moves the arm.
4. **The motion capture** of the lab file (:func:`~flyknot_hw.mocap.trial.open_source`; a
   live source is asked for rigid bodies only) is made ready before the arm moves.
5. **At each pose**: the slow move (:func:`~flyknot_hw.xarm_motion.move_joints`); wait until
   the measured joints stay within ``calibration.still_rad`` for ``calibration.still_s``;
   then for ``calibration.window_s`` poll the measured joints (the SDK's ``get_servo_angle``)
   while the motion capture records; the pose's measurement is the mean of the joints and
   the mean of the fingertip cluster's frames (:data:`~flyknot_hw.mocap.trial.TIP_BODY`),
   frames without it dropped. A pose whose cluster was seen in fewer than half the frames,
   or scattered by more than :data:`MAX_TIP_SCATTER_M`, has no usable markers (kept, with
   the reason). A file source must deliver one recording per pose (its capture software
   records while the arm holds).
6. Back to the start pose; then :func:`fit_measurements`: the least-squares fit
   (:func:`~flyknot_hw.mocap.calibration.calibrate_base`) of the fingertips by forward
   kinematics of the measured joints to the measured ones, its residual, the per-pose
   leave-one-out distances and the conditioning. It refuses (:class:`CalibrationError`) when
   fewer than ``calibration.min_poses`` poses had markers, or naming the pose that is an
   outlier (:func:`~flyknot_hw.mocap.calibration.find_outlier`, ``calibration.outlier_mm``).

Any controller error or warning, a refused move, a lost connection or Ctrl-C (a
:class:`~flyknot_hw.timing.SigintLatch`, checked at every poll) stops the arm
(:func:`~flyknot_hw.xarm_sdk.stop_arm`, state 4) and the recording, then raises, as the cell
does; the error carries the controller's code and title.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from flyknot.errors import HardwareError
from flyknot_hw import xarm_sdk
from flyknot_hw.calibrate_plan import (
    CalibrationPlan,
    Kinematics,
    TorqueModel,
    as_poses,
    default_poses,
    plan_calibration,
    xyz,
)
from flyknot_hw.config import CalibrationConfig, LabConfig
from flyknot_hw.mocap.calibration import (
    CalibrationResidual,
    FitConditioning,
    calibrate_base,
    find_outlier,
    fit_conditioning,
    leave_one_out,
)
from flyknot_hw.mocap.live import MotioncaptureSource
from flyknot_hw.mocap.stream import MocapSource, RawStream
from flyknot_hw.mocap.trial import TIP_BODY, open_source
from flyknot_hw.timing import SigintLatch
from flyknot_hw.xarm_motion import (
    REACH_POLL_S,
    LostConnectionError,
    check_controller,
    connect_arm,
    move_joints,
    position_mode,
    read_joints,
)

__all__ = [
    "MAX_TIP_SCATTER_M",
    "CalibrationError",
    "CalibrationResult",
    "PoseMeasurement",
    "fit_measurements",
    "run_calibration",
]

MAX_TIP_SCATTER_M = 0.002
"""[m] a pose whose fingertip frames scatter more than this (rms about their mean) has no
usable markers: the cluster was misread or the arm moved."""
MIN_FRAME_FRACTION = 0.5
"""A pose needs the fingertip cluster in at least this fraction of its frames (and 3)."""
STILL_TIMEOUT_S = 10.0  # [s] longest wait for the arm to come to rest at a pose


class CalibrationError(HardwareError):
    """The measurements do not give a trustworthy fit (too few poses with markers, or an
    outlier); nothing is written.

    Attributes:
        pose: The offending pose (1-based), or None.
        result: The fit over every usable pose, for the report (None: no fit was possible).
    """

    def __init__(self, message: str, pose: int | None = None, result: Any = None):
        super().__init__(message)
        self.pose, self.result = pose, result

    def __reduce__(self):
        return (type(self), (str(self), self.pose))


@dataclass(frozen=True)
class PoseMeasurement:
    """What was measured at one pose.

    Attributes:
        index: The pose's number (1-based).
        q_target: The commanded pose (7,) [rad].
        q_meas: Mean of the measured joints over the window (7,) [rad].
        tip_mocap: Mean of the fingertip cluster's frames, mocap frame (3,) [m]; NaN when
            unusable.
        frames: Frames recorded in the window.
        frames_used: Frames with the fingertip cluster.
        tip_rms_m: Scatter of those frames about their mean [m] (NaN without frames).
        problem: Why the markers are unusable, or None.
    """

    index: int
    q_target: np.ndarray
    q_meas: np.ndarray
    tip_mocap: np.ndarray
    frames: int
    frames_used: int
    tip_rms_m: float
    problem: str | None = None

    @property
    def usable(self) -> bool:
        """Whether the pose enters the fit."""
        return self.problem is None


def _tip_of(stream: RawStream) -> tuple[np.ndarray, int, int, float, str | None]:
    """Mean fingertip, frames, frames used, scatter and the problem (module docstring)."""
    n = stream.n_frames
    body = stream.bodies.get(TIP_BODY)
    if body is None:
        names = ", ".join(sorted(stream.bodies)) or "none"
        return np.full(3, np.nan), n, 0, np.nan, f"no {TIP_BODY!r} body (bodies: {names})"
    p = body.position[np.all(np.isfinite(body.position), axis=1)]
    if len(p) < max(3, MIN_FRAME_FRACTION * n):
        return np.full(3, np.nan), n, len(p), np.nan, f"fingertip seen in {len(p)} of {n} frames"
    mean = p.mean(axis=0)
    rms = float(np.sqrt(np.mean(np.sum((p - mean) ** 2, axis=1))))
    if rms > MAX_TIP_SCATTER_M:
        problem = f"fingertip frames scatter {1e3 * rms:.1f} mm rms"
        return np.full(3, np.nan), n, len(p), rms, problem
    return mean, n, len(p), rms, None


def _check_flags(api: Any, target: str) -> None:
    if api.has_err_warn:
        check_controller(api, f"at {target}")


def _wait_still(api: Any, cal: CalibrationConfig, latch: SigintLatch, target: str) -> None:
    hist: deque[tuple[float, np.ndarray]] = deque()
    end = time.perf_counter() + STILL_TIMEOUT_S
    while True:
        latch.check()
        _check_flags(api, target)
        q, now = read_joints(api), time.perf_counter()
        hist.append((now, q))
        while len(hist) > 1 and hist[1][0] <= now - cal.still_s:
            hist.popleft()
        moved = float(np.max(np.ptp(np.array([h[1] for h in hist]), axis=0)))
        if hist[0][0] <= now - cal.still_s and moved < cal.still_rad:
            return
        if now > end:
            raise HardwareError(
                f"the arm did not come to rest at {target} within {STILL_TIMEOUT_S:g} s "
                f"(joints moved {moved:.2g} rad over {cal.still_s:g} s)"
            )
        time.sleep(REACH_POLL_S)


def _measure(
    api: Any, cal: CalibrationConfig, mocap: MocapSource, latch: SigintLatch, index: int,
    q_target: np.ndarray, recording: list[bool],
) -> PoseMeasurement:  # fmt: skip
    target = f"calibration pose {index}"
    mocap.start()
    recording[0] = True
    qs = []
    end = time.perf_counter() + cal.window_s
    while time.perf_counter() < end:
        latch.check()
        _check_flags(api, target)
        qs.append(read_joints(api))
        time.sleep(REACH_POLL_S)
    recording[0] = False
    try:
        stream: RawStream | None = mocap.stop()
        problem = None
    except HardwareError as e:  # no recording at this pose: it has no markers
        stream, problem = None, f"no recording: {e}"
    q = np.array(qs)
    moved = float(np.max(np.ptp(q, axis=0)))
    if moved > cal.still_rad:
        raise HardwareError(
            f"the arm moved {moved:.2g} rad during the window at {target} "
            f"(calibration.still_rad = {cal.still_rad:g})"
        )
    if stream is None:
        return PoseMeasurement(index, q_target, q.mean(axis=0), np.full(3, np.nan), 0, 0,
                               np.nan, problem)  # fmt: skip
    tip, n, used, rms, problem = _tip_of(stream)
    return PoseMeasurement(index, q_target, q.mean(axis=0), tip, n, used, rms, problem)


def _tour(
    api: Any,
    config: LabConfig,
    plan: CalibrationPlan,
    mocap: MocapSource,
    emit: Callable[[str], Any],
) -> list[PoseMeasurement]:
    """Visit the poses and come back (module docstring, steps 5-6); stop the arm on trouble."""
    latch, recording = SigintLatch(), [False]
    out: list[PoseMeasurement] = []
    k = len(plan.poses)
    try:
        with latch:
            position_mode(api)
            q_prev = plan.q_start
            for i, pose in enumerate(plan.poses, start=1):
                emit(f"moving to calibration pose {i} of {k}")
                move_joints(api, config.robot, pose, q_prev, latch, f"calibration pose {i}")
                _wait_still(api, config.calibration, latch, f"calibration pose {i}")
                m = _measure(api, config.calibration, mocap, latch, i, pose, recording)
                seen = (
                    f"fingertip {xyz(m.tip_mocap)} m (mocap frame), {m.frames_used} of "
                    f"{m.frames} frames, scatter {1e3 * m.tip_rms_m:.2f} mm"
                )
                emit(f"  pose {i}: {seen if m.usable else 'NOT USED: ' + str(m.problem)}")
                out.append(m)
                q_prev = m.q_meas
            emit("moving back to the start pose")
            move_joints(api, config.robot, plan.q_start, q_prev, latch, "the start pose")
    except BaseException as e:
        stop = xarm_sdk.stop_arm(api)
        if recording[0]:
            with contextlib.suppress(Exception):
                mocap.stop()
        if isinstance(e, LostConnectionError):
            raise HardwareError(f"{e}; stop: {stop}") from None
        raise
    return out


def run_calibration(
    config: LabConfig,
    *,
    fingertip: Kinematics,
    torques: TorqueModel | None = None,
    poses: np.ndarray | None = None,
    mocap: MocapSource | None = None,
    emit: Callable[[str], Any] | None = None,
) -> CalibrationResult:
    """Drive the arm through the calibration poses and fit the base pose (module docstring).

    Args:
        config: The lab file.
        fingertip: Fingertip kinematics, base frame (the application's).
        torques: Inverse dynamics for the preflight's torque check, or None.
        poses: Calibration poses (k, 7) [rad]; None: :func:`default_poses`.
        mocap: A motion-capture source instead of the lab file's.
        emit: Called with each line of progress (None: silent).

    Raises:
        PreflightError: A pose or move breaks a limit (before anything moves).
        HardwareError: The controller (code and title), the connection, the motion capture.
        CalibrationError: Too few poses with markers, or an outlier (naming the pose).
        KeyboardInterrupt: Ctrl-C (the arm was stopped).
    """
    say = emit if emit is not None else (lambda line: None)
    q = default_poses(config.calibration.start) if poses is None else as_poses(poses)
    if mocap is None:
        mocap = open_source(config)
        if isinstance(mocap, MotioncaptureSource):
            mocap.require_points = False  # the fingertip's rigid body is all it needs here
    api, _, limits, info = connect_arm(config.robot)
    try:
        check_controller(api, "before the calibration")
        note = f"the connected robot's limits (serial {info.get('serial', '?')})"
        plan = plan_calibration(
            config, q, fingertip, limits=limits, q_start=read_joints(api), torques=torques,
            limits_note=note,
        )  # fmt: skip
        for line in plan.describe():
            say(line)
        ready = getattr(mocap, "ready", None)
        if callable(ready):
            ready()  # the motion capture can record, before anything moves
        measurements = _tour(api, config, plan, mocap, say)
    finally:
        with contextlib.suppress(Exception):
            api.disconnect()
    return fit_measurements(measurements, fingertip, config.calibration)


@dataclass(frozen=True)
class CalibrationResult:
    """The fitted base pose and everything needed to judge it.

    Attributes:
        base_pose: Robot base in the mocap frame (x, y, z, qw, qx, qy, qz), shape (7,).
        residual: The fit's residual over the poses used.
        leave_one_out_m: Per pose used: distance from the fit of the others (k_used,) [m].
        conditioning: Of the poses used.
        measurements: Every pose's measurement, used or not.
        used: Numbers (1-based) of the poses in the fit.
    """

    base_pose: np.ndarray
    residual: CalibrationResidual
    leave_one_out_m: np.ndarray
    conditioning: FitConditioning
    measurements: tuple[PoseMeasurement, ...]
    used: tuple[int, ...]

    def toml(self) -> str:
        """The lab file's ``[base]`` table, its residual in a comment."""
        values = ", ".join(f"{v:.6f}" for v in self.base_pose)
        r = self.residual
        return (
            f"[base]\n# flyknot calibrate: {r.n_poses} poses, residual rms "
            f"{r.rms_m * 1e3:.2f} mm, max {r.max_m * 1e3:.2f} mm\npose = [{values}]\n"
        )

    def report(self) -> list[str]:
        """Per-pose residuals and the fit's summary, as lines of text."""
        lines = ["pose  frames  scatter [mm]  residual [mm]  leave-one-out [mm]"]
        row = {p: k for k, p in enumerate(self.used)}
        for m in self.measurements:
            if m.index in row:
                k = row[m.index]
                res, loo = 1e3 * self.residual.per_pose[k], 1e3 * self.leave_one_out_m[k]
                lines.append(
                    f"{m.index:4d}  {m.frames_used:3d}/{m.frames:<3d}  {1e3 * m.tip_rms_m:12.2f}  "
                    f"{res:13.2f}  {loo:18.2f}"
                )
            else:
                lines.append(f"{m.index:4d}  not used: {m.problem}")
        r = self.residual
        lines.append(
            f"fit of {r.n_poses} poses: residual rms {r.rms_m * 1e3:.2f} mm, "
            f"max {r.max_m * 1e3:.2f} mm"
        )
        lines.append(f"conditioning: {self.conditioning.summary()}")
        return lines


def fit_measurements(
    measurements: list[PoseMeasurement] | tuple[PoseMeasurement, ...],
    fingertip: Kinematics,
    cal: CalibrationConfig,
) -> CalibrationResult:
    """The least-squares base pose from the usable poses (module docstring, step 6).

    Raises:
        CalibrationError: Fewer than ``cal.min_poses`` usable poses, or an outlier.
        ConfigError: The poses' fingertips are (nearly) collinear.
    """
    ms = tuple(measurements)
    good = [m for m in ms if m.usable]
    if len(good) < cal.min_poses:
        why = "; ".join(f"pose {m.index}: {m.problem}" for m in ms if not m.usable)
        raise CalibrationError(
            f"only {len(good)} of {len(ms)} calibration poses had usable fingertip markers "
            f"(calibration.min_poses = {cal.min_poses}): {why or 'no poses'}"
        )
    a = np.asarray(fingertip(np.array([m.q_meas for m in good]))[0], dtype=float)
    b = np.array([m.tip_mocap for m in good])
    pose, residual = calibrate_base(a, b)
    loo = leave_one_out(a, b)
    result = CalibrationResult(
        np.asarray(pose), residual, loo, fit_conditioning(a), ms, tuple(m.index for m in good)
    )
    worst = find_outlier(loo, cal.outlier_mm * 1e-3)
    if worst is not None:
        bad = good[worst].index
        raise CalibrationError(
            f"calibration pose {bad} is an outlier: its fingertip is {1e3 * loo[worst]:.1f} mm "
            f"from the fit of the other poses (calibration.outlier_mm = {cal.outlier_mm:g}; "
            f"median {1e3 * float(np.median(loo)):.2f} mm); check the fingertip markers at "
            "that pose, or leave it out (--poses)",
            pose=bad,
            result=result,
        )
    return result

"""Hardware mode, as the application assembles it: the real cell, its dry run, calibration.

The real lab (:mod:`flyknot_hw`) imports only the core; what it needs from above is injected
here: the learner's fingertip kinematics and inverse dynamics (:class:`LearnerKinematics`).

- :func:`open_xarm_cell` opens an :class:`~flyknot_hw.xarm_cell.XArmCell` from a lab file.
- :class:`DryRunCell` is the dry run: every command is preflighted exactly as on the arm
  (the lab file's margins and workspace, the published limits of the robot) and then played
  in the simulated lab with the lab file's rope; nothing connects to a robot.
- :func:`calibrate_arm` drives the arm through the calibration poses, takes the fingertip
  cluster from the motion capture at each and fits the robot base pose in the mocap frame
  (:mod:`flyknot_hw.calibrate_driver`); :func:`plan_arm_calibration` is its dry run (every
  move preflighted, nothing connected).
- :func:`calibrate` fits the base pose to fingertips measured elsewhere (at given poses).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError
from flyknot.geometry import matrix_to_quat
from flyknot.judge import KnotJudge
from flyknot.limits import JointLimits
from flyknot.record import JointCommand, TrialRecord
from flyknot_hw.calibrate_driver import CalibrationResult, run_calibration
from flyknot_hw.calibrate_plan import CalibrationPlan, dry_run_plan
from flyknot_hw.config import LabConfig, load_lab_config
from flyknot_hw.preflight import PreflightReport, command_derivatives, effective_limits, preflight
from learner.kinematics import RobotModel


class LearnerKinematics:
    """The learner's robot model as the real cell needs it (robot base frame).

    Calling it maps joints q (k, 7) [rad] to fingertip positions (k, 3) [m] and quaternions
    (w, x, y, z) (k, 4); :meth:`torques` maps a command to its inverse-dynamics torques
    (n, 7) [N m] with the same central differences the preflight uses.
    """

    def __init__(self, robot: RobotModel | None = None):
        self.robot = robot if robot is not None else RobotModel.from_mjcf()

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fingertip positions (k, 3) [m] and quaternions (k, 4) of joints q (k, 7) [rad]."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        tip = self.robot.tip_states(q, np.zeros_like(q))
        return tip.p, matrix_to_quat(tip.R)

    def positions(self, q: np.ndarray) -> np.ndarray:
        """Fingertip positions (k, 3) [m] of joints q (k, 7) [rad]."""
        return self(q)[0]

    def torques(self, command: JointCommand) -> np.ndarray:
        """Inverse-dynamics torques (n, 7) [N m] along ``command``."""
        qd, qdd = command_derivatives(command.q, 1.0 / command.rate_hz)
        return self.robot.torques(command.q, qd, qdd)


def _config(lab: str | Path | LabConfig) -> LabConfig:
    return lab if isinstance(lab, LabConfig) else load_lab_config(lab)


def open_xarm_cell(
    lab: str | Path | LabConfig,
    *,
    judge: KnotJudge | None = None,
    settle: Callable[[str], Any] | None = None,
    mocap: Any = None,
    kinematics: LearnerKinematics | None = None,
) -> Any:
    """The real lab of the lab file ``lab``, with the learner's kinematics injected.

    Args:
        lab: A lab file (``assets/lab_example.toml``) or its parsed :class:`LabConfig`.
        judge: Knot judge; None: the operator at the terminal, shown the markers' suggestion.
        settle: Rope-settled check (``settle.mode = "markers"`` or a custom one), or None.
        mocap: A motion-capture source to use instead of the lab file's, or None.
        kinematics: The learner's robot model wrapper (built from the MJCF if None).

    Returns:
        An :class:`~flyknot_hw.xarm_cell.XArmCell` (connects on its first trial).
    """
    from flyknot_hw.xarm_cell import XArmCell

    kin = kinematics if kinematics is not None else LearnerKinematics()
    kwargs: dict[str, Any] = {"fingertip": kin, "torques": kin.torques, "judge": judge}
    if settle is not None:
        kwargs["settle"] = settle
    if mocap is not None:
        kwargs["mocap"] = mocap
    return XArmCell(_config(lab), **kwargs)


class DryRunCell:
    """Preflight as on the arm, then play the command in the simulated lab.

    The lab file's rope, margins and workspace apply; the robot's own joint ranges are the
    published ones (no robot is asked). A command that fails the preflight raises
    :class:`~flyknot_hw.preflight.PreflightError` exactly as the real cell would, before
    anything is played. Each record's metadata carries the preflight report under
    ``"preflight"`` and ``"dry_run": true``.
    """

    def __init__(
        self,
        lab: str | Path | LabConfig,
        *,
        seed: int = 0,
        kinematics: LearnerKinematics | None = None,
    ):
        from flyknot_sim.lab import LabParams, SimLab

        self.config = _config(lab)
        self.kinematics = kinematics if kinematics is not None else LearnerKinematics()
        rope = self.config.rope
        self.sim = SimLab(LabParams(rope=rope.key, seed=seed, ropes=rope.ropes))
        self.limits = effective_limits()
        self.last_report: PreflightReport | None = None

    @property
    def base_pose(self) -> np.ndarray:
        """The simulated lab's calibration (the lab file's base pose is for the real arm)."""
        return self.sim.base_pose

    @property
    def trial_index(self) -> int:
        """Index of the next trial (seeds the simulated lab's variation)."""
        return self.sim.trial_index

    @trial_index.setter
    def trial_index(self, value: int) -> None:
        self.sim.trial_index = value

    def command_limits(self) -> JointLimits:
        """The limits a command may use: the effective ones less the lab file's margins."""
        return self.config.safety.margins.apply(self.limits)

    def check(self, command: JointCommand) -> PreflightReport:
        """The preflight the real cell would run on ``command`` (raises on a violation)."""
        self.last_report = preflight(
            command,
            self.limits,
            margins=self.config.safety.margins,
            torques=self.kinematics.torques(command),
            fingertip=self.kinematics.positions(command.q),
            workspace=self.config.safety.workspace,
            tip_speed_max=(
                self.config.safety.tip_speed_max if self.config.robot.stream == "servo" else None
            ),
        )
        return self.last_report

    def run(self, command: JointCommand) -> TrialRecord:
        """Preflight ``command``, then play it once in the simulated lab."""
        report = self.check(command)
        rec = self.sim.run(command)
        meta = {**rec.metadata, "dry_run": True, "preflight": report.as_metadata()}
        return _with_metadata(rec, meta)


def _with_metadata(rec: TrialRecord, metadata: dict[str, Any]) -> TrialRecord:
    from dataclasses import replace

    return replace(rec, metadata=metadata)


@dataclass(frozen=True)
class Calibration:
    """The fitted base pose and how well it fits.

    Attributes:
        base_pose: Robot base in the mocap frame (x, y, z, qw, qx, qy, qz), shape (7,).
        residual_rms: RMS distance between measured and predicted fingertips [m].
        residual_max: Largest such distance [m].
        poses: The joint poses used, shape (k, 7) [rad].
        per_pose: The distance at each pose, shape (k,) [m].
    """

    base_pose: np.ndarray
    residual_rms: float
    residual_max: float
    poses: np.ndarray
    per_pose: np.ndarray

    def toml(self) -> str:
        """The lab file's ``[base]`` table with this pose."""
        values = ", ".join(f"{v:.6f}" for v in self.base_pose)
        return f"[base]\npose = [{values}]\n"


def calibrate(
    fingertip_in_mocap: Callable[[np.ndarray], np.ndarray],
    poses: Sequence[Sequence[float]] | np.ndarray,
    *,
    kinematics: LearnerKinematics | None = None,
) -> Calibration:
    """Fit the base pose from the fingertip measured at several joint poses.

    Args:
        fingertip_in_mocap: Moves the arm to joint pose q (7,) [rad] and returns the
            fingertip position the motion capture sees there, (3,) [m], mocap frame.
        poses: At least 3 joint poses, shape (k, 7) [rad], whose fingertips are not collinear.
        kinematics: The learner's robot model wrapper.

    Returns:
        The :class:`Calibration` (least squares over a rigid transform).
    """
    from flyknot_hw.mocap.calibration import calibrate_base

    q = np.asarray(poses, dtype=float)
    if q.ndim != 2 or q.shape[1] != 7 or q.shape[0] < 3:
        raise ConfigError("poses", f"must be at least 3 joint poses of 7 joints, got {q.shape}")
    kin = kinematics if kinematics is not None else LearnerKinematics()
    measured = np.array([np.asarray(fingertip_in_mocap(row), dtype=float) for row in q])
    pose, res = calibrate_base(kin.positions(q), measured)
    return Calibration(np.asarray(pose), float(res.rms_m), float(res.max_m), q, res.per_pose)


def plan_arm_calibration(
    lab: str | Path | LabConfig,
    *,
    poses: np.ndarray | None = None,
    kinematics: LearnerKinematics | None = None,
) -> CalibrationPlan:
    """The dry run of :func:`calibrate_arm`: every pose and move preflighted (the published
    limits, the tour from the lab file's ``calibration.start``); nothing connects.

    Args:
        lab: A lab file or its parsed :class:`LabConfig`.
        poses: Calibration poses (k, 7) [rad]; None: the default ones.
        kinematics: The learner's robot model wrapper (built from the MJCF if None).

    Raises:
        PreflightError: A pose or a move breaks a limit (the message names it).
    """
    kin = kinematics if kinematics is not None else LearnerKinematics()
    return dry_run_plan(_config(lab), kin, poses=poses, torques=kin.torques)


def calibrate_arm(
    lab: str | Path | LabConfig,
    *,
    poses: np.ndarray | None = None,
    mocap: Any = None,
    kinematics: LearnerKinematics | None = None,
    emit: Callable[[str], Any] | None = None,
) -> CalibrationResult:
    """Drive the arm of the lab file through the calibration poses and fit its base pose.

    Args:
        lab: A lab file or its parsed :class:`LabConfig`.
        poses: Calibration poses (k, 7) [rad]; None: the default ones.
        mocap: A motion-capture source instead of the lab file's.
        kinematics: The learner's robot model wrapper (fingertip and inverse dynamics).
        emit: Called with each line of progress.

    Returns:
        The fit (:class:`~flyknot_hw.calibrate_driver.CalibrationResult`).

    Raises:
        See :func:`flyknot_hw.calibrate_driver.run_calibration`.
    """
    kin = kinematics if kinematics is not None else LearnerKinematics()
    return run_calibration(
        _config(lab), fingertip=kin, torques=kin.torques, poses=poses, mocap=mocap, emit=emit
    )


def read_rows(flag: str, path: str, width: int) -> np.ndarray:
    """A (k, width) table from a .npy or .csv file (CSV: one row per line, header allowed)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(flag, f"no file {str(p)!r}")
    try:
        a = np.load(p) if p.suffix == ".npy" else np.genfromtxt(p, delimiter=",", comments="#")
    except ValueError as e:
        raise ConfigError(flag, f"{str(p)!r} is not a numeric table: {e}") from None
    a = np.atleast_2d(np.asarray(a, dtype=float))
    a = a[np.all(np.isfinite(a), axis=1)]  # a CSV header row reads as NaN
    if a.ndim != 2 or a.shape[1] != width:
        raise ConfigError(flag, f"{str(p)!r} must hold rows of {width} numbers, got {a.shape}")
    return a


def _calibrate_files(args: Any) -> str:
    """``calibrate --poses P --measured M``: fit fingertips measured elsewhere; the table."""
    if args.poses is None:
        raise ConfigError("--measured", "needs --poses (the joint poses it was measured at)")
    if args.dry_run:
        raise ConfigError("--dry-run", "moves nothing with --measured (a fit of two files)")
    poses = read_rows("--poses", args.poses, 7)
    measured = read_rows("--measured", args.measured, 3)
    if len(measured) != len(poses):
        raise ConfigError(
            "--measured", f"has {len(measured)} rows for {len(poses)} poses (one per pose)"
        )
    rows = iter(measured)
    cal = calibrate(lambda q: next(rows), poses)  # the poses were measured in this order
    print("pose  residual [mm]")
    for i, r in enumerate(cal.per_pose, start=1):
        print(f"{i:4d}  {r * 1e3:13.2f}")
    print(
        f"base pose fitted from {len(poses)} poses: residual rms {cal.residual_rms * 1e3:.2f} mm, "
        f"max {cal.residual_max * 1e3:.2f} mm"
    )
    return cal.toml()


def calibrate_command(args: Any) -> int:
    """``flyknot calibrate``: the driven calibration, its dry run, or a fit of two files.

    ``args``: ``cell`` (lab file), ``poses`` (file or None), ``measured`` (file or None: drive
    the arm), ``dry_run``, ``out`` (file for the ``[base]`` table, or None). Prints the plan
    or the progress, the per-pose residuals and the table; returns the exit code.
    """
    from flyknot_hw.calibrate_driver import CalibrationError

    config = load_lab_config(args.cell)
    if args.out is not None and Path(args.out).resolve() == Path(args.cell).resolve():
        raise ConfigError("--out", "must not be the lab file (it would be overwritten)")
    if args.measured is not None:
        table = _calibrate_files(args)
    else:
        poses = None if args.poses is None else read_rows("--poses", args.poses, 7)
        if args.dry_run:
            print("\n".join(plan_arm_calibration(config, poses=poses).describe()))
            print("dry run: every move passed the preflight; nothing connected, nothing moved")
            return 0
        try:
            result = calibrate_arm(config, poses=poses, emit=print)
        except CalibrationError as e:
            if e.result is not None:
                print("\n".join(e.result.report()))
            raise
        print("\n".join(result.report()))
        table = result.toml()
    old = ", ".join(f"{v:.4f}" for v in config.base_pose)
    print(f"(the lab file's [base] pose now: [{old}])")
    print(table, end="")
    if args.out is not None:
        Path(args.out).write_text(table)
        print(f"Written: {args.out}")
    return 0

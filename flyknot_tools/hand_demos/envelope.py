"""The hand-pace envelope a person and the xArm 7 share, derived from the arm's limits.

A demonstration the arm can follow must not turn the rope faster, move the fingertip faster or
accelerate it harder than the arm can. The arm's side of the envelope is measured on the arm's
own knot-tying throw (a command that ties the knot in the simulated lab, shipped as
``assets/demos/seeds/robot_command.npz``): time-scaling a command by a factor s (playing it
s times faster) multiplies every joint velocity by s and every joint acceleration by s^2, so
the fastest version of the throw the arm can make is the largest s with

    s max|qd_j(t)| <= (1 - margin) qd_max_j,   s^2 max|qdd_j(t)| <= (1 - margin) qdd_max_j,
    |tau_j(q(t), s qd(t), s^2 qdd(t))| <= (1 - margin) tau_max_j       for every joint j, t,

(the paper's limits, ``flyknot.constants``; margin 5 %, the learner's ``limit_margin``). Its
fingertip pace is then (s v_peak, s w_peak, s^2 a_peak): the peak fingertip speed [m/s], the
peak turn rate of the rope's exit axis [rad/s] and the peak fingertip acceleration [m/s^2] of
the arm's fastest throw of that shape (:func:`arm_envelope`).

A person's side is the pace of the hand demonstrations (a free hand flicks the rope axis far
faster than the wrist joints turn, ``docs/learning.md``); the shared envelope is the smaller
of the two in each quantity (:func:`shared_envelope`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import ASSETS_DIR, QD_MAX, QDD_MAX, TAU_MAX
from flyknot.errors import ConfigError, check_positive

ROBOT_THROW = ASSETS_DIR / "demos" / "seeds" / "robot_command.npz"
"""The arm's own knot-tying throw (``docs/robot-feasibility.md``): Bezier ``knots`` (10, 8),
duration ``T`` [s]."""
LIMIT_MARGIN = 0.05
"""Fraction of each joint limit kept free (the learner's ``limit_margin``)."""
HAND_PACE = (3.93, 33.4, 40.8)
"""A person's pace (speed [m/s], exit-axis rate [rad/s], acceleration [m/s^2]): the smallest
peak value of each over the four shipped hand demonstrations (Fast 4.44, 41.9, 45.9; Slow
4.20, 40.3, 43.4; Swipe 4.17, 33.7, 43.8; Inverse 3.93, 33.4, 40.8), measured on their
motion curves."""


@dataclass(frozen=True)
class PaceEnvelope:
    """Peak pace a demonstration may have.

    Attributes:
        speed: Peak fingertip (hand) speed [m/s].
        axis_rate: Peak angular rate of the rope's exit axis [rad/s].
        accel: Peak fingertip (hand) acceleration [m/s^2].
        source: Where the numbers come from (one line).
    """

    speed: float
    axis_rate: float
    accel: float
    source: str = ""

    def __post_init__(self) -> None:
        for f in ("speed", "axis_rate", "accel"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"PaceEnvelope.{f}", f"must be a number > 0, got {v!r}")
            object.__setattr__(self, f, float(v))


@dataclass(frozen=True)
class ArmThrowPace:
    """The arm's throw at its own pace and the fastest time-scaled version of it.

    Attributes:
        scale: Largest time-scaling factor s within the limits (s > 1: the throw can go faster).
        limiting: What sets ``scale``: ``velocity``, ``acceleration`` or ``torque``, with the
            joint (``"velocity J4"``).
        speed: Peak fingertip speed of the throw as it is [m/s].
        axis_rate: Peak exit-axis rate of the throw as it is [rad/s].
        accel: Peak fingertip acceleration of the throw as it is [m/s^2].
        envelope: The pace of the fastest version: (s speed, s axis_rate, s^2 accel).
    """

    scale: float
    limiting: str
    speed: float
    axis_rate: float
    accel: float
    envelope: PaceEnvelope


def fingertip_pace(
    q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, robot: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fingertip speed, exit-axis rate and acceleration along a joint trajectory.

    v = J_p(q) qd,  d' = J_d(q) qd,  a = J_p(q) qdd + (dJ_p/dq qd) qd,
    with J_p = dp_tip/dq and J_d = d(R_tip e_z)/dq (``RobotModel.tip_jacobians``).

    Args:
        q: Joint angles (m, 7) [rad].
        qd: Joint velocities (m, 7) [rad/s].
        qdd: Joint accelerations (m, 7) [rad/s^2].
        robot: A :class:`learner.kinematics.RobotModel`.

    Returns:
        |v| (m,) [m/s], |d'| (m,) [rad/s], |a| (m,) [m/s^2].
    """
    jac = robot.tip_jacobians(q, qd)
    v = np.einsum("mij,mj->mi", jac.dp_dq, qd)
    rate = np.einsum("mij,mj->mi", jac.dd_dq, qd)
    acc = np.einsum("mij,mj->mi", jac.dp_dq, qdd) + np.einsum("mij,mj->mi", jac.dv_dq, qd)
    return (
        np.linalg.norm(v, axis=1),
        np.linalg.norm(rate, axis=1),
        np.linalg.norm(acc, axis=1),
    )


def _torque_ratio(
    robot: Any, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, s: float
) -> np.ndarray:
    """max_t |tau_j(q, s qd, s^2 qdd)| / tau_max_j per joint, shape (7,)."""
    tau = robot.torques(q, s * qd, s * s * qdd)
    return np.abs(tau).max(axis=0) / TAU_MAX


def time_scale_limit(
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    robot: Any,
    margin: float = LIMIT_MARGIN,
) -> tuple[float, str]:
    """Largest time-scaling factor s of a joint trajectory within the paper's limits.

    s = min(s_v, s_a, s_tau): s_v = min_j (1 - margin) qd_max_j / max|qd_j|,
    s_a = min_j sqrt((1 - margin) qdd_max_j / max|qdd_j|), and s_tau the largest s <= min(s_v,
    s_a) with every |tau_j(q, s qd, s^2 qdd)| <= (1 - margin) tau_max_j (bisection to 1e-4;
    the torque grows with s through the velocity and acceleration terms only).

    Args:
        q: Joint angles sampled densely along the trajectory (m, 7) [rad].
        qd: Joint velocities (m, 7) [rad/s].
        qdd: Joint accelerations (m, 7) [rad/s^2].
        robot: A :class:`learner.kinematics.RobotModel`.
        margin: Fraction of each limit kept free, in [0, 1).

    Returns:
        (s, what limits it: ``"velocity J<k>"``, ``"acceleration J<k>"`` or ``"torque J<k>"``).

    Raises:
        ConfigError: ``margin`` outside [0, 1), or the trajectory breaks a torque limit even at
            rest-like speeds (s -> 0: gravity alone).
    """
    if not (isinstance(margin, (int, float)) and 0.0 <= margin < 1.0):
        raise ConfigError("margin", f"must lie in [0, 1), got {margin!r}")
    keep = 1.0 - margin
    vel = np.abs(qd).max(axis=0)
    acc = np.abs(qdd).max(axis=0)
    with np.errstate(divide="ignore"):
        s_v = np.where(vel > 0, keep * QD_MAX / vel, np.inf)
        s_a = np.where(acc > 0, np.sqrt(keep * QDD_MAX / acc), np.inf)
    jv, ja = int(np.argmin(s_v)), int(np.argmin(s_a))
    s, what = (s_v[jv], f"velocity J{jv + 1}")
    if s_a[ja] < s:
        s, what = (s_a[ja], f"acceleration J{ja + 1}")
    if not math.isfinite(s):
        raise ConfigError("qd", "the trajectory does not move")
    if np.all(_torque_ratio(robot, q, qd, qdd, s) <= keep):
        return float(s), what
    if np.any(_torque_ratio(robot, q, qd, qdd, 0.0) > keep):
        raise ConfigError("q", "gravity alone breaks a torque limit on this trajectory")
    lo, hi = 0.0, float(s)
    while hi - lo > 1e-4:
        mid = 0.5 * (lo + hi)
        if np.all(_torque_ratio(robot, q, qd, qdd, mid) <= keep):
            lo = mid
        else:
            hi = mid
    j = int(np.argmax(_torque_ratio(robot, q, qd, qdd, hi)))
    return lo, f"torque J{j + 1}"


def load_command_file(path: str | Path, field: str = "path") -> tuple[np.ndarray, float]:
    """A Bezier command file: ``knots`` (10, 8) and duration ``T`` [s] from an ``.npz``, or a
    run's learned command (``final_knots.npy``, T from the ``result.json`` beside it).

    Raises:
        ConfigError: No such file or an array missing (named by ``field``).
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(field, f"no command file {str(p)!r}")
    if p.suffix == ".npy":
        from flyknot.errors import CommandError
        from flyknot_app.trial_cli import duration_beside, read_npy

        try:
            knots = read_npy(p)
            if knots.shape != (10, 8):
                raise CommandError(f"{str(p)!r} holds {knots.shape}, not Bezier knots (10, 8)")
            return np.array(knots, dtype=float), duration_beside(p)
        except CommandError as e:
            raise ConfigError(field, str(e)) from None
    with np.load(p) as z:
        if "knots" not in z.files or "T" not in z.files:
            raise ConfigError(field, f"{str(p)!r} needs arrays 'knots' and 'T'")
        return np.array(z["knots"], dtype=float), float(z["T"])


def arm_envelope(
    path: str | Path = ROBOT_THROW,
    *,
    robot: Any = None,
    margin: float = LIMIT_MARGIN,
    samples: int = 2001,
) -> ArmThrowPace:
    """The arm's side of the envelope: the pace of its own throw sped up to the first limit.

    Args:
        path: A command file with Bezier ``knots`` (10, 8) and duration ``T`` [s].
        robot: The robot model (default :meth:`learner.kinematics.RobotModel.from_mjcf`).
        margin: Fraction of each joint limit kept free.
        samples: Time samples over [0, T] (>= 3).

    Returns:
        The throw's pace, the scale and the envelope (module docstring).

    Raises:
        ConfigError: No such file, or arrays missing.
    """
    from learner.bezier import sample_command
    from learner.kinematics import RobotModel

    p = Path(path)
    knots, T = load_command_file(p)
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 3:
        raise ConfigError("samples", f"must be an integer >= 3, got {samples!r}")
    robot = RobotModel.from_mjcf() if robot is None else robot
    t = np.linspace(0.0, T, samples)
    q, qd, qdd = (sample_command(knots, T, t, k)[:, :7] for k in (0, 1, 2))
    s, what = time_scale_limit(q, qd, qdd, robot, margin)
    speed, rate, acc = (float(x.max()) for x in fingertip_pace(q, qd, qdd, robot))
    env = PaceEnvelope(
        speed=s * speed,
        axis_rate=s * rate,
        accel=s * s * acc,
        source=f"{p.name} sped up x{s:.3f} to the paper's limits less {margin:.0%} ({what})",
    )
    return ArmThrowPace(s, what, speed, rate, acc, env)


def shared_envelope(
    arm: PaceEnvelope, hand: tuple[float, float, float] = HAND_PACE
) -> PaceEnvelope:
    """The pace both can make: the smaller of the arm's and the person's in each quantity."""
    for name, v in zip(("speed", "axis_rate", "accel"), hand, strict=True):
        check_positive(f"hand.{name}", v)
    return PaceEnvelope(
        speed=min(arm.speed, hand[0]),
        axis_rate=min(arm.axis_rate, hand[1]),
        accel=min(arm.accel, hand[2]),
        source=f"min(arm: {arm.source}; person: the shipped hand demonstrations)",
    )

"""Where the robot stands in the mocap frame: a rigid fit of fingertip positions.

The robot is driven to k joint poses; at each, forward kinematics gives the fingertip in the
robot base frame (``a_i``) and the motion capture sees a marker at the fingertip (``b_i``,
mocap frame). The base pose (R, t) is the least-squares solution of

    min_{R in SO(3), t}  sum_i w_i |R a_i + t - b_i|^2

solved in closed form (Kabsch / Umeyama without scale): with weighted centroids a_bar, b_bar
and the cross-covariance H = sum_i w_i (a_i - a_bar)(b_i - b_bar)^T = U S V^T,

    R = V diag(1, 1, sign det(V U^T)) U^T,     t = b_bar - R a_bar.

The sign term keeps R a rotation (not a reflection). The solution is unique when the centred
a_i span at least a plane (3 non-collinear poses); :func:`calibrate_base` refuses fewer.

Optional refinement (``robust_m``): iteratively reweighted least squares with Huber weights
w_i = min(1, robust_m / r_i), each step the closed form above, so a pose where the marker was
misread counts less. Without it the closed form is already the exact least-squares optimum.

The pose is returned as the records store it: (x, y, z, qw, qx, qy, qz) with
p_mocap = R p_base + t.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError, check_positive
from flyknot.geometry import matrix_to_quat, quat_to_matrix, readonly

__all__ = [
    "MIN_SPREAD_M",
    "CalibrationResidual",
    "apply_pose",
    "calibrate_base",
    "pose_from_rt",
    "rigid_fit",
]

MIN_SPREAD_M = 0.01
"""The poses must span a plane: the second singular value of the centred fingertip positions,
divided by sqrt(k), must exceed this [m] (an RMS spread off the best line of 1 cm)."""

_REFINE_ITERS = 50
_REFINE_TOL = 1e-12  # [m] change of the translation that ends the reweighting


@dataclass(frozen=True)
class CalibrationResidual:
    """How well the fitted base pose explains the measurements.

    Attributes:
        per_pose: |R a_i + t - b_i| per pose, shape (k,) [m].
        rms_m: Root mean square of ``per_pose`` [m].
        max_m: Largest of ``per_pose`` [m].
        n_poses: k.
    """

    per_pose: np.ndarray
    rms_m: float
    max_m: float
    n_poses: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "per_pose", readonly(self.per_pose))


def _points(name: str, a: object) -> np.ndarray:
    p = np.asarray(a, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConfigError(name, f"must have shape (k, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        bad = int(np.argmax(~np.all(np.isfinite(p), axis=1)))
        raise ConfigError(name, f"must be finite; row {bad} is not")
    return p


def rigid_fit(
    a: np.ndarray, b: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R (3, 3) and translation t (3,) [m] minimising sum w_i |R a_i + t - b_i|^2.

    Closed form of the module docstring. ``a``, ``b``: shape (k, 3) [m], k >= 3 (not checked
    for collinearity here: :func:`calibrate_base` does); ``weights``: shape (k,), >= 0.
    """
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    w = w / np.sum(w)
    a_bar = w @ a
    b_bar = w @ b
    H = (a - a_bar).T @ (w[:, None] * (b - b_bar))
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, b_bar - R @ a_bar


def pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(x, y, z, qw, qx, qy, qz), shape (7,), of rotation R (3, 3) and translation t (3,) [m]."""
    return np.concatenate([np.asarray(t, dtype=float), matrix_to_quat(np.asarray(R))])


def apply_pose(pose: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points p (..., 3) of the base frame in the mocap frame: R p + t, pose (7,) as stored."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (7,) or not np.all(np.isfinite(pose)):
        raise ConfigError("base_pose", f"must be 7 finite numbers (x,y,z,qw,qx,qy,qz), got {pose}")
    R = quat_to_matrix(pose[3:])
    return np.asarray(p, dtype=float) @ R.T + pose[:3]


def calibrate_base(
    fk_points: np.ndarray,
    mocap_points: np.ndarray,
    *,
    robust_m: float | None = None,
) -> tuple[np.ndarray, CalibrationResidual]:
    """Robot base pose in the mocap frame from fingertip positions at k joint poses.

    Args:
        fk_points: Fingertip by forward kinematics, robot base frame, shape (k, 3) [m].
        mocap_points: The same fingertip seen by the motion capture, shape (k, 3) [m].
        robust_m: None: plain least squares. A distance [m]: Huber-reweighted refinement
            (module docstring); residuals above it are down-weighted.

    Returns:
        ``(base_pose, residual)``: base_pose (7,) = (x, y, z, qw, qx, qy, qz) with
        p_mocap = R p_base + t; the residual of the fit (:class:`CalibrationResidual`).

    Raises:
        ConfigError: Shapes differ, values are not finite, fewer than 3 poses, or the poses
            do not span a plane (collinear: the rotation about their line is undetermined).
    """
    a = _points("fk_points", fk_points)
    b = _points("mocap_points", mocap_points)
    if a.shape != b.shape:
        raise ConfigError(
            "mocap_points", f"must have the shape of fk_points {a.shape}, got {b.shape}"
        )
    k = a.shape[0]
    if k < 3:
        raise ConfigError("fk_points", f"needs at least 3 non-collinear poses, got {k}")
    for name, p in (("fk_points", a), ("mocap_points", b)):
        sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        spread = sv[1] / np.sqrt(k)
        if spread < MIN_SPREAD_M:
            raise ConfigError(
                name,
                f"the {k} poses are (nearly) collinear: spread off their best line "
                f"{spread * 1e3:.3g} mm < {MIN_SPREAD_M * 1e3:g} mm; add poses off that line",
            )
    if robust_m is not None:
        check_positive("robust_m", robust_m)
    R, t = rigid_fit(a, b)
    if robust_m is not None:
        for _ in range(_REFINE_ITERS):
            r = np.linalg.norm(a @ R.T + t - b, axis=1)
            w = np.minimum(1.0, robust_m / np.maximum(r, 1e-15))
            R, t_new = rigid_fit(a, b, w)
            done = np.linalg.norm(t_new - t) < _REFINE_TOL
            t = t_new
            if done:
                break
    per = np.linalg.norm(a @ R.T + t - b, axis=1)
    residual = CalibrationResidual(
        per_pose=per, rms_m=float(np.sqrt(np.mean(per**2))), max_m=float(per.max()), n_poses=k
    )
    return pose_from_rt(R, t), residual

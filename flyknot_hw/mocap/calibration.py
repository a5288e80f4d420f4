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

**Conditioning** (:func:`fit_conditioning`): how well the poses determine the pose. With the
fingertips centred on their centroid, c_i = a_i - a_bar, a small rotation dtheta moves them by
dtheta x c_i, so the rotation's normal matrix is N = sum_i (|c_i|^2 I - c_i c_i^T); its
condition sqrt(lambda_max / lambda_min) is 1 for an even spread and grows as the poses approach
a line. With independent noise sigma on every measured coordinate, the fit's covariance is
sigma^2 (J^T J)^-1 with the Jacobian J_i = [-[a_i]_x, I] of the residual in (dtheta, dt):
reported as the largest standard deviation of the base position and orientation per 1 mm of
noise (the base origin lies away from the poses, so its position error includes the rotation's
lever arm).

**Outliers** (:func:`leave_one_out`, :func:`find_outlier`): each pose is compared with the fit
of the other poses (a misread marker pulls a fit of all poses towards itself and hides in it);
a pose is an outlier when that distance exceeds both a fixed bound and
:data:`OUTLIER_FACTOR` times the median of those distances over all poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flyknot.errors import ConfigError, check_positive
from flyknot.geometry import matrix_to_quat, quat_to_matrix, readonly

__all__ = [
    "MIN_SPREAD_M",
    "OUTLIER_FACTOR",
    "CalibrationResidual",
    "FitConditioning",
    "apply_pose",
    "calibrate_base",
    "find_outlier",
    "fit_conditioning",
    "leave_one_out",
    "pose_from_rt",
    "rigid_fit",
]

MIN_SPREAD_M = 0.01
"""The poses must span a plane: the second singular value of the centred fingertip positions,
divided by sqrt(k), must exceed this [m] (an RMS spread off the best line of 1 cm)."""

OUTLIER_FACTOR = 4.0
"""A pose is an outlier only if its leave-one-out distance also exceeds this many times the
median over all poses (a fit whose every pose is off by the kinematics' own error has no
outlier)."""

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


@dataclass(frozen=True)
class FitConditioning:
    """How well a set of fingertip positions determines the base pose (module docstring).

    Attributes:
        spread_m: RMS distance of the fingertips from their centroid along their principal
            axes, largest first, shape (3,) [m].
        condition: sqrt(lambda_max / lambda_min) of the rotation's normal matrix [-]; 1 is
            an even spread, infinite for collinear poses.
        position_mm_per_mm: Largest standard deviation of the fitted base position per 1 mm
            of noise on every measured coordinate [mm / mm].
        rotation_deg_per_mm: The same for the base orientation (worst axis) [deg / mm].
    """

    spread_m: np.ndarray
    condition: float
    position_mm_per_mm: float
    rotation_deg_per_mm: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "spread_m", readonly(self.spread_m))

    def summary(self) -> str:
        """One line for a report."""
        spread = " / ".join(f"{1e3 * x:.0f}" for x in self.spread_m)
        return (
            f"spread {spread} mm (rms along the principal axes), condition "
            f"{self.condition:.2f}; 1 mm of noise per pose moves the base by up to "
            f"{self.position_mm_per_mm:.2f} mm and {self.rotation_deg_per_mm:.3f} deg"
        )


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fit_conditioning(fk_points: np.ndarray) -> FitConditioning:
    """The conditioning of a fit to the fingertips ``fk_points`` (k, 3) [m], base frame."""
    a = _points("fk_points", fk_points)
    k = a.shape[0]
    c = a - a.mean(axis=0)
    spread = np.linalg.svd(c, compute_uv=False) / np.sqrt(k)
    spread = np.concatenate([spread, np.zeros(3 - spread.size)])
    normal = np.sum(c * c) * np.eye(3) - c.T @ c
    ev = np.linalg.eigvalsh(normal)
    condition = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 1e-12 * max(ev[-1], 1e-300) else np.inf
    jac = np.concatenate([np.hstack([-_skew(p), np.eye(3)]) for p in a])
    try:
        cov = np.linalg.inv(jac.T @ jac)  # per (1 m)^2 of noise
    except np.linalg.LinAlgError:
        return FitConditioning(spread, np.inf, np.inf, np.inf)
    rot = float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0)))
    pos = float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)))
    return FitConditioning(spread, condition, pos, float(np.degrees(rot)) * 1e-3)


def leave_one_out(fk_points: np.ndarray, mocap_points: np.ndarray) -> np.ndarray:
    """For each pose, the distance of its measured fingertip from the rigid fit of all the
    other poses, shape (k,) [m]; k >= 4."""
    a = _points("fk_points", fk_points)
    b = _points("mocap_points", mocap_points)
    if a.shape != b.shape or a.shape[0] < 4:
        raise ConfigError(
            "mocap_points", f"needs the shape of fk_points and k >= 4, got {a.shape}, {b.shape}"
        )
    out = np.empty(a.shape[0])
    for i in range(a.shape[0]):
        keep = np.arange(a.shape[0]) != i
        R, t = rigid_fit(a[keep], b[keep])
        out[i] = np.linalg.norm(R @ a[i] + t - b[i])
    return out


def find_outlier(loo_m: np.ndarray, bound_m: float) -> int | None:
    """The index of the worst pose whose leave-one-out distance ``loo_m`` (k,) [m] exceeds
    both ``bound_m`` [m] and :data:`OUTLIER_FACTOR` times the median; None if there is none."""
    check_positive("bound_m", bound_m)
    loo = np.asarray(loo_m, dtype=float)
    limit = max(bound_m, OUTLIER_FACTOR * float(np.median(loo)))
    worst = int(np.argmax(loo))
    return worst if loo[worst] > limit else None

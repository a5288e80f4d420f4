"""Geometry shared by every part: SO(3), unit quaternions, skew matrices, read-only arrays.

Conventions: quaternions are (w, x, y, z) (MuJoCo's order), rotation matrices act on column
vectors (p_world = R p_body), rotation vectors phi [rad] have |phi| <= pi. Every function
takes batches over leading axes where its docstring says ``(...)``.
"""

from __future__ import annotations

import numpy as np

from flyknot.errors import ConfigError

_SMALL_ANGLE = 1e-4  # [rad] below this the series forms are used
_SMALL_SIN = 1e-8  # |quaternion vector| below which Log uses its series


def readonly(a: object, dtype: type = float) -> np.ndarray:
    """A read-only copy of ``a`` as an array of ``dtype`` (frozen dataclasses hold these)."""
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def as_vec3(name: str, a: object) -> np.ndarray:
    """``a`` as a float array of shape (..., 3); the error names ``name``."""
    a = np.asarray(a, dtype=float)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ConfigError(name, f"must have shape (..., 3), got {a.shape}")
    return a


def as_mat3(name: str, a: object) -> np.ndarray:
    """``a`` as a float array of shape (..., 3, 3); the error names ``name``."""
    a = np.asarray(a, dtype=float)
    if a.ndim < 2 or a.shape[-2:] != (3, 3):
        raise ConfigError(name, f"must have shape (..., 3, 3), got {a.shape}")
    return a


def skew(w: np.ndarray) -> np.ndarray:
    """[w]x, the matrix with [w]x v = w x v.

    Args:
        w: Vectors, shape (..., 3).

    Returns:
        Skew matrices, shape (..., 3, 3).
    """
    w = as_vec3("w", w)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Exp(phi) = I + (sin th / th) [phi]x + ((1 - cos th) / th^2) [phi]x^2, th = |phi|.

    Series (1 - th^2/6, 1/2 - th^2/24) below 1e-4 rad.

    Args:
        phi: Rotation vectors, shape (..., 3) [rad].

    Returns:
        Rotation matrices, shape (..., 3, 3).
    """
    phi = as_vec3("phi", phi)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = th < _SMALL_ANGLE
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    K = skew(phi)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with w >= 0 of rotation matrices (..., 3, 3).

    Shepperd's rule: take the largest of (tr, R00, R11, R22) under the square root, so the
    divisor is never below 1/2 and the result is accurate for every rotation.
    """
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    which = np.argmax(np.stack([tr, r00, r11, r22], axis=-1), axis=-1)
    q = np.empty((*R.shape[:-2], 4))
    # Differences and sums of the off-diagonal pairs.
    d0 = R[..., 2, 1] - R[..., 1, 2]  # 4 w x
    d1 = R[..., 0, 2] - R[..., 2, 0]  # 4 w y
    d2 = R[..., 1, 0] - R[..., 0, 1]  # 4 w z
    s01 = R[..., 0, 1] + R[..., 1, 0]  # 4 x y
    s02 = R[..., 0, 2] + R[..., 2, 0]  # 4 x z
    s12 = R[..., 1, 2] + R[..., 2, 1]  # 4 y z
    for case, (diag, rest) in enumerate(
        [
            (1.0 + tr, (d0, d1, d2)),  # w
            (1.0 + r00 - r11 - r22, (d0, s01, s02)),  # x: (w, y, z)
            (1.0 - r00 + r11 - r22, (d1, s01, s12)),  # y: (w, x, z)
            (1.0 - r00 - r11 + r22, (d2, s02, s12)),  # z: (w, x, y)
        ]
    ):
        sel = which == case
        if not np.any(sel):
            continue
        big = 0.5 * np.sqrt(np.maximum(diag[sel], 0.0))
        others = [r[sel] / (4.0 * big) for r in rest]
        order = {0: (0, 1, 2, 3), 1: (1, 0, 2, 3), 2: (2, 0, 1, 3), 3: (3, 0, 1, 2)}[case]
        vals = [big, *others]
        for pos, v in zip(order, vals, strict=True):
            q[sel, pos] = v
    q *= np.where(q[..., :1] < 0.0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Log(R), the rotation vector phi with Exp(phi) = R and |phi| <= pi.

    Through the quaternion (w, v) with w >= 0 (:func:`matrix_to_quat`, Shepperd's rule):
    th = 2 atan2(|v|, w), phi = (th / |v|) v, with th / |v| -> 2 / w for |v| < 1e-8 (w ~ 1 there).
    Both the atan2 and Shepperd's rule are well conditioned near th = 0 and th = pi (where
    arccos((tr R - 1) / 2) is not). At exactly th = pi either of the two opposite vectors is
    returned.

    Args:
        R: Rotation matrices, shape (..., 3, 3).

    Returns:
        Rotation vectors, shape (..., 3) [rad].
    """
    R = as_mat3("R", R)
    q = matrix_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    small = s < _SMALL_SIN
    ratio = np.where(
        small, 2.0 / np.maximum(w, 0.5), 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s)
    )
    return v * ratio[..., None]


def _inv_jac_coeff(th: np.ndarray) -> np.ndarray:
    """c(th) = 1/th^2 - (1 + cos th) / (2 th sin th) = 1/th^2 - cot(th/2) / (2 th).

    Series 1/12 + th^2/720 + th^4/30240 below 1e-4 rad; at th = pi, c = 1/pi^2.
    """
    small = th < _SMALL_ANGLE
    ths = np.where(small, 1.0, th)
    exact = 1.0 / ths**2 - np.cos(ths / 2.0) / (2.0 * ths * np.sin(ths / 2.0))
    return np.where(small, 1.0 / 12.0 + th**2 / 720.0 + th**4 / 30240.0, exact)


def right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3): Log(Exp(phi) Exp(d)) = phi + J_r^-1(phi) d + O(d^2).

    J_r^-1(phi) = I + (1/2) [phi]x + (1/th^2 - (1 + cos th) / (2 th sin th)) [phi]x^2,
    th = |phi| in [0, pi].

    Args:
        phi: Rotation vectors, shape (..., 3) [rad].

    Returns:
        Matrices, shape (..., 3, 3).
    """
    phi = as_vec3("phi", phi)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    return np.eye(3) + 0.5 * K + _inv_jac_coeff(th) * (K @ K)


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions (w, x, y, z), normalised first.

    R = I + 2 w [v]x + 2 [v]x^2 for the unit quaternion (w, v).

    Args:
        quat: Quaternions, shape (..., 4), non-zero.

    Returns:
        Rotation matrices, shape (..., 3, 3).

    Raises:
        ConfigError: A quaternion is zero or not finite.
    """
    q = np.asarray(quat, dtype=float)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ConfigError("quat", f"must have shape (..., 4), got {q.shape}")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(n)) or np.any(n < 1e-12):
        raise ConfigError("quat", f"has no direction: {q.tolist()}")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def quat_sign_continuous(quat: np.ndarray, *, first_positive: bool = False) -> np.ndarray:
    """Quaternions (k, 4) with signs flipped so consecutive rows have a non-negative dot product.

    q and -q are one rotation; a sampled path of rotations is made continuous in R^4. With
    ``first_positive`` the whole path is flipped so that the first row has w >= 0.
    """
    q = np.array(quat, dtype=float, copy=True)
    if q.ndim != 2 or q.shape[1] != 4:
        raise ConfigError("quat", f"must have shape (k, 4), got {q.shape}")
    if len(q) == 0:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=1)
    flips = np.concatenate([[1.0], np.where(dots < 0.0, -1.0, 1.0)])
    sign = np.cumprod(flips)
    if first_positive and q[0, 0] < 0:
        sign = -sign
    return q * sign[:, None]


def quat_from_x_to(axis: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the smallest rotation taking e_x to ``axis``.

    q = normalise(1 + u . a, u x a) takes a unit vector u to a = axis / |axis|. For
    e_x . a >= 0 it is used with u = e_x; otherwise (where 1 + e_x . a would cancel) with
    u = -e_x, composed with the half turn about e_z that takes e_x to -e_x:
    q = q(-e_x -> a) (0, 0, 0, 1). (The result is the smallest rotation up to that choice.)

    Args:
        axis: Direction, shape (3,), non-zero.

    Returns:
        Quaternion, shape (4,).
    """
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    flip = a[0] < 0
    u = np.array([-1.0, 0.0, 0.0]) if flip else np.array([1.0, 0.0, 0.0])
    q = np.concatenate([[1.0 + float(u @ a)], np.cross(u, a)])
    q /= np.linalg.norm(q)
    if flip:  # q (x) (0, 0, 0, 1)
        w, x, y, z = q
        q = np.array([-z, y, -x, w])
    return q


def min_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the smallest rotation taking direction u (3,) to v (3,).

    R = I + [w]x + [w]x^2 / (1 + c) with w = u x v, c = u . v (unit u, v); for opposite
    directions a half turn about an axis perpendicular to u.
    """
    u = np.asarray(u, dtype=float) / np.linalg.norm(u)
    v = np.asarray(v, dtype=float) / np.linalg.norm(v)
    c = float(u @ v)
    if c < -1 + 1e-12:  # opposite: any perpendicular axis
        p = np.cross(u, [1.0, 0, 0]) if abs(u[0]) < 0.9 else np.cross(u, [0, 1.0, 0])
        p /= np.linalg.norm(p)
        return 2 * np.outer(p, p) - np.eye(3)
    wx = skew(np.cross(u, v))
    return np.eye(3) + wx + wx @ wx / (1 + c)


def turning_angles(x: np.ndarray) -> np.ndarray:
    """The turning angle [rad] at each interior vertex 1..n-1 of a polyline x (n + 1, 3):
    the angle between segment k - 1 and segment k, in [0, pi]; shape (n - 1,)."""
    e = np.diff(np.asarray(x, dtype=float), axis=0)
    cross = np.linalg.norm(np.cross(e[:-1], e[1:]), axis=1)
    dot = np.einsum("ij,ij->i", e[:-1], e[1:])
    return np.arctan2(cross, dot)


__all__ = [
    "as_mat3",
    "as_vec3",
    "matrix_to_quat",
    "min_rotation",
    "quat_from_x_to",
    "quat_sign_continuous",
    "quat_to_matrix",
    "readonly",
    "right_jacobian_inv",
    "skew",
    "so3_exp",
    "so3_log",
    "turning_angles",
]

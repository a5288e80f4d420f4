"""The search seed: the family member fitted to the feasibility study's hand motion.

The feasibility study measured a hand motion that tied the flying knot in rope 1
(:data:`REFERENCE_MOTION`, data beside this tool). :func:`fit_motion` fits the motion family
(:class:`flyknot_sim.hand_motion.KnotMotion`) to such a sampled motion and
:func:`load_reference_motion` gives the member every search starts from (or its mirror
image).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError, RecordError
from flyknot_sim.hand_motion import IDENTITY_WARP, KnotMotion, bernstein, tie_matrix
from flyknot_sim.hand_params import hand_rotation

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
"""The offline tools' data (``flyknot_tools/data``)."""

REFERENCE_MOTION = DATA_DIR / "reference_hand_motion_rope1.csv"
"""The feasibility study's flying-knot hand motion (measured data, a search seed)."""

_TIE = tie_matrix()


def angles_from_quat(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (a, b) of R(quat) = Ry(b) Rx(a), unwrapped in time, and the fit residual.

    R e_x = Ry(b) e_x = (cos b, 0, -sin b), so b = atan2(-R_20, R_00); then
    Ry(b)^T R = Rx(a) gives a = atan2(M_21, M_11) with M = Ry(b)^T R. The residual
    |R - Ry(b) Rx(a)|_F is 0 for orientations of this form.

    Args:
        quat: Hand-body quaternions (w, x, y, z), shape (k, 4).

    Returns:
        a, b: shape (k,) [rad]; residual: shape (k,) [-].
    """
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    b = np.unwrap(np.arctan2(-r[:, 2, 0], r[:, 0, 0]))
    m = np.einsum("kji,kjl->kil", hand_rotation(b, np.zeros_like(b)), r)
    a = np.unwrap(np.arctan2(m[:, 2, 1], m[:, 1, 1]))
    residual = np.linalg.norm(r - hand_rotation(b, a), axis=(1, 2))
    return a, b, residual


def fit_motion(
    t: np.ndarray,
    pos: np.ndarray,
    quat: np.ndarray,
    *,
    durations: Sequence[float] = tuple(np.arange(0.60, 1.2001, 0.002)),
    starts: Sequence[float] | None = None,
) -> tuple[KnotMotion, float, float]:
    """Fit the family to a sampled hand motion (positions relative to the first sample).

    For a fixed start t_0 and duration T the family is linear in its free control points,
    so they are the least-squares solution of B(s_k) Y = y_k over the samples
    (s_k = clip((t_k - t_0) / T, 0, 1)); t_0 and T are chosen on grids by the smallest sum of
    the five curves' largest absolute residuals (m and rad).

    Args:
        t: Sample times, shape (k,) [s].
        pos: Hand positions, shape (k, 3) [m].
        quat: Hand-body orientations (w, x, y, z), shape (k, 4) (of the form Ry(b) Rx(a)).
        durations: Candidate T [s].
        starts: Candidate t_0 [s] (default: every 1 ms within 20 ms before the first moving
            sample).

    Returns:
        The motion, its start t_0 [s] and the largest residual over the curves [m or rad].
    """
    t = np.asarray(t, dtype=float)
    p = np.asarray(pos, dtype=float) - np.asarray(pos, dtype=float)[0]
    a, b, _ = angles_from_quat(quat)
    y = np.column_stack([p, a - a[0], b - b[0]])
    if starts is None:
        moving = np.nonzero(np.abs(np.diff(y, axis=0)).max(axis=1) > 1e-9)[0]
        t_move = t[moving[0]] if len(moving) else t[0]
        starts = np.arange(max(t[0], t_move - 0.02), t_move + 1e-9, 0.001)
    if len(durations) == 0 or len(starts) == 0:
        raise ConfigError("durations", "need at least one duration and one start")
    best: tuple[float, KnotMotion, float, float] | None = None
    for t0 in starts:
        for T in durations:
            basis = bernstein(np.clip((t - t0) / T, 0.0, 1.0)) @ _TIE
            free, *_ = np.linalg.lstsq(basis, y, rcond=None)
            err = np.abs(basis @ free - y).max(axis=0)
            if best is None or err.sum() < best[0]:
                motion = KnotMotion(np.concatenate([[T, *IDENTITY_WARP], free.T.ravel()]))
                best = (float(err.sum()), motion, float(t0), float(err.max()))
    return best[1], best[2], best[3]  # type: ignore[index]


def load_reference_motion(path: str | Path = REFERENCE_MOTION) -> KnotMotion:
    """The family member closest to the feasibility study's hand motion (see
    :func:`fit_motion`; max residual 0.4 mm and 0.2 degree)."""
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"reference motion {str(path)!r} does not exist")
    a = np.loadtxt(path, delimiter=",", comments="#", skiprows=2)
    motion, _, _ = fit_motion(a[:, 0], a[:, 1:4], a[:, 4:8], durations=np.arange(0.66, 0.76, 0.002))
    return motion

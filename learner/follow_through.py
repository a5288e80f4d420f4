"""Follow-through fingertip tracking after the critical time (paper, appendix "QP Hand Tracking
Objective" and "Demonstration Tracking").

For model samples t in [t_c, T] the error of the command's fingertip against the matched
demonstration hand is

    e_ft(t) = [p_tip(t) - p_ref(t)            (3) [m]
               Log(R_ref(t)^T R_tip(t))       (3) [rad]
               v_tip(t) - v_ref(t)]           (3) [m/s]

with the fingertip from the command through the Bezier curves and the forward kinematics, in
the demonstration frame: p_tip = K_p(q) + b, R_tip = K_R(q), v_tip = J_p(q) qd + b'.

Matching rule ("the follow-through reference is continuously matched to the robot motion at
t_c"): the demonstration hand (p_h, R_h, v_h) is moved rigidly so that it passes through the
fingertip pose at t_c,

    p_ref(t) = p_h(t) - p_h(t_c) + p_tip(t_c)              (a translation)
    R_ref(t) = R_h(t) R_h(t_c)^T R_tip(t_c)                (a fixed change of hand frame)
    v_ref(t) = v_h(t).

The rotation offset multiplies on the right (a constant rotation between the hand's and the
fingertip's body frames), so the world-frame rotational motion of the demonstration,
R_ref(t) R_ref(t_c)^T = R_h(t) R_h(t_c)^T, is kept, just as the translation keeps the hand's
path. At t_c the position and rotation errors are zero; the velocity error is not matched.

The match is made once at the linearisation point kappa_k and then held fixed: J_ft is the
plain derivative of e_ft with the reference constant. (Were the reference re-matched for every
kappa, the position and rotation errors at t_c would vanish identically and the paper's weights
w_pc, w_Rc at t_c would have no effect; held fixed, they penalise moving the fingertip pose at
t_c away from the current one.) The base rows enter through p_tip = K_p(q) + b(t) and
v_tip = J_p qd + b'(t).

Rotation derivative: with the body-frame angular Jacobian J_w (R_tip(q + dq) =
R_tip Exp(J_w dq)), d Log(R_ref^T R_tip) = J_r^-1(e_R) J_w dq (right Jacobian inverse of SO(3)).
"""

from __future__ import annotations

import numbers

import numpy as np

from flyknot.constants import N_BASE_ROWS, N_JOINTS, N_KNOTS, N_VARS
from flyknot.errors import ConfigError, check_positive
from flyknot.geometry import as_mat3, as_vec3, right_jacobian_inv, so3_log
from learner.bezier import bernstein_basis, check_knots
from learner.inverse_qp import FollowThrough
from learner.kinematics import RobotModel

_T_C_SLACK = 1e-9  # [s] the first sample must be t_c within this


# --------------------------------------------------------------------------------------------
# fingertip kinematics along the command
# --------------------------------------------------------------------------------------------


def tip_angular_jacobian(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """Body-frame angular Jacobian of the fingertip: R_tip(q + dq) ~= R_tip(q) Exp(J_w(q) dq).

    J_w[:, j] = vee(R_tip^T dR_tip/dq_j) (:meth:`RobotModel.tip_angular_jacobians`).

    Args:
        robot: Robot model.
        q: Joints, shape (m, 7) [rad].

    Returns:
        J_w, shape (m, 3, 7) [rad/rad].
    """
    return robot.tip_angular_jacobians(q)


def _fingertip(knots: np.ndarray, T: float, t: np.ndarray, robot: RobotModel):
    """Fingertip along the command: p = K_p(q) + b, R = K_R(q), v = J_p(q) qd + b' at t."""
    B0 = bernstein_basis(t, T, 0)
    B1 = bernstein_basis(t, T, 1)
    y0, y1 = B0 @ knots.T, B1 @ knots.T
    q, qd = y0[:, :N_JOINTS], y1[:, :N_JOINTS]
    st = robot.tip_states(q, qd)
    return st.p + y0[:, N_JOINTS:], st.R, st.v + y1[:, N_JOINTS:], q, qd, B0, B1


def matched_reference(
    p_tip_c: np.ndarray,
    R_tip_c: np.ndarray,
    demo_hand_p: np.ndarray,
    demo_hand_R: np.ndarray,
    demo_hand_v: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The demonstration hand moved rigidly onto the fingertip pose at t_c (module docstring).

    p_ref = p_h - p_h[0] + p_tip_c,  R_ref = R_h R_h[0]^T R_tip_c,  v_ref = v_h, where sample
    0 is t_c.

    Args:
        p_tip_c: Fingertip position at t_c, shape (3,) [m].
        R_tip_c: Fingertip orientation at t_c, shape (3, 3).
        demo_hand_p: Hand positions, shape (k, 3) [m], sample 0 at t_c.
        demo_hand_R: Hand orientations, shape (k, 3, 3).
        demo_hand_v: Hand velocities, shape (k, 3) [m/s].

    Returns:
        (p_ref (k, 3) [m], R_ref (k, 3, 3), v_ref (k, 3) [m/s]).
    """
    p_h = as_vec3("demo_hand_p", demo_hand_p)
    R_h = as_mat3("demo_hand_R", demo_hand_R)
    v_h = as_vec3("demo_hand_v", demo_hand_v)
    k = p_h.shape[0]
    if p_h.shape != (k, 3) or R_h.shape != (k, 3, 3) or v_h.shape != (k, 3) or k < 1:
        raise ConfigError(
            "demo_hand_p",
            f"demo_hand_p, demo_hand_R, demo_hand_v must have shapes (k, 3), (k, 3, 3), (k, 3) "
            f"with k >= 1, got {p_h.shape}, {R_h.shape}, {v_h.shape}",
        )
    p_ref = p_h - p_h[0] + np.asarray(p_tip_c, dtype=float)
    R_ref = R_h @ (R_h[0].T @ np.asarray(R_tip_c, dtype=float))
    return p_ref, R_ref, v_h.copy()


def _times(t_samples: object, T: float, t_c: float) -> np.ndarray:
    t = np.asarray(t_samples, dtype=float)
    if t.ndim != 1 or t.size < 1 or not np.all(np.isfinite(t)):
        raise ConfigError("t_samples", f"must be a finite 1-D array of times, got {t.shape}")
    if np.any(np.diff(t) <= 0):
        raise ConfigError("t_samples", "must be strictly increasing")
    if abs(t[0] - t_c) > _T_C_SLACK or t[-1] > T * (1 + 1e-9):
        raise ConfigError(
            "t_samples",
            f"must start at t_c = {t_c:g} s and end by T = {T:g} s, got [{t[0]:g}, {t[-1]:g}] s",
        )
    return t


def fingertip_errors(
    knots: np.ndarray,
    T: float,
    t: np.ndarray,
    ref_p: np.ndarray,
    ref_R: np.ndarray,
    ref_v: np.ndarray,
    robot: RobotModel,
) -> np.ndarray:
    """e(t) = [p_tip - p_ref, Log(R_ref^T R_tip), v_tip - v_ref] against a fixed reference.

    Args:
        knots: Knots, shape (10, 8).
        T: Duration [s].
        t: Times, shape (k,) [s] in [0, T].
        ref_p: Reference positions, shape (k, 3) [m] (demo frame).
        ref_R: Reference orientations, shape (k, 3, 3).
        ref_v: Reference velocities, shape (k, 3) [m/s].
        robot: Robot model.

    Returns:
        Errors, shape (k, 9) [m, rad, m/s].
    """
    knots = check_knots(knots)
    p, R, v, *_ = _fingertip(knots, T, np.asarray(t, dtype=float), robot)
    e_R = so3_log(np.swapaxes(np.asarray(ref_R, dtype=float), -1, -2) @ R)
    return np.concatenate([p - ref_p, e_R, v - ref_v], axis=1)


def follow_through_terms(
    knots: np.ndarray,
    T: float,
    t_samples: np.ndarray,
    t_c: float,
    demo_hand_p: np.ndarray,
    demo_hand_R: np.ndarray,
    demo_hand_v: np.ndarray,
    robot: RobotModel,
) -> FollowThrough:
    """Follow-through errors e_ft (k, 9) and their knot Jacobians J_ft (k, 9, 80).

    The reference is :func:`matched_reference` at the current knots, then held fixed:

        de_p/dkappa = dK_p/dq S_0 (+ b_i(t) I on the base rows)
        de_R/dkappa = J_r^-1(e_R) J_w S_0
        de_v/dkappa = dv/dq S_0 + dv/dqd S_1 (+ b_i'(t) I on the base rows)

    with S_r[:, 8 j + i] = b_i^(r)(t) on joint row j the Bezier basis (and its derivative).

    Args:
        knots: Current knots kappa_k, shape (10, 8).
        T: Duration [s].
        t_samples: Sample times, shape (k,) [s], strictly increasing, the first equal to t_c,
            all in [t_c, T].
        t_c: Critical time [s].
        demo_hand_p: Demonstration hand positions at t_samples, shape (k, 3) [m] (demo frame).
        demo_hand_R: Demonstration hand orientations at t_samples, shape (k, 3, 3).
        demo_hand_v: Demonstration hand velocities at t_samples, shape (k, 3) [m/s].
        robot: Robot model.

    Returns:
        :class:`learner.inverse_qp.FollowThrough` with ``is_tc`` true at sample 0 only.

    Raises:
        ConfigError: on malformed inputs.
    """
    knots = check_knots(knots)
    if isinstance(T, numbers.Real) and not isinstance(T, bool):
        T = float(T)
    check_positive("T", T)
    t = _times(t_samples, T, float(t_c))
    k = t.size
    p, R, v, q, qd, B0, B1 = _fingertip(knots, T, t, robot)
    p_ref, R_ref, v_ref = matched_reference(p[0], R[0], demo_hand_p, demo_hand_R, demo_hand_v)
    if p_ref.shape[0] != k:
        raise ConfigError(
            "demo_hand_p", f"must have one row per sample ({k}), got {p_ref.shape[0]}"
        )
    e_R = so3_log(np.swapaxes(R_ref, -1, -2) @ R)
    e = np.concatenate([p - p_ref, e_R, v - v_ref], axis=1)
    jac = robot.tip_jacobians(q, qd)
    Jw = tip_angular_jacobian(robot, q)
    JrInv = right_jacobian_inv(e_R)
    arm = N_JOINTS * N_KNOTS
    J = np.zeros((k, 9, N_VARS))

    def arm_cols(Jq: np.ndarray, basis: np.ndarray) -> np.ndarray:
        return np.einsum("kaj,ki->kaji", Jq, basis).reshape(k, Jq.shape[1], arm)

    J[:, 0:3, :arm] = arm_cols(jac.dp_dq, B0)
    J[:, 3:6, :arm] = arm_cols(JrInv @ Jw, B0)
    J[:, 6:9, :arm] = arm_cols(jac.dv_dq, B0) + arm_cols(jac.dv_dqd, B1)
    for c in range(N_BASE_ROWS):
        col = (N_JOINTS + c) * N_KNOTS
        J[:, c, col : col + N_KNOTS] = B0
        J[:, 6 + c, col : col + N_KNOTS] = B1
    is_tc = np.zeros(k, dtype=bool)
    is_tc[0] = True
    return FollowThrough(e=e, J=J, is_tc=is_tc)


__all__ = [
    "fingertip_errors",
    "follow_through_terms",
    "matched_reference",
    "tip_angular_jacobian",
]

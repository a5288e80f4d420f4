"""The learner's robot model: fingertip kinematics and rigid-body inverse dynamics in CasADi.

The chain is read once from the robot's MJCF file (``constants.XARM7_XML``,
:func:`learner.mjcf_chain.read_chain`): body poses, hinge axes and anchors, inertials, armature,
damping and springs. Nothing from a running simulation is used, so the same model serves the
simulated and the real lab (paper, "Robot Model").

Frames and conventions:
    * Every quantity is expressed in the *robot base frame*, the frame of the body that carries
      the first chain joint's body (``link_base`` for the xArm 7).
    * Rotation matrices map tip-frame coordinates to base-frame coordinates; the rope leaves the
      fingertip tube along the fingertip site's z axis, ``d_tip = R_tip[:, 2]``.
    * Joint angles follow MuJoCo: the body rotates by ``q - ref`` about the joint axis through
      the joint anchor, so ``q`` here is exactly MuJoCo's ``qpos`` of the chain joints.

Inverse dynamics (recursive Newton-Euler) gives the torque a joint motor must supply::

    tau = M(q) qdd + c(q, qd) + g(q) + armature * qdd + damping * qd + stiffness * (q - q_spring)

with ``M, c, g`` the rigid-body terms of the chain (bodies rigidly attached to a chain body,
including subtrees whose own joints are held at their reference pose ``qpos0``, are lumped into
it). Armature is MuJoCo's reflected rotor inertia; damping and stiffness are the MJCF's passive
joint terms, which the motor has to overcome. Dry friction (``frictionloss``) is left out: it is
not differentiable and at most ~1 N m on the xArm 7. This equals MuJoCo's ``mj_inverse`` with
constraints disabled (``qfrc_inverse``) when all three flags are on, and ``mj_rne`` (flag 1)
when they are off. Gravity is the model's ``opt.gravity`` (default ``(0, 0, -9.81)`` m/s^2)
rotated into the base frame.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import casadi as ca
import mujoco
import numpy as np

from flyknot.constants import JOINT_NAMES, XARM7_XML
from flyknot.errors import ConfigError
from flyknot.geometry import skew
from learner.mjcf_chain import read_chain
from learner.native import NativeBatch, NativeUnavailableError, compile_batch

FINGERTIP_SITE = "fingertip"

_NATIVE: dict[tuple, dict] = {}
"""Compiled batches per MJCF file (path, modification time) and chain options, shared by the
models read from it in this process (loading them costs more than building the model)."""


# --------------------------------------------------------------------------------------------
# symbolic model
# --------------------------------------------------------------------------------------------


def _rot_axis(axis: np.ndarray, angle: ca.SX) -> ca.SX:
    """Rodrigues: ``Rot(a, th) = I + sin(th) [a]x + (1 - cos(th)) [a]x^2``, (3, 3)."""
    K = ca.DM(skew(axis))
    return ca.DM.eye(3) + ca.sin(angle) * K + (1 - ca.cos(angle)) * (K @ K)


def _body_omega(R: ca.SX, q: ca.SX) -> ca.SX:
    """J_w (3, n) with column j = vee(R^T dR/dq_j): the body-frame angular velocity per unit
    joint rate of an orientation R(q)."""
    dR = ca.jacobian(ca.vec(R), q)  # (9, n), column-major vec
    cols = []
    for j in range(q.numel()):
        W = R.T @ ca.reshape(dR[:, j], 3, 3)  # [w_j]x in the body frame
        cols.append(0.5 * ca.vertcat(W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]))
    return ca.horzcat(*cols)


def _chain_functions(
    chain: dict, n: int, flags: tuple[bool, bool, bool]
) -> tuple[dict[str, ca.Function], dict[str, ca.Function]]:
    """The chain's CasADi functions: the public ones by :class:`RobotModel`'s field names
    (``fk``, ``d_tip``, ``p_dot``, ``tip_jac``, ``inverse_dynamics``, ``torque_jac``) and
    the flat ones its batches map (``tip``, ``tip_jac``, ``tau``, ``tau_jac``, ``tau_jvp``,
    ``tip_omega``; matrices flattened row-major, so numpy reshapes need no transpose)."""
    q = ca.SX.sym("q", n)
    qd = ca.SX.sym("qd", n)
    qdd = ca.SX.sym("qdd", n)
    p_tip, R_tip, tau = _build_symbolic(chain, q, qd, qdd, flags)
    d = R_tip[:, 2]
    Jp = ca.jacobian(p_tip, q)
    v = Jp @ qd
    Jd = ca.jacobian(d, q)
    Jv = ca.jacobian(v, q)
    vq, vqd, vqdd = (ca.SX.sym(name, n) for name in ("vq", "vqd", "vqdd"))
    Jt_q = ca.jacobian(tau, q)
    Jt_qd = ca.jacobian(tau, qd)
    Jt_qdd = ca.jacobian(tau, qdd)
    fk = ca.Function("fk", [q], [p_tip, R_tip], ["q"], ["p_tip", "R_tip"])
    funs = {
        "fk": fk,
        "d_tip": ca.Function("d_tip", [q], [d], ["q"], ["d_tip"]),
        "p_dot": ca.Function("p_dot", [q, qd], [v], ["q", "qd"], ["v_tip"]),
        "tip_jac": ca.Function(
            "tip_jac", [q, qd], [Jp, Jd, Jv, Jp], ["q", "qd"], ["dp_dq", "dd_dq", "dv_dq", "dv_dqd"]
        ),
        "inverse_dynamics": ca.Function(
            "inverse_dynamics", [q, qd, qdd], [tau], ["q", "qd", "qdd"], ["tau"]
        ),
        "torque_jac": ca.Function(
            "torque_jac",
            [q, qd, qdd],
            [Jt_q, Jt_qd, Jt_qdd],
            ["q", "qd", "qdd"],
            ["dtau_dq", "dtau_dqd", "dtau_dqdd"],
        ),
    }

    def rows(x: ca.SX) -> ca.SX:  # row-major flattening
        return ca.reshape(x.T, x.numel(), 1)

    flat = {
        "tip": ca.Function("tip_flat", [q, qd], [p_tip, rows(R_tip), v]),
        "tip_jac": ca.Function("tip_jac_flat", [q, qd], [rows(Jp), rows(Jd), rows(Jv)]),
        "tau": ca.Function("tau_flat", [q, qd, qdd], [tau]),
        "tau_jac": ca.Function(
            "tau_jac_flat", [q, qd, qdd], [rows(Jt_q), rows(Jt_qd), rows(Jt_qdd)]
        ),
        "tau_jvp": ca.Function(
            "tau_jvp_flat",
            [q, qd, qdd, vq, vqd, vqdd],
            [ca.jtimes(tau, ca.vertcat(q, qd, qdd), ca.vertcat(vq, vqd, vqdd))],
        ),
        "tip_omega": ca.Function("tip_omega_flat", [q], [rows(_body_omega(fk(q)[1], q))]),
    }
    return funs, flat


def _build_symbolic(chain: dict, q: ca.SX, qd: ca.SX, qdd: ca.SX, flags: tuple[bool, ...]):
    """Forward kinematics and recursive Newton-Euler in the base frame.

    Forward pass (anchor ``o_i``, axis ``z_i``, segment com ``c_i``, base values
    ``w_0 = dw_0 = 0``, ``a_0 = -g``)::

        w_i  = w_{i-1} + z_i qd_i
        dw_i = dw_{i-1} + z_i qdd_i + w_{i-1} x z_i qd_i
        a_i  = a_{i-1} + dw_{i-1} x r_i + w_{i-1} x (w_{i-1} x r_i),  r_i = o_i - o_{i-1}
        ac_i = a_i + dw_i x (c_i - o_i) + w_i x (w_i x (c_i - o_i))
        F_i  = m_i ac_i,   N_i = I_i dw_i + w_i x I_i w_i

    Backward pass (moments about the anchor)::

        f_i = F_i + f_{i+1}
        n_i = N_i + (c_i - o_i) x F_i + n_{i+1} + (o_{i+1} - o_i) x f_{i+1}
        tau_i = z_i . n_i (+ armature_i qdd_i + damping_i qd_i + stiffness_i (q_i - q_spring_i))

    Returns:
        ``p_tip`` (3, 1) [m], ``R_tip`` (3, 3), ``tau`` (n, 1) [N m].
    """
    links = chain["links"]
    n = len(links)
    R = ca.DM.eye(3)
    p = ca.DM.zeros(3, 1)
    o_prev = ca.DM.zeros(3, 1)
    w = ca.DM.zeros(3, 1)
    dw = ca.DM.zeros(3, 1)
    a = ca.DM(-chain["gravity"].reshape(3, 1))
    frames = []
    for i, lk in enumerate(links):
        R_pre = R @ ca.DM(lk.S)
        o = p + R @ ca.DM(lk.s) + R_pre @ ca.DM(lk.anchor)
        R = R_pre @ _rot_axis(lk.axis, q[i] - lk.ref)
        p = o - R @ ca.DM(lk.anchor)
        z = R_pre @ ca.DM(lk.axis)
        r = o - o_prev
        a = a + ca.cross(dw, r) + ca.cross(w, ca.cross(w, r))
        dw = dw + z * qdd[i] + ca.cross(w, z * qd[i])
        w = w + z * qd[i]
        rc = R @ ca.DM(lk.com - lk.anchor)  # c_i - o_i = (p + R com) - (p + R anchor)
        ac = a + ca.cross(dw, rc) + ca.cross(w, ca.cross(w, rc))
        I_w = R @ ca.DM(lk.inertia) @ R.T
        F = lk.mass * ac
        N = I_w @ dw + ca.cross(w, I_w @ w)
        frames.append((o, z, rc, F, N))
        o_prev = o
    p_tip = p + R @ ca.DM(chain["site_pos"].reshape(3, 1))
    R_tip = R @ ca.DM(chain["site_rot"])
    use_arm, use_damp, use_spring = flags
    f_next = ca.DM.zeros(3, 1)
    n_next = ca.DM.zeros(3, 1)
    o_next = None
    tau = [None] * n
    for i in reversed(range(n)):
        o, z, rc, F, N = frames[i]
        n_i = N + ca.cross(rc, F) + n_next
        if o_next is not None:
            n_i = n_i + ca.cross(o_next - o, f_next)
        f_i = F + f_next
        t = ca.dot(z, n_i)
        if use_arm:
            t = t + chain["armature"][i] * qdd[i]
        if use_damp:
            t = t + chain["damping"][i] * qd[i]
        if use_spring:
            t = t + chain["stiffness"][i] * (q[i] - chain["springref"][i])
        tau[i] = t
        f_next, n_next, o_next = f_i, n_i, o
    return p_tip, R_tip, ca.vertcat(*tau)


class TipStates(NamedTuple):
    """Fingertip states for a batch of configurations."""

    p: np.ndarray  # (m, 3) [m]
    R: np.ndarray  # (m, 3, 3)
    v: np.ndarray  # (m, 3) [m/s]


class TipJacobians(NamedTuple):
    """Jacobians of the fingertip states for a batch of configurations."""

    dp_dq: np.ndarray  # (m, 3, n) [m/rad]
    dd_dq: np.ndarray  # (m, 3, n) [1/rad], d_tip = R_tip[:, 2]
    dv_dq: np.ndarray  # (m, 3, n) [m/(s rad)]
    dv_dqd: np.ndarray  # (m, 3, n) [m/rad] (equals dp_dq)


class TorqueJacobians(NamedTuple):
    """Jacobians of the inverse dynamics for a batch of states."""

    dtau_dq: np.ndarray  # (m, n, n) [N m/rad]
    dtau_dqd: np.ndarray  # (m, n, n) [N m s/rad]
    dtau_dqdd: np.ndarray  # (m, n, n) [N m s^2/rad] (mass matrix + armature)


@dataclass(frozen=True)
class RobotModel:
    """Fingertip kinematics and inverse dynamics of a serial hinge chain, as CasADi Functions.

    Build it with :meth:`from_mjcf`. The CasADi Functions take column vectors (n = 7 joints)
    and accept SX/MX symbols as well as numbers, so optimisers can embed them:

    * ``fk(q) -> (p_tip (3,1) [m], R_tip (3,3))``
    * ``d_tip(q) -> (3,1)``, the rope axis ``R_tip[:, 2]``
    * ``p_dot(q, qd) -> (3,1) [m/s]``, ``v = (d p_tip / d q) qd``
    * ``tip_jac(q, qd) -> (dp/dq, dd_tip/dq, dv/dq, dv/dqd)``, each (3, n)
    * ``inverse_dynamics(q, qd, qdd) -> tau (n,1) [N m]``
    * ``torque_jac(q, qd, qdd) -> (dtau/dq, dtau/dqd, dtau/dqdd)``, each (n, n)

    The numpy methods :meth:`tip_states`, :meth:`tip_jacobians`, :meth:`torques` and
    :meth:`torque_jacobians` evaluate batches (m, n): compiled to native code once per machine
    (:mod:`learner.native`, the same numbers bit for bit) when ``native`` is set and a C
    compiler is there, otherwise through ``Function.map`` in CasADi's interpreter.

    Attributes:
        joint_names: Chain joints, base to tip.
        site_name: Fingertip site.
        base_name: Body whose frame is the base frame.
        gravity: Gravity in the base frame (3,) [m/s^2].
        armature: Reflected rotor inertia per joint (n,) [kg m^2] (0 when not included).
        damping: Viscous joint damping (n,) [N m s/rad] (0 when not included).
        stiffness: Joint spring stiffness (n,) [N m/rad] (0 when not included).
        q_spring: The springs' rest angles (n,) [rad].
        q_range: Joint ranges from the MJCF (n, 2) [rad] (the learner's limits are the
            paper's, see ``flyknot.constants``).
        native: Evaluate batches in compiled code (:mod:`learner.native`); off, or without a
            C compiler (a warning says why), in CasADi's interpreter.
    """

    joint_names: tuple[str, ...]
    site_name: str
    base_name: str
    gravity: np.ndarray
    armature: np.ndarray
    damping: np.ndarray
    stiffness: np.ndarray
    q_range: np.ndarray
    q_spring: np.ndarray
    fk: ca.Function
    d_tip: ca.Function
    p_dot: ca.Function
    tip_jac: ca.Function
    inverse_dynamics: ca.Function
    torque_jac: ca.Function
    _flat: dict[str, ca.Function] = field(repr=False, compare=False)
    native: bool = True
    _maps: dict[tuple[str, int], ca.Function] = field(
        default_factory=dict, repr=False, compare=False
    )
    _native: dict[str, NativeBatch | None] = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_joints(self) -> int:
        """Number of chain joints."""
        return len(self.joint_names)

    def __getstate__(self) -> dict:
        """Pickled without the mapped and compiled batches (a loaded library cannot be
        pickled); the copy builds its own on first use."""
        return {**self.__dict__, "_maps": {}, "_native": {}}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    @classmethod
    def from_mjcf(
        cls,
        path: str | Path = XARM7_XML,
        *,
        joint_names: tuple[str, ...] = JOINT_NAMES,
        site: str = FINGERTIP_SITE,
        base_body: str | None = None,
        include_armature: bool = True,
        include_damping: bool = True,
        include_stiffness: bool = True,
        native: bool = True,
    ) -> RobotModel:
        """Read the chain from an MJCF file and build the CasADi Functions.

        The joints must be hinges, one per body, forming a serial path from the base body to the
        site's body in the listed order. Bodies below a chain body are lumped into it rigidly at
        their reference pose; a free joint below the chain cuts its subtree off.

        Args:
            path: MJCF file.
            joint_names: Chain joints, base to tip.
            site: Fingertip site name.
            base_body: Body whose frame is the base frame; default the parent of the first
                joint's body. It must be fixed to the world.
            include_armature: Add ``armature * qdd`` to the torque.
            include_damping: Add ``damping * qd`` to the torque.
            include_stiffness: Add ``stiffness * (q - q_spring)`` to the torque.
            native: Evaluate batches in compiled code (see the class).

        Returns:
            The model.

        Raises:
            ConfigError: The file is missing, or names or chain structure do not fit.
        """
        path = Path(path)
        if not path.is_file():
            raise ConfigError("path", f"MJCF file {str(path)!r} does not exist")
        model = mujoco.MjModel.from_xml_path(str(path))
        joint_names = tuple(joint_names)
        chain = read_chain(model, joint_names, site, base_body)
        flags = (include_armature, include_damping, include_stiffness)
        n = len(joint_names)
        funs, flat = _chain_functions(chain, n, flags)
        zeros = np.zeros(n)

        def ro(x: np.ndarray) -> np.ndarray:
            x = np.array(x, dtype=float)
            x.setflags(write=False)
            return x

        return cls(
            joint_names=joint_names,
            site_name=site,
            base_name=chain["base_name"],
            gravity=ro(chain["gravity"]),
            armature=ro(chain["armature"] if include_armature else zeros),
            damping=ro(chain["damping"] if include_damping else zeros),
            stiffness=ro(chain["stiffness"] if include_stiffness else zeros),
            q_range=ro(chain["q_range"]),
            q_spring=ro(chain["springref"]),
            **funs,
            native=native,
            _flat=flat,
            _native=_NATIVE.setdefault(
                (str(path.resolve()), path.stat().st_mtime_ns, joint_names, site, base_body, flags),
                {},
            )
            if native
            else {},
        )

    # ---------------------------------------------------------------------------- batches

    def _mapped(self, key: str, m: int) -> ca.Function:
        fun = self._maps.get((key, m))
        if fun is None:
            fun = self._flat[key].map(m, "serial")
            self._maps[(key, m)] = fun
        return fun

    def _compiled(self, key: str) -> NativeBatch | None:
        if key not in self._native:
            try:
                self._native[key] = compile_batch(self._flat[key])
            except NativeUnavailableError as exc:
                warnings.warn(f"robot model in CasADi's interpreter: {exc}", stacklevel=3)
                self._native[key] = None
        return self._native[key]

    def _eval(self, key: str, *inputs: np.ndarray) -> list[np.ndarray]:
        """The flat function ``key`` on a batch: inputs (m, n_i), outputs (m, k_j)."""
        native = self._compiled(key) if self.native else None
        if native is not None:
            return native(*inputs)
        out = self._mapped(key, inputs[0].shape[0])(*(x.T for x in inputs))
        return [np.asarray(o).T for o in (out if isinstance(out, tuple) else (out,))]

    def _batch(self, name: str, x: np.ndarray, m: int | None = None) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        n = self.n_joints
        if x.ndim != 2 or x.shape[1] != n or (m is not None and x.shape[0] != m):
            want = f"({'m' if m is None else m}, {n})"
            raise ConfigError(name, f"expected shape {want}, got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ConfigError(name, "contains non-finite values")
        return x

    def tip_states(self, q: np.ndarray, qd: np.ndarray) -> TipStates:
        """Fingertip position, orientation and velocity for a batch.

        ``p = K_p(q)``, ``R = K_R(q)``, ``v = (d K_p / d q) qd``.

        Args:
            q: Joint angles (m, n) [rad].
            qd: Joint velocities (m, n) [rad/s].

        Returns:
            ``TipStates(p (m, 3) [m], R (m, 3, 3), v (m, 3) [m/s])`` in the base frame.
        """
        q = self._batch("q", q)
        qd = self._batch("qd", qd, q.shape[0])
        m = q.shape[0]
        p, R, v = self._eval("tip", q, qd)
        return TipStates(p, R.reshape(m, 3, 3), v)

    def tip_angular_jacobians(self, q: np.ndarray) -> np.ndarray:
        """Body-frame angular Jacobian of the fingertip for a batch:
        ``R_tip(q + dq) ~= R_tip(q) Exp(J_w(q) dq)``, ``J_w[:, j] = vee(R^T dR/dq_j)``.

        Args:
            q: Joint angles (m, n) [rad].

        Returns:
            J_w, shape (m, 3, n) [rad/rad].
        """
        q = self._batch("q", q)
        m, n = q.shape
        return self._eval("tip_omega", q)[0].reshape(m, 3, n)

    def tip_jacobians(self, q: np.ndarray, qd: np.ndarray) -> TipJacobians:
        """Jacobians of the fingertip states for a batch.

        ``dp/dq = d K_p / d q``, ``dd/dq = d (K_R e_z) / d q``, ``dv/dq = d (J_p(q) qd) / d q``,
        ``dv/dqd = J_p(q)``.

        Args:
            q: Joint angles (m, n) [rad].
            qd: Joint velocities (m, n) [rad/s].

        Returns:
            ``TipJacobians`` with four (m, 3, n) arrays.
        """
        q = self._batch("q", q)
        qd = self._batch("qd", qd, q.shape[0])
        m, n = q.shape
        Jp, Jd, Jv = (J.reshape(m, 3, n) for J in self._eval("tip_jac", q, qd))
        return TipJacobians(Jp, Jd, Jv, Jp.copy())

    def torques(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Inverse dynamics for a batch, ``tau = ID(q, qd, qdd)`` (see the module docstring).

        Args:
            q: Joint angles (m, n) [rad].
            qd: Joint velocities (m, n) [rad/s].
            qdd: Joint accelerations (m, n) [rad/s^2].

        Returns:
            Joint torques (m, n) [N m].
        """
        q = self._batch("q", q)
        m = q.shape[0]
        qd = self._batch("qd", qd, m)
        qdd = self._batch("qdd", qdd, m)
        return self._eval("tau", q, qd, qdd)[0]

    def passive_torques(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """The joints' own part of :meth:`torques` for a batch; the links' rigid-body torque is
        the rest, the torque the simulated controller faults on.

            tau_joint = armature * qdd + damping * qd + stiffness * (q - q_spring)   (m, n) [N m]

        Linear in the state: its Jacobians are diag(stiffness), diag(damping) and
        diag(armature).
        """
        q = self._batch("q", q)
        m = q.shape[0]
        qd, qdd = self._batch("qd", qd, m), self._batch("qdd", qdd, m)
        return self.armature * qdd + self.damping * qd + self.stiffness * (q - self.q_spring)

    def torque_jacobians(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> TorqueJacobians:
        """Jacobians of the inverse dynamics for a batch.

        ``dtau/dq``, ``dtau/dqd`` and ``dtau/dqdd = M(q) + diag(armature)``.

        Args:
            q: Joint angles (m, n) [rad].
            qd: Joint velocities (m, n) [rad/s].
            qdd: Joint accelerations (m, n) [rad/s^2].

        Returns:
            ``TorqueJacobians`` with three (m, n, n) arrays.
        """
        q = self._batch("q", q)
        m, n = q.shape
        qd = self._batch("qd", qd, m)
        qdd = self._batch("qdd", qdd, m)
        a, b, c = self._eval("tau_jac", q, qd, qdd)
        return TorqueJacobians(*(x.reshape(m, n, n) for x in (a, b, c)))

    def torque_jvp(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        qdd: np.ndarray,
        dq: np.ndarray,
        dqd: np.ndarray,
        dqdd: np.ndarray,
    ) -> np.ndarray:
        """Directional derivative of the inverse dynamics for a batch (forward mode).

        ``dtau = dtau/dq dq + dtau/dqd dqd + dtau/dqdd dqdd`` at each state, without forming
        the Jacobians.

        Args:
            q: Joint angles (m, n) [rad].
            qd: Joint velocities (m, n) [rad/s].
            qdd: Joint accelerations (m, n) [rad/s^2].
            dq: Direction of the angles (m, n) [rad].
            dqd: Direction of the velocities (m, n) [rad/s].
            dqdd: Direction of the accelerations (m, n) [rad/s^2].

        Returns:
            ``dtau`` (m, n) [N m].
        """
        q = self._batch("q", q)
        m = q.shape[0]
        args = [self._batch(name, x, m) for name, x in (("qd", qd), ("qdd", qdd))]
        dirs = [self._batch(name, x, m) for name, x in (("dq", dq), ("dqd", dqd), ("dqdd", dqdd))]
        return self._eval("tau_jvp", q, *args, *dirs)[0]

"""The simulated xArm 7: names in ``assets/xarm7/xarm7.xml`` and its joint position servos.

The MJCF is ours (UFACTORY's published kinematics and inertials, primitive geometry); see
``assets/xarm7/README.md``. Each actuator ``act<i>`` is a position servo on ``joint<i>``::

    tau_i = kp_i (u_i - q_i) - kv_i qd_i                                  [N m]

written in MuJoCo's affine form ``gainprm = (kp,)``, ``biasprm = (0, -kp, -kv)``, where ``u``
is the joint position target [rad] (``ctrl``), ``q`` [rad] and ``qd`` [rad/s] the joint state.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from flyknot.constants import JOINT_NAMES, N_JOINTS, XARM7_XML
from flyknot.errors import ConfigError, check_nonnegative, check_positive

__all__ = [
    "ACTUATOR_NAMES",
    "BASE_BODY",
    "FINGERTIP_SITE",
    "FLANGE_SITE",
    "JOINT_NAMES",
    "ServoParams",
    "actuator_ids",
    "apply_servo_params",
    "load_robot_model",
    "load_robot_spec",
]

FINGERTIP_SITE = "fingertip"  # end of the rope tube; its z axis points out of the tube
FLANGE_SITE = "flange"  # tool flange, origin of body link7
BASE_BODY = "link_base"
FINGERTIP_BODY = "link7"  # the body carrying the fingertip tube (the rope's anchor)
ACTUATOR_NAMES = tuple(f"act{i}" for i in range(1, N_JOINTS + 1))


def load_robot_spec() -> mujoco.MjSpec:
    """Parse the xArm 7 MJCF (``constants.XARM7_XML``) into a fresh, editable spec."""
    return mujoco.MjSpec.from_file(str(XARM7_XML))


def load_robot_model() -> mujoco.MjModel:
    """Compile the robot alone (gravity on, no rope): the model used for inverse dynamics."""
    return load_robot_spec().compile()


def fingertip_anchor() -> tuple[str, np.ndarray, np.ndarray]:
    """Where the rope is held: (body name, position (3,) [m], rope axis (3,)) in that body.

    Read from the fingertip site of the MJCF: its position on ``link7`` and its z axis,
    along which the rope leaves the tube.
    """
    model = load_robot_model()
    sid = model.site(FINGERTIP_SITE).id
    if model.body(model.site_bodyid[sid]).name != FINGERTIP_BODY:
        raise ConfigError("xarm7.xml", f"site {FINGERTIP_SITE!r} is not on body {FINGERTIP_BODY!r}")
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, model.site_quat[sid])
    return FINGERTIP_BODY, model.site_pos[sid].copy(), mat.reshape(3, 3)[:, 2].copy()


def actuator_ids(model: mujoco.MjModel, prefix: str = "") -> np.ndarray:
    """Ids of ``act1``..``act7`` in ``model``, in joint order.

    Args:
        model: A compiled model holding the robot (alone or attached into a scene).
        prefix: Name prefix the scene gave the robot when attaching it.

    Returns:
        Actuator ids, shape (7,) int.

    Raises:
        ConfigError: If an actuator is missing; the message lists the model's actuators.
    """
    ids = []
    for name in ACTUATOR_NAMES:
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, prefix + name)
        if i < 0:
            names = [model.actuator(k).name for k in range(model.nu)]
            raise ConfigError("actuator", f"no actuator named {prefix + name!r}", names)
        ids.append(i)
    return np.array(ids, dtype=int)


def _seven_positive(field: str, values: object) -> tuple[float, ...]:
    try:
        seq = list(values)  # type: ignore[call-overload]
    except TypeError:
        raise ConfigError(field, f"must be a sequence of {N_JOINTS} numbers") from None
    if len(seq) != N_JOINTS:
        raise ConfigError(field, f"must have {N_JOINTS} entries, got {len(seq)}")
    out = []
    for i, v in enumerate(seq):
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise ConfigError(f"{field}[{i}]", f"must be a finite number > 0, got {v!r}")
        check_positive(f"{field}[{i}]", float(v))
        out.append(float(v))
    return tuple(out)


@dataclass(frozen=True)
class ServoParams:
    """Gains of the seven joint position servos.

    Attributes:
        kp: Position gains, 7 values [N m/rad].
        kv: Velocity (damping) gains, 7 values [N m s/rad].
    """

    kp: tuple[float, ...]
    kv: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "kp", _seven_positive("kp", self.kp))
        object.__setattr__(self, "kv", _seven_positive("kv", self.kv))

    @classmethod
    def default(cls) -> ServoParams:
        """The gains written in ``assets/xarm7/xarm7.xml``.

        Raises:
            ConfigError: If an actuator in the XML is not an affine position servo
                (``biasprm[1] != -gainprm[0]``).
        """
        spec = load_robot_spec()
        kp, kv = [], []
        for name in ACTUATOR_NAMES:
            act = spec.actuator(name)
            if act is None:
                raise ConfigError("xarm7.xml", f"no actuator named {name!r}", ACTUATOR_NAMES)
            gain, bias = float(act.gainprm[0]), np.asarray(act.biasprm, dtype=float)
            if bias[0] != 0.0 or bias[1] != -gain:
                raise ConfigError(
                    f"xarm7.xml {name}",
                    f"not a position servo: gainprm[0]={gain}, biasprm[:3]={bias[:3].tolist()}",
                )
            kp.append(gain)
            kv.append(-float(bias[2]))
        return cls(tuple(kp), tuple(kv))

    def perturbed(self, rng: np.random.Generator, rel_sigma: float) -> ServoParams:
        """Gains for one trial, varied around these by independent log-normal factors.

            kp_i' = kp_i exp(rel_sigma z_i),  kv_i' = kv_i exp(rel_sigma w_i),
            z_i, w_i ~ N(0, 1) i.i.d.

        Args:
            rng: Random generator (the trial's seed stream).
            rel_sigma: Relative spread (standard deviation of the log of the factor) [-].

        Returns:
            New gains; positive for any draw.
        """
        check_nonnegative("rel_sigma", rel_sigma)
        z = rng.standard_normal((2, N_JOINTS))
        kp = np.asarray(self.kp) * np.exp(rel_sigma * z[0])
        kv = np.asarray(self.kv) * np.exp(rel_sigma * z[1])
        return ServoParams(tuple(kp.tolist()), tuple(kv.tolist()))


def apply_servo_params(
    model: mujoco.MjModel, ids: Sequence[int] | np.ndarray, params: ServoParams
) -> None:
    """Write servo gains into a compiled model, in place.

        gainprm[id, 0] = kp,  biasprm[id, 0:3] = (0, -kp, -kv)

    Args:
        model: Compiled model; modified in place.
        ids: The 7 actuator ids in joint order (see :func:`actuator_ids`).
        params: Gains to write.

    Raises:
        ConfigError: If ``ids`` does not hold 7 valid actuator ids.
    """
    ids = np.asarray(ids)
    if ids.shape != (N_JOINTS,) or not np.issubdtype(ids.dtype, np.integer):
        raise ConfigError("actuator ids", f"must be {N_JOINTS} integers, got shape {ids.shape}")
    if ids.min() < 0 or ids.max() >= model.nu:
        raise ConfigError("actuator ids", f"must lie in [0, {model.nu}), got {ids.tolist()}")
    kp, kv = np.asarray(params.kp), np.asarray(params.kv)
    model.actuator_gainprm[ids, 0] = kp
    model.actuator_biasprm[ids, 0] = 0.0
    model.actuator_biasprm[ids, 1] = -kp
    model.actuator_biasprm[ids, 2] = -kv

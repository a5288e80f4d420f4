"""Tests of learner/kinematics.py against MuJoCo's own kinematics and dynamics.

Two models: the fixture tests/data/chain7.xml (rotated, raised base; offset joint anchor and ref;
skew axis; jointless intermediate body; fingertip on a child body; springs) and the real robot
asset (skipped if absent).
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from flyknot.constants import XARM7_XML
from flyknot.errors import ConfigError
from flyknot.geometry import quat_to_matrix
from learner.kinematics import RobotModel

CHAIN7 = Path(__file__).parent / "data" / "chain7.xml"
FD_STEP = 1e-6
FD_RTOL = 1e-6  # |J - J_fd| <= FD_RTOL * max(1, max|J|)
MJ_TOL = 1e-10  # kinematics vs MuJoCo [m], [-], [m/s]
ID_TOL = 1e-8  # inverse dynamics vs MuJoCo, relative to max(1, max|tau|)


def _paths() -> list:
    return [
        pytest.param(CHAIN7, id="chain7"),
        pytest.param(
            XARM7_XML,
            id="xarm7",
            marks=pytest.mark.skipif(not XARM7_XML.is_file(), reason=f"{XARM7_XML} is absent"),
        ),
    ]


class Setup:
    """A RobotModel and the MuJoCo model it was read from."""

    def __init__(self, path: Path):
        self.robot = RobotModel.from_mjcf(path)
        self.model = mujoco.MjModel.from_xml_path(str(path))
        self.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        self.data = mujoco.MjData(self.model)
        self.site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "fingertip")
        self.base = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "link_base")
        jids = [
            mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, f"joint{i}")
            for i in range(1, 8)
        ]
        self.qadr = np.array([self.model.jnt_qposadr[j] for j in jids])
        self.dadr = np.array([self.model.jnt_dofadr[j] for j in jids])

    def random_states(self, m: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.default_rng(seed)
        lo, hi = self.robot.q_range.T
        q = rng.uniform(np.maximum(lo, -3.0), np.minimum(hi, 3.0), size=(m, 7))
        qd = rng.uniform(-3.14, 3.14, size=(m, 7))
        qdd = rng.uniform(-100.0, 100.0, size=(m, 7))
        return q, qd, qdd

    def mujoco_state(self, q, qd, qdd=None) -> mujoco.MjData:
        d = self.data
        d.qpos[:] = self.model.qpos0
        d.qvel[:] = 0.0
        d.qacc[:] = 0.0
        d.qpos[self.qadr] = q
        d.qvel[self.dadr] = qd
        if qdd is not None:
            d.qacc[self.dadr] = qdd
        return d


@pytest.fixture(scope="module", params=_paths())
def setup(request) -> Setup:
    return Setup(request.param)


def test_fk_and_velocity_match_mujoco(setup: Setup):
    q, qd, _ = setup.random_states(25, seed=1)
    p, R, v = setup.robot.tip_states(q, qd)
    for i in range(q.shape[0]):
        d = setup.mujoco_state(q[i], qd[i])
        mujoco.mj_kinematics(setup.model, d)
        mujoco.mj_comPos(setup.model, d)
        Rb, pb = d.xmat[setup.base].reshape(3, 3), d.xpos[setup.base]
        jacp = np.zeros((3, setup.model.nv))
        mujoco.mj_jacSite(setup.model, d, jacp, None, setup.site)
        np.testing.assert_allclose(p[i], Rb.T @ (d.site_xpos[setup.site] - pb), atol=MJ_TOL)
        np.testing.assert_allclose(R[i], Rb.T @ d.site_xmat[setup.site].reshape(3, 3), atol=MJ_TOL)
        np.testing.assert_allclose(v[i], Rb.T @ jacp @ d.qvel, atol=MJ_TOL)


def test_inverse_dynamics_matches_mj_inverse(setup: Setup):
    """Armature, damping and springs on: equals qfrc_inverse with constraints disabled."""
    q, qd, qdd = setup.random_states(25, seed=2)
    tau = setup.robot.torques(q, qd, qdd)
    for i in range(q.shape[0]):
        d = setup.mujoco_state(q[i], qd[i], qdd[i])
        mujoco.mj_inverse(setup.model, d)
        ref = d.qfrc_inverse[setup.dadr]
        assert np.max(np.abs(tau[i] - ref)) <= ID_TOL * max(1.0, np.max(np.abs(ref)))


def test_rigid_body_terms_match_mj_rne():
    """All passive/armature flags off: equals mj_rne (M qdd + bias) alone."""
    s = Setup(CHAIN7)
    robot = RobotModel.from_mjcf(
        CHAIN7, include_armature=False, include_damping=False, include_stiffness=False
    )
    assert not robot.armature.any() and not robot.damping.any() and not robot.stiffness.any()
    q, qd, qdd = s.random_states(15, seed=3)
    tau = robot.torques(q, qd, qdd)
    out = np.zeros(s.model.nv)
    for i in range(q.shape[0]):
        d = s.mujoco_state(q[i], qd[i], qdd[i])
        mujoco.mj_forward(s.model, d)
        d.qacc[s.dadr] = qdd[i]
        mujoco.mj_rne(s.model, d, 1, out)
        ref = out[s.dadr]
        assert np.max(np.abs(tau[i] - ref)) <= ID_TOL * max(1.0, np.max(np.abs(ref)))


def test_dtau_dqdd_is_mass_matrix_plus_armature(setup: Setup):
    q, qd, qdd = setup.random_states(5, seed=4)
    jac = setup.robot.torque_jacobians(q, qd, qdd)
    nv = setup.model.nv
    for i in range(q.shape[0]):
        d = setup.mujoco_state(q[i], qd[i])
        mujoco.mj_forward(setup.model, d)
        full = np.zeros((nv, nv))
        mujoco.mj_fullM(setup.model, d, full)  # MuJoCo's M includes armature
        ref = full[np.ix_(setup.dadr, setup.dadr)]
        np.testing.assert_allclose(jac.dtau_dqdd[i], ref, atol=1e-10)


def test_gravity_is_world_gravity_in_base_frame():
    s = Setup(CHAIN7)
    d = s.mujoco_state(np.zeros(7), np.zeros(7))
    mujoco.mj_kinematics(s.model, d)
    Rb = d.xmat[s.base].reshape(3, 3)
    np.testing.assert_allclose(s.robot.gravity, Rb.T @ np.array([0, 0, -9.81]), atol=1e-12)
    assert abs(s.robot.gravity[2]) < 9.81 - 0.1  # the fixture's base is tilted


def _central_fd(f, x: np.ndarray, h: float = FD_STEP) -> np.ndarray:
    """d f / d x by central differences; f maps (m, 7) -> (m, k); returns (m, k, 7)."""
    cols = []
    for j in range(x.shape[1]):
        e = np.zeros_like(x)
        e[:, j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def _assert_jac(J: np.ndarray, J_fd: np.ndarray) -> None:
    scale = max(1.0, float(np.max(np.abs(J))))
    assert np.max(np.abs(J - J_fd)) <= FD_RTOL * scale


def test_tip_jacobians_match_finite_differences(setup: Setup):
    robot = setup.robot
    q, qd, _ = setup.random_states(6, seed=5)
    jac = robot.tip_jacobians(q, qd)
    _assert_jac(jac.dp_dq, _central_fd(lambda x: robot.tip_states(x, qd).p, q))
    _assert_jac(jac.dd_dq, _central_fd(lambda x: robot.tip_states(x, qd).R[:, :, 2], q))
    _assert_jac(jac.dv_dq, _central_fd(lambda x: robot.tip_states(x, qd).v, q))
    _assert_jac(jac.dv_dqd, _central_fd(lambda x: robot.tip_states(q, x).v, qd))


def test_torque_jacobians_match_finite_differences(setup: Setup):
    robot = setup.robot
    q, qd, qdd = setup.random_states(6, seed=6)
    jac = robot.torque_jacobians(q, qd, qdd)
    _assert_jac(jac.dtau_dq, _central_fd(lambda x: robot.torques(x, qd, qdd), q))
    _assert_jac(jac.dtau_dqd, _central_fd(lambda x: robot.torques(q, x, qdd), qd))
    _assert_jac(jac.dtau_dqdd, _central_fd(lambda x: robot.torques(q, qd, x), qdd))


def test_torque_jvp_is_the_jacobians_along_a_direction(setup: Setup):
    """dtau = dtau/dq dq + dtau/dqd dqd + dtau/dqdd dqdd, and central differences along it."""
    robot = setup.robot
    q, qd, qdd = setup.random_states(5, seed=8)
    rng = np.random.default_rng(9)
    v = [rng.standard_normal(q.shape) for _ in range(3)]
    jac = robot.torque_jacobians(q, qd, qdd)
    want = sum(np.einsum("aij,aj->ai", J, d) for J, d in zip(jac, v, strict=True))
    got = robot.torque_jvp(q, qd, qdd, *v)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
    h = 1e-6
    plus = robot.torques(q + h * v[0], qd + h * v[1], qdd + h * v[2])
    minus = robot.torques(q - h * v[0], qd - h * v[1], qdd - h * v[2])
    np.testing.assert_allclose(got, (plus - minus) / (2 * h), rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match=r"dqd: expected shape \(5, 7\)"):
        robot.torque_jvp(q, qd, qdd, v[0], v[1][:2], v[2])


def test_casadi_functions_match_batches(setup: Setup):
    robot = setup.robot
    q, qd, qdd = setup.random_states(3, seed=7)
    states = robot.tip_states(q, qd)
    tjac = robot.tip_jacobians(q, qd)
    taus = robot.torques(q, qd, qdd)
    for i in range(3):
        p, R = robot.fk(q[i])
        np.testing.assert_allclose(np.asarray(p).ravel(), states.p[i], atol=1e-14)
        np.testing.assert_allclose(np.asarray(R), states.R[i], atol=1e-14)
        np.testing.assert_allclose(
            np.asarray(robot.d_tip(q[i])).ravel(), states.R[i][:, 2], atol=1e-14
        )
        np.testing.assert_allclose(
            np.asarray(robot.p_dot(q[i], qd[i])).ravel(), states.v[i], atol=1e-14
        )
        np.testing.assert_allclose(np.asarray(robot.tip_jac(q[i], qd[i])[1]), tjac.dd_dq[i])
        np.testing.assert_allclose(
            np.asarray(robot.inverse_dynamics(q[i], qd[i], qdd[i])).ravel(), taus[i], atol=1e-12
        )


_ROBOT = None


def _chain_robot() -> RobotModel:
    global _ROBOT
    if _ROBOT is None:
        _ROBOT = RobotModel.from_mjcf(CHAIN7)
    return _ROBOT


@settings(max_examples=30, deadline=None)
@given(
    q=st.integers(1, 6).flatmap(
        lambda m: arrays(float, (m, 7), elements=st.floats(-6.0, 6.0, allow_nan=False))
    ),
    scale=st.floats(-3.0, 3.0),
)
def test_tip_state_properties(q: np.ndarray, scale: float):
    """R is a rotation, d_tip a unit vector, and v linear in qd, for any batch size."""
    robot = _chain_robot()
    qd = np.linspace(-1.0, 1.0, 7)[None, :].repeat(q.shape[0], axis=0)
    p, R, v = robot.tip_states(q, qd)
    assert p.shape == (q.shape[0], 3) and R.shape == (q.shape[0], 3, 3)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(R[:, :, 2], axis=1), 1.0, atol=1e-12)
    v2 = robot.tip_states(q, scale * qd).v
    np.testing.assert_allclose(v2, scale * v, atol=1e-12)


def test_quat_to_mat_matches_mujoco():
    rng = np.random.default_rng(8)
    for _ in range(10):
        quat = rng.normal(size=4)
        quat /= np.linalg.norm(quat)
        ref = np.zeros(9)
        mujoco.mju_quat2Mat(ref, quat)
        np.testing.assert_allclose(quat_to_matrix(quat), ref.reshape(3, 3), atol=1e-15)


def test_bad_shapes_and_names_raise_with_exact_messages():
    robot = _chain_robot()
    with pytest.raises(ConfigError, match=r"^q: expected shape \(m, 7\), got \(3, 6\)$"):
        robot.tip_states(np.zeros((3, 6)), np.zeros((3, 7)))
    with pytest.raises(ConfigError, match=r"^qd: expected shape \(3, 7\), got \(2, 7\)$"):
        robot.torques(np.zeros((3, 7)), np.zeros((2, 7)), np.zeros((3, 7)))
    with pytest.raises(ConfigError, match=r"^qdd: contains non-finite values$"):
        robot.torque_jacobians(np.zeros((1, 7)), np.zeros((1, 7)), np.full((1, 7), np.nan))
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, site="tool")
    assert str(exc.value) == "site: site 'tool' not in the MJCF (valid choices: fingertip)"
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, joint_names=("joint1", "joint2", "joint9"))
    assert str(exc.value).startswith("joint_names: joint 'joint9' not in the MJCF (valid choices")
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, joint_names=tuple(f"joint{i}" for i in (1, 3, 2, 4, 5, 6, 7)))
    assert str(exc.value) == (
        "joint_names: must list the hinges from base to site in chain order; the chain has "
        "'joint1', 'joint2', 'joint3', 'joint4', 'joint5', 'joint6', 'joint7'"
    )
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, joint_names=tuple(f"joint{i}" for i in range(1, 7)))
    assert str(exc.value) == "joint_names: joint 'joint7' lies on the chain but is not listed"
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, base_body="nope")
    assert str(exc.value) == (
        "base_body: body 'nope' not in the MJCF (valid choices: world, pedestal, link_base, "
        "link1, link2, link3, link3_cover, link4, link5, link6, link7, tube)"
    )
    with pytest.raises(ConfigError) as exc:
        RobotModel.from_mjcf(CHAIN7, base_body="link7")
    assert str(exc.value) == "base_body: 'link7' is not fixed to the world"
    with pytest.raises(ConfigError, match=r"^path: MJCF file '.*nowhere\.xml' does not exist$"):
        RobotModel.from_mjcf(CHAIN7.parent / "nowhere.xml")

"""The xArm 7 MJCF against UFACTORY's published kinematics and inertials, and its servos."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from flyknot.constants import JOINT_NAMES
from flyknot.errors import ConfigError
from flyknot_sim import robot

# UFACTORY modified DH of the xArm 7 (ufactory_docs, "Kinematic and Dynamic Parameters of
# xArm 7"), Craig convention: row i = (alpha_{i-1} [rad], a_{i-1} [m], d_i [m]), theta_i = q_i.
DH = [
    (0.0, 0.0, 0.267),
    (-np.pi / 2, 0.0, 0.0),
    (np.pi / 2, 0.0, 0.293),
    (np.pi / 2, 0.0525, 0.0),
    (np.pi / 2, 0.0775, 0.3425),
    (np.pi / 2, 0.0, 0.0),
    (-np.pi / 2, 0.076, 0.097),
]
# xarm_ros xarm7_type7_HT_BR2.yaml ("xArm7 Model 3") and the link_base inertial of xarm7.urdf.xacro:
# mass [kg], com [m], (ixx, iyy, izz, ixy, ixz, iyz) [kg m^2]
INERTIALS = {
    "link_base": (
        0.88556,
        (-0.021131, -0.0016302, 0.056488),
        (0.0030595, 0.0037783, 0.0020125, 0.00012259, -0.00062705, 0.00027023),
    ),
    "link1": (
        2.382,
        (-0.0002, 0.02905, -0.01233),
        (0.0056905, 0.0049566, 0.003316654, -1.579e-05, 5.125e-06, -0.000873378),
    ),
    "link2": (
        1.869,
        (0.00022, -0.12856, 0.01735),
        (0.0095989, 0.00382472, 0.007565669, 1.541e-06, 5.56e-06, -0.00317156),
    ),
    "link3": (
        1.6383,
        (0.0466, -0.02463, -0.00768),
        (0.00310955, 0.00264483, 0.0026624, 0.00030837, -0.00058453, 0.000338893),
    ),
    "link4": (
        1.7269,
        (0.07047, -0.11575, 0.012),
        (0.005889, 0.00359703, 0.00543244, 0.00137112, 0.00088143, -0.001762155),
    ),
    "link5": (
        1.3203,
        (-0.00032, 0.01604, -0.026),
        (0.00534665, 0.0049779, 0.0013624, 1.5117e-05, -3.69e-07, -0.00022132),
    ),
    "link6": (
        1.325,
        (0.06469, 0.03278, 0.02141),
        (0.0014745, 0.0019037, 0.0023652, -0.000488, 0.0002953, 0.00014749),
    ),
    "link7": (0.17, (0.0, -0.00677, -0.01098), (9.3e-05, 5.87e-05, 0.000132, 0.0, 0.0, -3.6e-06)),
}
# Joint ranges of the arm itself (xarm7.urdf.xacro), not the paper's narrower table [rad].
RANGES = [
    (-6.28319, 6.28319),
    (-2.059, 2.0944),
    (-6.28319, 6.28319),
    (-0.19198, 3.927),
    (-6.28319, 6.28319),
    (-1.69297, 3.14159),
    (-6.28319, 6.28319),
]
HOME = np.array([0, -0.247, 0, 0.909, 0, 1.15644, 0])


def mdh_chain(q: np.ndarray) -> list[np.ndarray]:
    """Frames of links 1..7 in the base frame, each (4, 4) [m].

    T_i = T_{i-1} Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(q_i) Tz(d_i).
    """
    T = np.eye(4)
    out = []
    for (alpha, a, d), th in zip(DH, q, strict=True):
        ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(th), np.sin(th)
        step = np.array(
            [
                [ct, -st, 0.0, a],
                [st * ca, ct * ca, -sa, -sa * d],
                [st * sa, ct * sa, ca, ca * d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        T = T @ step
        out.append(T)
    return out


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return robot.load_robot_model()


def test_names_and_structure(model):
    assert model.nq == model.nv == model.nu == 7
    assert robot.JOINT_NAMES == JOINT_NAMES
    for j, name in enumerate(JOINT_NAMES):
        jnt = model.joint(name)
        assert jnt.type == mujoco.mjtJoint.mjJNT_HINGE
        np.testing.assert_array_equal(jnt.axis, [0, 0, 1])
        np.testing.assert_allclose(jnt.range, RANGES[j], atol=0)
        assert model.body(jnt.bodyid[0]).name == f"link{j + 1}"
        act = model.actuator(robot.ACTUATOR_NAMES[j])
        assert act.trnid[0] == jnt.id
    base = model.body(robot.BASE_BODY)
    assert base.parentid[0] == 0
    np.testing.assert_array_equal(base.pos, [0, 0, 0])
    np.testing.assert_array_equal(model.key("home").qpos, HOME)
    np.testing.assert_array_equal(model.key("home").ctrl, HOME)


def test_forward_kinematics_matches_modified_dh(model):
    data = mujoco.MjData(model)
    rng = np.random.default_rng(7)
    lo, hi = np.array(RANGES).T
    worst = 0.0
    for _ in range(100):
        q = rng.uniform(lo, hi)
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        for i, T in enumerate(mdh_chain(q)):
            b = data.body(f"link{i + 1}")
            worst = max(worst, np.abs(b.xpos - T[:3, 3]).max())
            worst = max(worst, np.abs(b.xmat.reshape(3, 3) - T[:3, :3]).max())
    assert worst < 1e-9


def test_flange_and_fingertip_at_zero(model):
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    flange = data.site(robot.FLANGE_SITE)
    np.testing.assert_allclose(flange.xpos, [0.206, 0.0, 0.1205], atol=1e-12)
    np.testing.assert_allclose(data.body("link7").xpos, flange.xpos, atol=1e-15)
    tip = data.site(robot.FINGERTIP_SITE)
    # the tube points down at q = 0; the rope leaves it along the fingertip's z axis
    np.testing.assert_allclose(tip.xmat.reshape(3, 3)[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(tip.xpos, [0.206, 0.0, 0.0205], atol=1e-12)


def test_fingertip_is_on_the_flange_axis(model):
    data = mujoco.MjData(model)
    rng = np.random.default_rng(3)
    for _ in range(20):
        data.qpos[:] = rng.uniform(-2, 2, 7)
        mujoco.mj_kinematics(model, data)
        R7 = data.body("link7").xmat.reshape(3, 3)
        tip = data.site(robot.FINGERTIP_SITE)
        np.testing.assert_allclose(tip.xmat.reshape(3, 3), R7, atol=1e-12)
        np.testing.assert_allclose(tip.xpos, data.body("link7").xpos + 0.1 * R7[:, 2], atol=1e-12)
    tube = model.geom("fingertip_tube")
    assert tube.type == mujoco.mjtGeom.mjGEOM_CYLINDER
    np.testing.assert_allclose(tube.size[:2], [0.01, 0.05])
    np.testing.assert_allclose(tube.pos, [0, 0, 0.05], atol=1e-15)


def test_masses_and_inertia_tensors_match_ufactory(model):
    for name, (mass, com, (ixx, iyy, izz, ixy, ixz, iyz)) in INERTIALS.items():
        b = model.body(name)
        assert b.mass[0] == pytest.approx(mass, abs=1e-12)
        np.testing.assert_allclose(b.ipos, com, atol=1e-12)
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, b.iquat)
        R = R.reshape(3, 3)
        inertia = R @ np.diag(b.inertia) @ R.T
        expected = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        np.testing.assert_allclose(inertia, expected, atol=1e-12)
    assert model.body_mass[1:].sum() == pytest.approx(0.88556 + 10.4315, abs=1e-9)


def test_links_do_not_collide_with_each_other_but_with_a_rope(model):
    data = mujoco.MjData(model)
    rng = np.random.default_rng(5)
    for _ in range(20):
        data.qpos[:] = rng.uniform(-2, 2, 7)
        mujoco.mj_forward(model, data)
        assert data.ncon == 0
    for g in range(model.ngeom):
        assert (model.geom_contype[g], model.geom_conaffinity[g]) == (2, 1)
    # a rope-like geom (contype 1, conaffinity 1 | 2) touching the forearm makes a contact
    spec = robot.load_robot_spec()
    ball = spec.worldbody.add_body(name="rope_bit", pos=[0.0, 0.0, 0.0])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02, 0, 0], contype=1, conaffinity=3)
    m2 = spec.compile()
    d2 = mujoco.MjData(m2)
    d2.qpos[7:10] = [0.206, 0.0, 0.06]  # next to the fingertip tube at q = 0
    d2.qpos[10] = 1.0
    mujoco.mj_forward(m2, d2)
    touched = {m2.geom(int(c.geom[i])).name for c in d2.contact[: d2.ncon] for i in (0, 1)}
    assert "fingertip_tube" in touched


def _simulate_joint1(model, ref, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Robot alone at dt = 1 ms from rest at home, joint 1 targeting ref(t) [rad].

    Step k holds ctrl = ref(t_k); returns t_{k+1} (n,) [s] and q1(t_{k+1}) (n,) [rad].
    """
    model.opt.timestep = 0.001
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    q1 = np.empty(n)
    for k in range(n):
        data.ctrl[:] = HOME
        data.ctrl[0] = ref(k * 1e-3)
        mujoco.mj_step(model, data)
        q1[k] = data.qpos[0]
    return np.arange(1, n + 1) * 1e-3, q1


def trapezoid(t):
    """0.9 rad move: 100 rad/s^2 for 0.03 s, 3 rad/s for 0.27 s, -100 rad/s^2 for 0.03 s [rad]."""
    t = np.clip(t, 0.0, 0.33)
    if t < 0.03:
        return 50.0 * t**2
    if t < 0.30:
        return 0.045 + 3.0 * (t - 0.03)
    return 0.9 - 50.0 * (0.33 - t) ** 2


def quintic(t):
    """Smooth 0.4 rad step in 0.25 s (peak 3 rad/s, 37 rad/s^2) [rad]."""
    x = min(max(t / 0.25, 0.0), 1.0)
    return 0.4 * (10 * x**3 - 15 * x**4 + 6 * x**5)


def test_servo_lags_a_3_rad_per_s_ramp_by_a_few_hundredths():
    model = robot.load_robot_model()
    t, q1 = _simulate_joint1(model, trapezoid, 600)
    lag = np.array([trapezoid(s) for s in t]) - q1
    cruise = (t > 0.1) & (t < 0.3)
    # steady lag at constant speed: ((kv + damping) qd + frictionloss) / kp
    #   = ((50 + 10) * 3 + 1) / 8000 = 0.0226 rad (+ the 1 ms control hold, ~v dt / 2)
    np.testing.assert_allclose(lag[cruise], 0.0226, atol=0.002)
    assert 0.02 < np.abs(lag).max() < 0.04
    assert abs(lag[-1]) < 1e-3


def test_servo_overshoots_a_smooth_step_a_little():
    model = robot.load_robot_model()
    t, q1 = _simulate_joint1(model, quintic, 800)
    lag = np.array([quintic(s) for s in t]) - q1
    overshoot = q1.max() - 0.4
    assert 2e-4 < overshoot < 5e-3
    assert 0.01 < np.abs(lag).max() < 0.04
    assert abs(q1[-1] - 0.4) < 5e-4


def test_servo_params_default_reads_the_xml(model):
    p = robot.ServoParams.default()
    ids = robot.actuator_ids(model)
    np.testing.assert_array_equal(p.kp, model.actuator_gainprm[ids, 0])
    np.testing.assert_array_equal(p.kv, -model.actuator_biasprm[ids, 2])
    np.testing.assert_array_equal(model.actuator_biasprm[ids, 1], -model.actuator_gainprm[ids, 0])


def test_apply_servo_params_sets_the_pd_law():
    model = robot.load_robot_model()
    ids = robot.actuator_ids(model)
    p = robot.ServoParams(kp=(1000, 900, 800, 700, 600, 500, 400), kv=(1, 2, 3, 4, 5, 6, 7))
    robot.apply_servo_params(model, ids, p)
    data = mujoco.MjData(model)
    data.qpos[:] = np.linspace(-0.3, 0.3, 7)
    data.qvel[:] = np.linspace(0.01, 0.07, 7)
    data.ctrl[:] = 0.02
    mujoco.mj_forward(model, data)
    pd = np.array(p.kp) * (0.02 - data.qpos) - np.array(p.kv) * data.qvel
    # the servos saturate at the paper's torque limits (forcerange)
    limit = np.array([130, 130, 40, 40, 40, 20, 20])
    np.testing.assert_allclose(model.actuator_forcerange[ids, 1], limit)
    np.testing.assert_allclose(data.actuator_force, np.clip(pd, -limit, limit), rtol=1e-12)
    assert 0 < (np.abs(pd) > limit).sum() < 7


def test_perturbed_is_lognormal_and_reproducible():
    p = robot.ServoParams.default()
    assert p.perturbed(np.random.default_rng(0), 0.0) == p
    a = p.perturbed(np.random.default_rng(1), 0.1)
    assert a == p.perturbed(np.random.default_rng(1), 0.1)
    assert a != p
    rng = np.random.default_rng(2)
    logs = np.array([np.log(np.array(p.perturbed(rng, 0.1).kp) / p.kp) for _ in range(400)])
    assert abs(logs.mean()) < 0.01  # 2800 draws: standard error 0.0019
    assert logs.std() == pytest.approx(0.1, rel=0.05)


@pytest.mark.parametrize(
    ("kp", "message"),
    [
        ((1.0,) * 6, "kp: must have 7 entries, got 6"),
        ((1, 1, 1, 0, 1, 1, 1), "kp[3]: must be a finite number > 0, got 0.0"),
        ((1, 1, 1, 1, 1, 1, float("nan")), "kp[6]: must be a finite number > 0, got nan"),
        ((1, 1, "a", 1, 1, 1, 1), "kp[2]: must be a finite number > 0, got 'a'"),
        (5.0, "kp: must be a sequence of 7 numbers"),
    ],
)
def test_servo_params_validation(kp, message):
    with pytest.raises(ConfigError) as err:
        robot.ServoParams(kp=kp, kv=(1.0,) * 7)
    assert str(err.value) == message


def test_servo_helpers_validation(model):
    with pytest.raises(ConfigError) as err:
        robot.ServoParams.default().perturbed(np.random.default_rng(0), -0.1)
    assert str(err.value) == "rel_sigma: must be a finite number >= 0, got -0.1"
    with pytest.raises(ConfigError) as err:
        robot.actuator_ids(model, prefix="arm/")
    assert str(err.value).startswith("actuator: no actuator named 'arm/act1' (valid choices: act1,")
    with pytest.raises(ConfigError) as err:
        robot.apply_servo_params(model, [0, 1, 2, 3, 4, 5, 7], robot.ServoParams.default())
    assert str(err.value) == "actuator ids: must lie in [0, 7), got [0, 1, 2, 3, 4, 5, 7]"

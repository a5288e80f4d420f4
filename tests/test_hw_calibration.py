"""Robot base pose in the mocap frame: the fit (flyknot_hw.mocap.calibration), and the driven
calibration (flyknot_hw.calibrate_plan, flyknot_hw.calibrate_driver, ``flyknot calibrate``)
against the fake controller on loopback (127.x.y.z only) through the real, unmodified SDK."""

from __future__ import annotations

import json
import os
import signal
import time
import tomllib

import numpy as np
import pytest
import xarm  # noqa: F401 - the test extra installs it
from fakes import lab_doc
from fakes.fake_xarm import HOME
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from flyknot.constants import ASSETS_DIR
from flyknot.errors import ConfigError, HardwareError
from flyknot.geometry import quat_to_matrix
from flyknot_app import cli
from flyknot_app.hardware import LearnerKinematics, calibrate_arm
from flyknot_hw.calibrate_plan import default_poses, planned_move
from flyknot_hw.config import CalibrationConfig, parse_lab_config
from flyknot_hw.mocap.calibration import (
    apply_pose,
    calibrate_base,
    find_outlier,
    fit_conditioning,
    leave_one_out,
    rigid_fit,
)
from flyknot_hw.preflight import PreflightError
from flyknot_sim.commands import HOME_Q

LAB_EXAMPLE = ASSETS_DIR / "lab_example.toml"
KIN = LearnerKinematics()

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


def _pose(quat, t) -> np.ndarray:
    q = np.asarray(quat, dtype=float)
    return np.concatenate([np.asarray(t, dtype=float), q / np.linalg.norm(q)])


def _same_pose(a: np.ndarray, b: np.ndarray, tol: float) -> None:
    np.testing.assert_allclose(a[:3], b[:3], atol=tol)
    np.testing.assert_allclose(quat_to_matrix(a[3:]), quat_to_matrix(b[3:]), atol=tol)


def _workspace_points(rng: np.random.Generator, k: int) -> np.ndarray:
    """Fingertip positions an xArm 7 reaches: a box in front of the base [m]."""
    return rng.uniform([0.2, -0.4, 0.1], [0.7, 0.4, 0.8], size=(k, 3))


def test_recovers_a_known_pose_exactly():
    rng = np.random.default_rng(0)
    truth = _pose([0.9, 0.1, -0.2, 0.3], [1.5, -0.4, 0.9])
    a = _workspace_points(rng, 8)
    pose, res = calibrate_base(a, apply_pose(truth, a))
    _same_pose(pose, truth, 1e-10)
    assert pose[3] >= 0 and abs(np.linalg.norm(pose[3:]) - 1) < 1e-12
    assert res.rms_m < 1e-10 and res.max_m < 1e-10 and res.n_poses == 8
    assert res.per_pose.shape == (8,)


@settings(max_examples=60)
@given(
    quat=arrays(float, 4, elements=finite),
    t=arrays(float, 3, elements=st.floats(-3, 3)),
    pts=arrays(float, st.tuples(st.integers(3, 12), st.just(3)), elements=finite),
)
def test_random_rigid_transforms_are_recovered(quat, t, pts):
    assume(np.linalg.norm(quat) > 0.1)
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    assume(sv[1] / np.sqrt(len(pts)) > 0.05)  # well away from collinear
    truth = _pose(quat, t)
    pose, res = calibrate_base(pts, apply_pose(truth, pts))
    _same_pose(pose, truth, 1e-8)
    assert res.rms_m < 1e-9


@settings(max_examples=30)
@given(seed=st.integers(0, 10_000))
def test_noise_gives_a_residual_of_the_noise_level(seed):
    rng = np.random.default_rng(seed)
    truth = _pose(rng.normal(size=4), rng.uniform(-2, 2, 3))
    a = _workspace_points(rng, 20)
    noise = 0.001
    b = apply_pose(truth, a) + rng.normal(0, noise, a.shape)
    pose, res = calibrate_base(a, b)
    # Residual of a 6-parameter fit to 60 coordinates: sqrt(3 (1 - 6/60)) sigma ~ 1.6 mm.
    assert 0.5 * noise < res.rms_m < 2.5 * noise
    assert np.linalg.norm(pose[:3] - truth[:3]) < 3 * noise


def test_robust_refinement_discounts_a_misread_pose():
    rng = np.random.default_rng(3)
    truth = _pose([1.0, 0.0, 0.0, 0.4], [0.3, 0.2, 1.0])
    a = _workspace_points(rng, 10)
    b = apply_pose(truth, a) + rng.normal(0, 0.0005, a.shape)
    b[4] += [0.05, 0.0, 0.0]  # the marker of pose 4 was misread by 5 cm
    plain, _ = calibrate_base(a, b)
    robust, res_robust = calibrate_base(a, b, robust_m=0.002)
    err_plain = np.linalg.norm(plain[:3] - truth[:3])
    err_robust = np.linalg.norm(robust[:3] - truth[:3])
    assert err_robust < 0.002 < err_plain
    assert int(np.argmax(res_robust.per_pose)) == 4 and res_robust.max_m > 0.045


def test_rigid_fit_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(6, 3))
    b = a * np.array([1.0, 1.0, -1.0])  # a mirror image: no rotation maps a onto it
    R, _ = rigid_fit(a, b)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize(
    ("a", "b", "field", "text"),
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "fk_points", "at least 3"),
        (
            np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0.0]]),
            np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0.0]]),
            "fk_points",
            "collinear",
        ),
        (np.zeros((4, 3)), np.zeros((5, 3)), "mocap_points", "shape"),
        (np.zeros((4, 2)), np.zeros((4, 2)), "fk_points", "(k, 3)"),
        (np.full((4, 3), np.nan), np.zeros((4, 3)), "fk_points", "finite"),
    ],
)
def test_bad_inputs_name_the_field(a, b, field, text):
    with pytest.raises(ConfigError) as e:
        calibrate_base(a, b)
    assert e.value.field == field and text in str(e.value)


def test_collinear_mocap_points_are_refused_too():
    a = _workspace_points(np.random.default_rng(2), 5)
    b = np.outer(np.arange(5.0), [0.1, 0.0, 0.0])
    with pytest.raises(ConfigError, match="collinear") as e:
        calibrate_base(a, b)
    assert e.value.field == "mocap_points"


def test_bad_robust_scale_and_pose_are_refused():
    a = _workspace_points(np.random.default_rng(4), 5)
    with pytest.raises(ConfigError, match="robust_m"):
        calibrate_base(a, a, robust_m=0.0)
    with pytest.raises(ConfigError, match="base_pose"):
        apply_pose(np.zeros(6), a)


# --- conditioning and outliers ---------------------------------------------------------------
def test_conditioning_predicts_the_scatter_of_the_fit():
    """The predicted standard deviations per mm of noise match a Monte Carlo of the fit."""
    rng = np.random.default_rng(5)
    a = _workspace_points(rng, 8)
    truth = _pose([0.8, -0.1, 0.3, 0.5], [1.2, 0.4, 0.7])
    cond = fit_conditioning(a)
    sigma = 1e-3
    pos, ang = [], []
    for _ in range(400):
        pose, _ = calibrate_base(a, apply_pose(truth, a) + rng.normal(0, sigma, a.shape))
        pos.append(pose[:3] - truth[:3])
        d = quat_to_matrix(pose[3:]) @ quat_to_matrix(truth[3:]).T
        ang.append(np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]]) / 2)
    # the largest std over the principal directions, measured, per 1 mm of noise (sigma)
    pos_std = np.sqrt(np.linalg.eigvalsh(np.cov(np.array(pos).T))[-1]) / sigma  # mm per mm
    ang_std = np.degrees(np.sqrt(np.linalg.eigvalsh(np.cov(np.array(ang).T))[-1]))  # sigma: 1 mm
    assert pos_std == pytest.approx(cond.position_mm_per_mm, rel=0.15)
    assert ang_std == pytest.approx(cond.rotation_deg_per_mm, rel=0.15)
    assert 1.0 <= cond.condition < 5.0 and cond.spread_m[0] >= cond.spread_m[2] > 0
    line = np.outer(np.arange(5.0), [0.1, 0.05, 0.0])
    assert fit_conditioning(line).condition == np.inf


def test_leave_one_out_finds_the_misread_pose():
    rng = np.random.default_rng(6)
    a = _workspace_points(rng, 8)
    truth = _pose([1.0, 0.2, 0.0, -0.3], [0.5, 1.0, 0.9])
    b = apply_pose(truth, a) + rng.normal(0, 2e-4, a.shape)
    loo = leave_one_out(a, b)
    assert loo.max() < 1.5e-3 and find_outlier(loo, 5e-3) is None
    b[5] += [0.0, 0.012, 0.0]  # a 12 mm misread
    loo = leave_one_out(a, b)
    assert find_outlier(loo, 5e-3) == 5 and loo[5] == pytest.approx(0.012, abs=1.5e-3)
    # a fit whose every pose is off by ~6 mm (poor kinematics) has no single outlier
    assert find_outlier(np.full(8, 6e-3) + rng.normal(0, 1e-4, 8), 5e-3) is None


# --- the lab file's [calibration] -------------------------------------------------------------
def test_calibration_table_of_the_lab_file():
    from fakes.fake_xarm import HOME

    doc = tomllib.loads(LAB_EXAMPLE.read_text())
    cfg = parse_lab_config(doc)
    np.testing.assert_allclose(cfg.calibration.start, HOME)
    assert cfg.calibration.min_poses == 6 and cfg.calibration.window_s > 0
    doc["calibration"] = {"start": list(HOME + 0.1), "min_poses": 5, "outlier_mm": 2}
    cal = parse_lab_config(doc).calibration
    assert cal == CalibrationConfig(start=HOME + 0.1, min_poses=5, outlier_mm=2.0)
    for table, field in (
        ({"min_poses": 3}, "calibration.min_poses"),
        ({"start": [0.0] * 6}, "calibration.start"),
        ({"window_s": 0}, "calibration.window_s"),
        ({"dwell": 1.0}, "calibration.dwell"),
    ):
        doc["calibration"] = table
        with pytest.raises(ConfigError) as e:
            parse_lab_config(doc)
        assert e.value.field == field


# --- the plan ---------------------------------------------------------------------------------
def test_planned_move_is_the_controllers_trapezoid():
    a, b = np.zeros(7), np.array([0.6, -0.3, 0, 0, 0, 0.1, 0])
    cmd = planned_move(a, b, speed=0.35, acc=1.0, rate_hz=250.0)
    np.testing.assert_allclose(cmd.q[0], a)
    np.testing.assert_allclose(cmd.q[-2:], [b, b])
    assert cmd.duration == pytest.approx(0.6 / 0.35 + 0.35 / 1.0, abs=0.01)
    qd = np.diff(cmd.q, axis=0) * 250.0
    assert np.abs(qd[:, 0]).max() == pytest.approx(0.35, rel=1e-3)
    assert np.abs(np.diff(qd[:, 0]) * 250.0).max() <= 1.0 + 1e-6
    short = planned_move(a, a + 0.01, speed=0.35, acc=1.0, rate_hz=250.0)  # a triangle
    assert short.duration == pytest.approx(2 * np.sqrt(0.01 / 1.0), abs=0.005)
    assert planned_move(a, a, 0.35, 1.0, 250.0).n == 2


def test_default_poses_pass_the_preflight_of_the_example_lab(capsys):
    """The dry run of the example lab: 8 poses, 9 moves, all preflighted, no robot asked."""
    assert cli.main(["calibrate", "--cell", str(LAB_EXAMPLE), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "8 poses, 9 moves" in out and "published xArm 7 limits" in out
    assert "condition 1.55" in out and "spread 208 / 149 / 71 mm" in out
    assert "nothing connected, nothing moved" in out


# --- driven, against the fake controller on loopback ---------------------------------------------
MOTION = {11, 12, 19, 23, 29}  # motion enable, set state, set mode, joint move, servo_j
FAST = {"window_s": 0.3, "still_s": 0.2}


@pytest.fixture
def make_fake(monkeypatch):
    """Start fakes on loopback (127.x.y.z); patch the SDK's command port only when the fake
    could not bind 502."""
    from fakes import fake_factory
    from fakes.fake_calibration import MoveFaultXArm

    yield from fake_factory(monkeypatch, MoveFaultXArm)


def _toml(doc: dict) -> str:
    """A lab-file mapping as TOML text (tables of numbers, strings and lists)."""

    def value(v) -> str:
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple, np.ndarray)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(float(v)) if isinstance(v, float) else str(v)

    out = []
    for name, table in doc.items():
        out.append(f"[{name}]")
        nested = {k: v for k, v in table.items() if isinstance(v, dict)}
        out += [f"{k} = {value(v)}" for k, v in table.items() if k not in nested and v is not None]
        for k, sub in nested.items():
            out.append(f"[{name}.{k}]")
            out += [f"{kk} = {value(vv)}" for kk, vv in sub.items()]
    return "\n".join(out) + "\n"


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return np.concatenate([rng.uniform(-2, 2, 3), q / np.linalg.norm(q) * np.sign(q[0])])


@pytest.mark.slow
def test_driven_calibration_recovers_the_base_pose(make_fake, tmp_path, capsys, monkeypatch):
    """``flyknot calibrate --cell LAB --out F`` against the fake controller and a live system
    seeing the fingertip in a random frame (0.3 mm noise per frame, 5 % of the frames without
    the body, pose 4 hidden): the base pose comes back within 1 mm / 0.1 deg."""
    from fakes.fake_calibration import FakeMocapSystem

    from flyknot_hw.calibrate_plan import default_poses
    from flyknot_hw.mocap import live

    fake = make_fake()
    truth = _random_pose(np.random.default_rng(11))
    system = FakeMocapSystem(fake, truth, noise_m=3e-4, dropout=0.05, seed=1)
    poses = default_poses(HOME_Q)
    system.hide(poses[3])
    monkeypatch.setattr(live, "import_motioncapture", system.module)
    mocap = {"kind": "live", "system": "vicon", "address": "192.168.1.20:801", "file": None}
    doc = lab_doc(fake, mocap=mocap, calibration=FAST)
    lab = tmp_path / "lab.toml"
    lab.write_text(_toml(doc))
    out = tmp_path / "base.toml"
    t = time.perf_counter()
    assert cli.main(["calibrate", "--cell", str(lab), "--out", str(out)]) == 0, capsys.readouterr()
    took = time.perf_counter() - t
    text = capsys.readouterr().out
    pose = np.array(tomllib.loads(out.read_text())["base"]["pose"])
    err_mm = 1e3 * np.linalg.norm(pose[:3] - truth[:3])
    d = quat_to_matrix(pose[3:]) @ quat_to_matrix(truth[3:]).T
    err_deg = np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1)))
    print(f"\ndriven calibration on the fake: {err_mm:.3f} mm, {err_deg:.4f} deg, {took:.1f} s")
    assert err_mm < 1.0 and err_deg < 0.1
    assert "   4  not used: no 'fingertip' body" in text, text
    assert "fit of 7 poses: residual rms" in text and out.read_text() in text
    assert system.connects == [("vicon", {"hostname": "192.168.1.20:801"})]
    # the tour: 8 poses and back to where the arm stood, all in position mode
    goals = [v for _, name, v in fake.events if name == "move_joint"]
    assert len(goals) == 9 and not fake.servo and fake.error_code == 0
    np.testing.assert_allclose(goals[:8], poses, atol=1e-6)
    np.testing.assert_allclose(goals[8], HOME, atol=5e-3)
    np.testing.assert_allclose(fake.q, HOME, atol=6e-3)


@pytest.mark.parametrize(
    ("code", "warn", "label"),
    [
        (31, False, "C31 Collision Caused Abnormal Current"),
        (11, True, "W11 Current controller cache is full"),
    ],
)
def test_a_fault_during_a_move_stops_the_calibration(make_fake, code, warn, label):
    """An error (the fake stops the arm itself) or a warning (it does not) during the move to
    pose 2: the calibration stops the arm (state 4) and raises with the code."""
    from fakes import StandInMocap

    fake = make_fake(arm="exact")
    fake.inject_during_move(code, move=2, after_s=0.15, warn=warn)
    mocap = StandInMocap(fake)
    with pytest.raises(HardwareError) as e:
        calibrate_arm(
            parse_lab_config(lab_doc(fake, calibration=FAST)), mocap=mocap, kinematics=KIN
        )
    assert f"the controller reports {label} during the move to calibration pose 2" in str(e.value)
    raised = [t for t, name, v in fake.events if name in ("error", "warn") and v == code]
    stops = [t for t, name, v in fake.events if name == "set_state" and v == 4]
    assert raised and stops and stops[-1] > raised[0] and fake.state == 4
    assert fake.moves == 2 and mocap.started == mocap.stopped == 1  # pose 1 measured
    assert np.max(np.abs(fake.q - default_poses(HOME_Q)[1])) > 0.05  # pose 2 not reached


def test_ctrl_c_during_a_move_stops_the_arm(make_fake):
    from fakes import StandInMocap

    fake = make_fake(arm="exact")

    def emit(line: str) -> None:
        if line.startswith("moving to calibration pose 2"):
            os.kill(os.getpid(), signal.SIGINT)  # caught by the calibration's latch

    with pytest.raises(KeyboardInterrupt):
        calibrate_arm(
            parse_lab_config(lab_doc(fake, calibration=FAST)),
            mocap=StandInMocap(fake), kinematics=KIN, emit=emit,
        )  # fmt: skip
    moves = [t for t, name, _ in fake.events if name == "move_joint"]
    assert fake.state == 4 and fake.events[-1][1:] == ("set_state", 4)
    assert len(moves) == 2 and fake.events[-1][0] > moves[-1]  # stopped during the move
    assert np.max(np.abs(fake.q - default_poses(HOME_Q)[1])) > 0.05  # pose 2 not reached


@pytest.mark.parametrize("what", ["pose", "workspace", "error", "too_few"])
def test_refused_before_any_motion(make_fake, tmp_path, what):
    from fakes import StandInMocap

    fake = make_fake(arm="exact", initial_error=31 if what == "error" else 0)
    poses = default_poses(HOME_Q)
    sections: dict = {"calibration": FAST}
    if what == "pose":
        poses[2, 1] = 2.1  # past joint 2's range
    if what == "workspace":
        sections["safety"] = {"workspace": {"min": [-1, -1, 0.2], "max": [1, 1, 0.8]}}
    if what == "too_few":
        poses = poses[:5]
    mocap = StandInMocap(fake)
    with pytest.raises((PreflightError, HardwareError, ConfigError)) as e:
        calibrate_arm(
            parse_lab_config(lab_doc(fake, **sections)), poses=poses, mocap=mocap, kinematics=KIN
        )
    assert {
        "pose": "calibration pose 3: joint 2 position 2.1 rad exceeds",
        "workspace": "the move to calibration pose 2 (from pose 1): fingertip z = 0.8",
        "error": "the controller reports C31 Collision Caused Abnormal Current before the "
        "calibration",
        "too_few": "poses: needs at least calibration.min_poses = 6 poses, got 5",
    }[what] in str(e.value)
    assert not MOTION & set(fake.registers()), fake.registers()
    assert mocap.started == 0


def test_the_dry_run_connects_to_nothing(make_fake, tmp_path, capsys):
    fake = make_fake(arm="exact")
    lab = tmp_path / "lab.toml"
    lab.write_text(_toml(lab_doc(fake, calibration=FAST)))
    poses = tmp_path / "poses.csv"
    np.savetxt(poses, default_poses(HOME_Q)[:6], delimiter=",", header="q1,q2,q3,q4,q5,q6,q7")
    assert cli.main(["calibrate", "--cell", str(lab), "--poses", str(poses), "--dry-run"]) == 0
    assert "6 poses, 7 moves" in capsys.readouterr().out
    time.sleep(0.2)
    assert not fake.requests and not fake._conns
    bad = default_poses(HOME_Q)[:6]
    bad[4, 3] = -0.5  # joint 4 below its range
    np.savetxt(poses, bad, delimiter=",")
    assert cli.main(["calibrate", "--cell", str(lab), "--poses", str(poses), "--dry-run"]) == 2
    assert "calibration pose 5: joint 4 position -0.5 rad is below" in capsys.readouterr().err
    assert not fake.requests and not fake._conns


# --- the fit's refusals -------------------------------------------------------------------------
def _measurements(rng, truth, poses, kin):
    from flyknot_hw.calibrate_driver import PoseMeasurement

    tips = apply_pose(truth, kin.positions(poses)) + rng.normal(0, 5e-5, (len(poses), 3))
    return [
        PoseMeasurement(i + 1, q, q, tip, 60, 58, 3e-4)
        for i, (q, tip) in enumerate(zip(poses, tips, strict=True))
    ]


def test_an_outlier_pose_is_refused_by_name():
    from dataclasses import replace

    from flyknot_hw.calibrate_driver import CalibrationError, fit_measurements

    rng = np.random.default_rng(8)
    truth = _random_pose(rng)
    poses = default_poses(HOME_Q)
    ms = _measurements(rng, truth, poses, KIN)
    cal = CalibrationConfig()
    good = fit_measurements(ms, KIN, cal)
    assert good.used == tuple(range(1, 9)) and good.residual.rms_m < 1e-4
    assert good.toml().startswith("[base]\n# flyknot calibrate: 8 poses, residual rms 0.0")
    ms[6] = replace(ms[6], tip_mocap=ms[6].tip_mocap + np.array([0.0, 0.0, 0.02]))
    with pytest.raises(
        CalibrationError, match=r"^calibration pose 7 is an outlier: its fingertip"
    ) as e:
        fit_measurements(ms, KIN, cal)
    assert e.value.pose == 7 and e.value.result.residual.max_m > 0.01
    report = "\n".join(e.value.result.report())
    assert "   7  " in report and "leave-one-out" in report


def test_too_few_poses_with_markers_are_refused():
    from dataclasses import replace

    from flyknot_hw.calibrate_driver import CalibrationError, fit_measurements

    rng = np.random.default_rng(9)
    ms = _measurements(rng, _random_pose(rng), default_poses(HOME_Q), KIN)
    for i in (1, 4, 6):
        ms[i] = replace(
            ms[i], tip_mocap=np.full(3, np.nan), problem="fingertip seen in 2 of 60 frames"
        )
    with pytest.raises(CalibrationError, match=r"only 5 of 8 calibration poses had usable") as e:
        fit_measurements(ms, KIN, CalibrationConfig())
    assert "pose 2: fingertip seen in 2 of 60 frames; pose 5: " in str(e.value)
    assert e.value.pose is None and e.value.result is None
    assert fit_measurements(ms, KIN, CalibrationConfig(min_poses=5)).used == (1, 3, 4, 6, 8)


def test_the_window_drops_frames_without_the_fingertip():
    from flyknot_hw.calibrate_driver import _tip_of
    from flyknot_hw.mocap import BodyTrack, RawStream

    rng = np.random.default_rng(10)
    p = np.array([0.3, 0.2, 1.1]) + rng.normal(0, 3e-4, (60, 3))
    p[::7] = np.nan
    s = RawStream(
        np.arange(60) / 200, np.zeros((60, 0, 3)), {"fingertip": BodyTrack.positions_only(p)}
    )
    tip, n, used, rms, problem = _tip_of(s)
    assert problem is None and (n, used) == (60, 51)
    np.testing.assert_allclose(tip, [0.3, 0.2, 1.1], atol=2e-4)
    assert 3e-4 < rms < 7e-4
    p[:40] = np.nan
    s = RawStream(
        np.arange(60) / 200, np.zeros((60, 0, 3)), {"fingertip": BodyTrack.positions_only(p)}
    )
    assert _tip_of(s)[4] == "fingertip seen in 17 of 60 frames"
    s = RawStream(np.arange(60) / 200, np.zeros((60, 0, 3)), {"wand": BodyTrack.positions_only(p)})
    assert _tip_of(s)[4] == "no 'fingertip' body (bodies: wand)"

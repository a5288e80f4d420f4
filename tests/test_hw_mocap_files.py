"""C3D and CSV recordings of simulated trials: labelling and clock alignment recover the truth.

One simulated trial (the showcase swing, noiseless markers) plays the real lab's capture: its
markers are moved into a Y-up mocap frame, their labels are swapped between neighbours over
stretches of frames (as capture software does), frames drop out, ghost points appear, the
hand carries a 3-marker cluster, and the capture clock runs 0.8 s plus the simulated start
delay ahead of the robot's. Written as C3D (millimetres) or CSV, read back, labelled and
aligned, it must give:

* labels correct on >= 99 % of the tracked marker-frames (all of them, in fact), with the
  markers tracked in >= 97 % of the frames where they were visible;
* the clock offset within 1 ms and a fingertip residual below 1 mm (noiseless data);
  with 1 mm noise, within 1 ms and below 3 mm;
* on rope marker 0 instead of a fingertip cluster (the rope lags the hand): within 15 ms
  (the residual then holds marker 0's 0.10 m distance from the fingertip).
"""

from __future__ import annotations

import os
import threading
import time
from datetime import datetime

import mujoco
import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from flyknot.errors import HardwareError, RecordError
from flyknot.geometry import matrix_to_quat, quat_to_matrix
from flyknot_hw.mocap import (
    RawStream,
    RecordedFileSource,
    apply_pose,
    calibrate_base,
    label_rope_markers,
    match_recording,
    read_c3d,
    read_csv,
    trial_markers,
    write_c3d,
    write_csv,
)
from flyknot_sim import robot
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab, VariationParams
from flyknot_sim.mocap import MocapParams

RATE = 200.0
EXTRA_S = 0.8  # capture started this long (plus the simulated start delay) before the robot
# Mocap frame: Y up (as OptiTrack and Qualisys often are), origin off the lab's.
MOCAP_FROM_WORLD = np.concatenate(
    [[0.3, 1.0, -0.2], matrix_to_quat(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]))]
)
GRAVITY_MOCAP = quat_to_matrix(MOCAP_FROM_WORLD[3:]) @ np.array([0.0, 0.0, -1.0])
CLUSTER = np.array([[0.015, 0.0, 0.0], [-0.0075, 0.013, 0.0], [-0.0075, -0.013, 0.0]])


class MujocoFk:
    """Fingertip forward kinematics of the simulated xArm (the application's job on hw)."""

    def __init__(self):
        self.model = robot.load_robot_model()
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site(robot.FINGERTIP_SITE).id
        self.qadr = [self.model.jnt_qposadr[self.model.joint(n).id] for n in robot.JOINT_NAMES]

    def __call__(self, q: np.ndarray) -> np.ndarray:
        out = np.empty((len(q), 3))
        for i, qi in enumerate(np.asarray(q)):
            self.data.qpos[self.qadr] = qi
            mujoco.mj_kinematics(self.model, self.data)
            out[i] = self.data.site_xpos[self.site]
        return out


@pytest.fixture(scope="module")
def trial():
    lab = SimLab(
        LabParams(
            seed=3,
            settle_s=0.4,
            mocap=MocapParams(noise_std=0.0, loss_mode="none"),
            variation=VariationParams(start_delay_max_s=0.005),
        )
    )
    rec = lab.run(swing_command())
    fk = MujocoFk()
    delay = rec.metadata["start_delay_s"]
    # Mocap clock = sim clock + EXTRA_S; robot clock = sim clock - delay.
    t_mocap = rec.t_marker + EXTRA_S
    offset = -(EXTRA_S + delay)
    base_mocap = _compose(MOCAP_FROM_WORLD, np.asarray(rec.base_pose))
    q_at = CubicSpline(rec.t_joint, rec.q_meas, axis=0)
    t_rob = np.clip(t_mocap + offset, rec.t_joint[0], rec.t_joint[-1])
    tip = apply_pose(base_mocap, fk(q_at(t_rob)))
    return {
        "rec": rec,
        "fk": fk,
        "t_mocap": t_mocap,
        "offset": offset,
        "base": base_mocap,
        "markers": apply_pose(MOCAP_FROM_WORLD, np.asarray(rec.markers)),
        "tip": tip,
    }


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose a after pose b (7,) each."""
    Ra, Rb = quat_to_matrix(a[3:]), quat_to_matrix(b[3:])
    return np.concatenate([Ra @ b[:3] + a[:3], matrix_to_quat(Ra @ Rb)])


def _capture(trial, seed: int, noise: float = 0.0):
    """The lab software's labelled recording: (labels, points (m, 17, 3), truth, visible)."""
    rng = np.random.default_rng(seed)
    truth = trial["markers"]
    m = truth.shape[0]
    rope = truth + rng.normal(0.0, noise, truth.shape)
    visible = rng.random((m, 11)) >= 0.03  # 3 % random dropouts
    for _ in range(5):  # and longer ones, of a marker and its neighbour
        k, f0, n = rng.integers(0, 10), rng.integers(20, m - 40), rng.integers(5, 30)
        visible[f0 : f0 + n, k : k + 2] = False
    rope[~visible] = np.nan
    labelled = rope.copy()
    for _ in range(6):  # the software swaps neighbours' labels over stretches of frames
        k, f0, n = rng.integers(0, 10), rng.integers(0, m - 30), rng.integers(3, 30)
        labelled[f0 : f0 + n, [k, k + 1]] = labelled[f0 : f0 + n, [k + 1, k]]
    ghosts = rng.uniform([-0.5, 0.0, -1.5], [1.5, 2.0, 0.5], (m, 3, 3))
    ghosts[rng.random((m, 3)) < 0.7] = np.nan
    cluster = trial["tip"][:, None, :] + CLUSTER[None] + rng.normal(0.0, noise, (m, 3, 3))
    points = np.concatenate([labelled, ghosts, cluster], axis=1)
    labels = [f"rope{k:02d}" for k in range(11)] + ["*1", "*2", "*3", "tip1", "tip2", "tip3"]
    return labels, points, trial["markers"], visible


def _check_labels(result_markers, truth, visible, tol=0.003):
    tracked = np.all(np.isfinite(result_markers), axis=2)
    correct = tracked & (np.linalg.norm(result_markers - truth, axis=2) < tol)
    assert correct.sum() >= 0.99 * tracked.sum()
    assert (tracked & visible).sum() >= 0.97 * visible.sum()
    return correct.sum() / tracked.sum()


def test_c3d_round_trip_keeps_times_units_and_gaps(tmp_path, trial):
    labels, points, _, _ = _capture(trial, seed=0)
    stream = RawStream(trial["t_mocap"], points)
    path = write_c3d(tmp_path / "trial.c3d", stream, rate_hz=RATE, labels=labels)
    back = read_c3d(path)
    np.testing.assert_allclose(back.times, trial["t_mocap"], atol=1e-9)
    # Labels are dropped, and missing points with them: compare the sets of points per frame.
    for f in (0, 57, 130):
        want = points[f][np.all(np.isfinite(points[f]), axis=1)]
        got = back.points[f][np.all(np.isfinite(back.points[f]), axis=1)]
        assert got.shape == want.shape
        np.testing.assert_allclose(np.sort(got, axis=0), np.sort(want, axis=0), atol=2e-6)
    with pytest.raises(RecordError, match="does not exist"):
        read_c3d(tmp_path / "none.c3d")


def test_labelling_recovers_swapped_dropped_c3d_markers(tmp_path, trial):
    labels, points, truth, visible = _capture(trial, seed=1)
    path = write_c3d(
        tmp_path / "t.c3d", RawStream(trial["t_mocap"], points), rate_hz=RATE, labels=labels
    )
    stream = read_c3d(path, body_labels={"fingertip": ["tip1", "tip2", "tip3"]})
    np.testing.assert_allclose(stream.body("fingertip").position, trial["tip"], atol=1e-5)
    swapped = np.linalg.norm(points[:, :11] - truth, axis=2) > 0.01
    assert swapped.sum() > 50  # the file's own labels are wrong there
    res = label_rope_markers(
        stream.times, stream.points, stream.body("fingertip").position, gravity_dir=GRAVITY_MOCAP
    )
    assert res.init_frame == 0
    fraction = _check_labels(res.markers, truth, visible)
    assert fraction == 1.0  # noiseless: every tracked label is right


@pytest.mark.parametrize("noise", [0.0, 0.001])
def test_pipeline_aligns_the_clock_within_a_millisecond(tmp_path, trial, noise):
    labels, points, truth, visible = _capture(trial, seed=2, noise=noise)
    path = write_c3d(
        tmp_path / "t.c3d", RawStream(trial["t_mocap"], points), rate_hz=RATE, labels=labels
    )
    stream = read_c3d(path, body_labels={"fingertip": ["tip1", "tip2", "tip3"]})
    rec = trial["rec"]
    out = trial_markers(
        stream,
        t_joint=rec.t_joint,
        q_meas=rec.q_meas,
        fk=trial["fk"],
        base_pose=trial["base"],
        tip_body="fingertip",
        label_params=None,
        gravity_dir=GRAVITY_MOCAP,
    )
    al = out.alignment
    assert abs(al.offset_s - trial["offset"]) < 1e-3
    assert al.residual_rms_m < (1e-3 if noise == 0 else 3e-3)
    _check_labels(out.labels.markers, truth, visible, tol=0.003 + 5 * noise)
    # Resampled onto k / 200 Hz of the robot clock, matching the truth there.
    k = out.t_marker * RATE
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    t_m = out.t_marker - al.offset_s  # back on the mocap clock
    want = np.stack(
        [[np.interp(t_m, trial["t_mocap"], truth[:, j, c]) for c in range(3)] for j in range(11)]
    ).transpose(2, 0, 1)
    ok = np.all(np.isfinite(out.markers), axis=2)
    assert ok.mean() > 0.9
    err = np.linalg.norm(out.markers - want, axis=2)[ok]
    assert np.percentile(err, 99) < 0.004 + 5 * noise  # a dt^2 / 8 of a whipping rope


def test_alignment_on_rope_marker_0_is_coarser(trial):
    truth = trial["markers"]
    rec = trial["rec"]
    stream = RawStream(trial["t_mocap"], truth)
    out = trial_markers(
        stream,
        t_joint=rec.t_joint,
        q_meas=rec.q_meas,
        fk=trial["fk"],
        base_pose=trial["base"],
        gravity_dir=GRAVITY_MOCAP,
    )
    assert abs(out.alignment.offset_s - trial["offset"]) < 0.015
    # With the base pose given, the residual holds marker 0's 0.10 m from the fingertip.
    assert 0.08 < out.alignment.residual_rms_m < 0.15


def test_csv_with_a_body_and_the_hand_cluster_unlabelled(tmp_path, trial):
    _, points, truth, visible = _capture(trial, seed=4)
    tip = trial["tip"]
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(tip), 1))
    from flyknot_hw.mocap import BodyTrack

    stream = RawStream(trial["t_mocap"], points, {"fingertip": BodyTrack(tip, quat)})
    path = write_csv(tmp_path / "t.csv", stream)
    back = read_csv(path)
    assert list(back.bodies) == ["fingertip"]
    np.testing.assert_allclose(back.body("fingertip").position, tip, atol=1e-8)
    np.testing.assert_allclose(back.times, stream.times, atol=1e-9)
    res = label_rope_markers(
        back.times, back.points, back.body("fingertip").position, gravity_dir=GRAVITY_MOCAP
    )
    assert _check_labels(res.markers, truth, visible) == 1.0
    mm = read_csv(write_csv(tmp_path / "mm.csv", stream, units="mm"), units="mm")
    np.testing.assert_allclose(mm.body("fingertip").position, tip, atol=1e-8)


def test_csv_format_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,a.x,a.y,a.z\n0,1,2,3\n")
    with pytest.raises(RecordError, match="first column"):
        read_csv(bad)
    bad.write_text("t,a.x,a.y,a.w\n0,1,2,3\n")
    with pytest.raises(RecordError, match="axis"):
        read_csv(bad)
    bad.write_text("# exported\nt,a.x,a.y,a.z\n0,1,2,3\n0,1,2,3\n")
    with pytest.raises(RecordError, match="increase"):
        read_csv(bad)


def test_calibration_from_the_simulated_arm(trial):
    fk = trial["fk"]
    rng = np.random.default_rng(5)
    q = np.asarray(trial["rec"].q_meas[0]) + rng.uniform(-0.5, 0.5, (6, 7))
    a = fk(q)
    b = apply_pose(trial["base"], a) + rng.normal(0, 0.0003, a.shape)
    pose, res = calibrate_base(a, b)
    assert np.linalg.norm(pose[:3] - trial["base"][:3]) < 0.002
    assert res.rms_m < 0.0005 and res.max_m < 0.001


# --- matching recordings to trials ---------------------------------------------------------


def _touch(path, mtime=None):
    path.write_text("t,p0.x,p0.y,p0.z\n0,0,0,0\n0.005,0,0,0\n")
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def test_match_by_name(tmp_path):
    _touch(tmp_path / "trial_0007.csv")
    _touch(tmp_path / "trial_0007_retake.csv")
    _touch(tmp_path / "trial_0008 capture.csv")
    assert match_recording(tmp_path, trial_stem="trial_0007").name == "trial_0007.csv"
    assert match_recording(tmp_path, trial_stem="trial_0008").name == "trial_0008 capture.csv"
    with pytest.raises(HardwareError, match="found 0"):
        match_recording(tmp_path, trial_stem="trial_0009")
    _touch(tmp_path / "trial_0008_b.csv")
    with pytest.raises(HardwareError, match="found 2"):
        match_recording(tmp_path, trial_stem="trial_0008")


def test_match_by_time_stamp_in_the_name_or_by_modification_time(tmp_path):
    start = datetime(2026, 3, 4, 10, 0, 30).timestamp()
    _touch(tmp_path / "Capture 2026-03-04 10-00-25.csv")  # started 5 s before the trial
    _touch(tmp_path / "Capture 2026-03-04 09-59-40.csv")  # the previous trial's
    got = match_recording(tmp_path, trial_start=start, trial_end=start + 10)
    assert got.name == "Capture 2026-03-04 10-00-25.csv"
    other = tmp_path / "plain"
    other.mkdir()
    _touch(other / "a.csv", mtime=start - 30)  # an earlier trial's file
    _touch(other / "b.csv", mtime=start + 12)  # written 2 s after the trial ended
    assert match_recording(other, trial_start=start, trial_end=start + 10).name == "b.csv"
    with pytest.raises(HardwareError, match="found 0"):
        match_recording(other, trial_start=start + 100, trial_end=start + 110)


def test_recorded_file_source_waits_for_the_file(tmp_path, trial):
    src = RecordedFileSource(tmp_path, trial_stem="trial_0001", wait_s=5.0, poll_s=0.05)
    src.start()
    stream = RawStream(trial["t_mocap"][:50], trial["markers"][:50])

    def capture_software():
        time.sleep(0.2)
        write_csv(tmp_path / "trial_0001.csv", stream)

    writer = threading.Thread(target=capture_software)
    writer.start()
    got = src.stop()
    writer.join()
    assert got.n_frames == 50
    np.testing.assert_allclose(got.points, trial["markers"][:50], atol=1e-8)
    late = RecordedFileSource(tmp_path, trial_stem="trial_0002", wait_s=0.2, poll_s=0.05)
    late.start()
    with pytest.raises(HardwareError, match="no finished recording"):
        late.stop()

"""The simulated lab as a cell: what a trial measures, faults, variation, the CLI."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from flyknot.errors import ConfigError
from flyknot.record import Cell, TrialRecord
from flyknot_app.cli import main
from flyknot_sim.commands import swing_command
from flyknot_sim.lab import LabParams, SimLab, VariationParams
from flyknot_sim.mocap import MocapParams


@pytest.fixture(scope="module")
def lab():
    return SimLab(LabParams(rope=1, settle_s=0.3))


@pytest.fixture(scope="module")
def record(lab):
    return lab.run(swing_command())


def test_lab_is_a_cell(lab):
    assert isinstance(lab, Cell)


def test_record_rates_and_shapes(record):
    cmd = swing_command()
    n = cmd.n + round(0.3 * 250)
    assert record.t_joint.shape == (n,)
    np.testing.assert_allclose(np.diff(record.t_joint), 1 / 250)
    np.testing.assert_allclose(np.diff(record.t_marker), 1 / 200, atol=1e-12)
    assert record.markers.shape[1:] == (11, 3)
    np.testing.assert_array_equal(record.q_cmd[: cmd.n], cmd.q)
    assert record.fault is None and record.knot == "unknot"
    assert record.first_contact_time is None
    assert not np.isnan(record.markers).any()  # no self-contact, no loss


def test_servos_lag_a_fast_command_but_follow_it(record):
    err = np.abs(record.q_meas - record.q_cmd)
    assert err.max() < 0.05  # [rad]
    assert err.max() > 1e-3  # a real servo lags


def test_fingertip_matches_robot_kinematics(lab, record):
    m = mujoco.MjModel.from_xml_path(str(__import__("flyknot.constants").constants.XARM7_XML))
    d = mujoco.MjData(m)
    d.qpos[:7] = record.q_meas[10]
    mujoco.mj_kinematics(m, d)
    tip = d.site("fingertip").xpos + record.base_pose[:3]
    np.testing.assert_allclose(record.fingertip_pos[10], tip, atol=1e-9)


def test_markers_hang_below_the_fingertip_at_rest(record):
    tip = record.fingertip_pos[0]
    m0 = record.markers[0]
    # 0.10 m spacing along a (nearly) straight hanging rope; noise 1 mm, sway <= a few deg.
    gaps = np.linalg.norm(np.diff(m0, axis=0), axis=1)
    np.testing.assert_allclose(gaps, 0.10, atol=0.006)
    assert np.all(m0[:, 2] < tip[2]) and m0[-1, 2] == pytest.approx(tip[2] - 1.1, abs=0.03)


def test_trials_vary_with_the_seed_and_repeat_exactly():
    cmd = swing_command()
    a = SimLab(LabParams(rope=1, seed=3, settle_s=0.1))
    b = SimLab(LabParams(rope=1, seed=3, settle_s=0.1))
    r1, r2 = a.run(cmd), a.run(cmd)
    assert not np.allclose(r1.markers, r2.markers)  # sway, gains, delay, noise differ
    np.testing.assert_array_equal(b.run(cmd).markers, r1.markers)  # same (seed, index)


def test_without_variation_only_mocap_noise_differs():
    cmd = swing_command()
    quiet = LabParams(
        rope=1, settle_s=0.1, variation=VariationParams.none(), mocap=MocapParams(noise_std=0.0)
    )
    r1, r2 = SimLab(quiet).run(cmd), SimLab(quiet).run(cmd)
    np.testing.assert_array_equal(r1.q_meas, r2.q_meas)
    np.testing.assert_allclose(r1.markers, r2.markers)


@pytest.mark.parametrize(
    ("amplitude", "duration", "quantity", "joint"),
    [(1.0, 0.8, "velocity", 1), (2.3, 3.0, "position", 2)],
)
def test_a_command_beyond_the_limits_faults_mid_motion(lab, amplitude, duration, quantity, joint):
    amp = np.zeros(7)
    amp[joint - 1] = amplitude
    cmd = swing_command(amplitude=amp, duration=duration)
    rec = lab.run(cmd)
    assert rec.fault is not None and f"joint {joint} {quantity}" in rec.fault
    assert rec.knot is None and not rec.succeeded
    assert 0 < rec.fault_time < cmd.duration
    assert rec.t_joint[-1] < cmd.duration + 0.3 + 1e-9  # aborted, braked, stopped


def test_tracking_is_lost_shortly_after_the_first_self_contact(monkeypatch):
    lab = SimLab(LabParams(rope=1, settle_s=0.1, mocap=MocapParams(loss_delay=0.02)))
    state = {"t": 0}

    def fake_contact(model, data):
        # MjData's contacts after a step belong to the state before it.
        return data.time - model.opt.timestep >= 0.3 - 1e-12

    monkeypatch.setattr(type(lab.rope), "self_contact", lambda self, m, d: fake_contact(m, d))
    rec = lab.run(swing_command())
    assert rec.first_contact_time == pytest.approx(0.3, abs=1e-9)
    lost = np.isnan(rec.markers).all(axis=(1, 2))
    assert not lost[rec.t_marker < rec.first_contact_time + 0.02 - 1e-9].any()
    assert lost[rec.t_marker >= rec.first_contact_time + 0.02 + 1e-9].all()
    assert state == {"t": 0}


def test_record_round_trip_from_the_lab(tmp_path, record):
    record.save(tmp_path / "t")
    back = TrialRecord.load(tmp_path / "t", with_truth=True)
    np.testing.assert_array_equal(back.markers, record.markers)
    assert back.truth["centreline"].shape[1:] == record.truth["centreline"].shape[1:]
    assert back.metadata["rope"] == 1 and back.metadata["versions"]["mujoco"] == mujoco.__version__


def test_the_labs_verdict_measures_the_floor_by_the_ropes_radius(monkeypatch):
    import flyknot_sim.session as session

    seen = []
    judge = session.judge_centreline

    def spy(points, axis, params):
        seen.append(params)
        return judge(points, axis, params)

    monkeypatch.setattr(session, "judge_centreline", spy)
    rec = SimLab(LabParams(rope=5, settle_s=0.1)).run(
        swing_command(duration=0.3, amplitude=np.full(7, 0.1))
    )
    assert rec.fault is None
    assert [p.rope_radius_m for p in seen] == [0.0125]
    assert rec.metadata["rope_diameter_m"] == 0.025


def test_unknown_rope_lists_choices():
    with pytest.raises(
        ConfigError, match=r"unknown rope id 9 \(valid choices: 1, 2, 3, 4, 5, 6, 7\)"
    ):
        LabParams(rope=9)


def test_cli_trial_and_its_errors(tmp_path, capsys):
    cmd_file = tmp_path / "c.csv"
    swing_command(duration=0.3, amplitude=np.full(7, 0.1)).save(cmd_file)
    assert (
        main(
            [
                "trial",
                "--rope",
                "4",
                "--command",
                str(cmd_file),
                "--out",
                str(tmp_path / "o"),
                "--settle",
                "0.1",
                "--json",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["rope"] == 4 and out["fault"] is None
    assert TrialRecord.load(tmp_path / "o" / "trial").metadata["rope"] == 4
    # errors: exit code 2, one clear line, no traceback
    assert main(["trial", "--rope", "9", "--command", str(cmd_file), "--out", str(tmp_path)]) == 2
    assert "unknown rope id 9" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("t,q1,q2,q3,q4,q5,q6,q7\n0,0,0,0,0,0,0,0\n0.004,0,0,nan,0,0,0,0\n")
    assert main(["trial", "--command", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "non-finite" in err and "Traceback" not in err
    short = tmp_path / "short.npy"
    np.save(short, np.zeros((10, 6)))
    assert main(["trial", "--command", str(short), "--out", str(tmp_path)]) == 2
    assert "must have shape (n, 7), got (10, 6)" in capsys.readouterr().err

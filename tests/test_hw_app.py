"""Hardware mode in the application: the xarm cell kind, --cell / --dry-run, the dry run's
preflight, calibration with the learner's kinematics. No robot: the dry run never connects."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from flyknot.constants import REPO_ROOT
from flyknot.errors import ConfigError
from flyknot.geometry import quat_to_matrix
from flyknot.numerics import numerics_class
from flyknot.record import JointCommand
from flyknot_app import cli
from flyknot_app.cells import cell_spec, open_cell
from flyknot_app.hardware import DryRunCell, LearnerKinematics, calibrate
from flyknot_hw.config import parse_lab_config
from flyknot_hw.preflight import PreflightError
from flyknot_sim.commands import HOME_Q

LAB = REPO_ROOT / "assets" / "lab_example.toml"


@pytest.fixture(scope="module")
def kin():
    return LearnerKinematics()


def _lab(**safety):
    doc = tomllib.loads(LAB.read_text())
    doc["safety"].update(safety)
    return parse_lab_config(doc)


def _hold(q, n=50):
    return JointCommand(q=np.tile(q, (n, 1)), rate_hz=250.0)


def test_the_learners_fingertip_matches_the_simulated_arm(kin):
    from fakes import SimFingertip

    q = HOME_Q + np.random.default_rng(0).normal(scale=0.3, size=(5, 7))
    p, quat = kin(q)
    p_sim, quat_sim = SimFingertip()(q)
    np.testing.assert_allclose(p, p_sim, atol=1e-9)
    np.testing.assert_allclose(quat_to_matrix(quat), quat_to_matrix(quat_sim), atol=1e-9)


def test_a_dry_run_refuses_what_the_arm_would_refuse_before_playing(kin):
    lab = _lab(workspace={"min": [-0.9, -0.9, 0.05], "max": [0.1, 0.9, 1.3]})
    cell = DryRunCell(lab, kinematics=kin)
    with pytest.raises(PreflightError, match=r"^command: fingertip x = .* leaves the workspace"):
        cell.run(_hold(HOME_Q))
    assert cell.trial_index == 0  # nothing was played


def test_a_dry_run_plays_a_passing_command_in_the_simulated_lab(kin):
    cell = DryRunCell(_lab(), kinematics=kin)
    rec = cell.run(_hold(HOME_Q, 25))
    assert cell.trial_index == 1
    assert rec.metadata["dry_run"] is True
    assert set(rec.metadata["preflight"]["checked"]) >= {"position", "torque", "workspace"}


def test_the_xarm_cell_needs_the_mounted_rope(tmp_path):
    spec = cell_spec("xarm", {"lab": str(LAB), "rope": 3})
    bad_rope = r"^rope: the run needs rope 3 but the lab file .* says rope 1 is mounted"
    with pytest.raises(ConfigError, match=bad_rope):
        open_cell("xarm", spec)
    with pytest.raises(ConfigError, match=r"^cell\.lab: the real lab needs its lab file"):
        cell_spec("xarm", {"rope": 1})
    dry = open_cell("xarm", cell_spec("xarm", {"lab": str(LAB), "rope": 1, "dry_run": True}))
    assert isinstance(dry, DryRunCell)


def test_dry_run_without_a_lab_file_is_refused(capsys):
    assert cli.main(["run", "quick", "--dry-run"]) == 2
    assert capsys.readouterr().err.strip() == (
        "flyknot: error: --dry-run: needs --cell LAB.toml (the real lab it stands in for)"
    )


def test_run_with_cell_dry_run_plays_the_scenario_through_the_preflight(egl, tmp_path, capsys):
    args = ["run", "quick", "--cell", str(LAB), "--dry-run", "--set", "max_trials=0"]
    # The example lab keeps the controller's servo-mode TCP speed limit (C60, 1.2 m/s): the
    # learned throw is refused before anything moves.
    assert cli.main([*args, "--out", str(tmp_path / "refused")]) == 2
    assert "fingertip speed" in capsys.readouterr().err
    fast = tmp_path / "fast_lab.toml"
    fast.write_text(LAB.read_text().replace("tip_speed_max = 1.2", "tip_speed_max = 4.0"))
    args[3] = str(fast)
    out = tmp_path / "dry"
    assert cli.main([*args, "--out", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    run = manifest["runs"][0]
    assert run["cell"] == "xarm" and run["cell_options"]["dry_run"] is True
    assert manifest["numerics"] == numerics_class()  # the machine class the run ran on
    rec = json.loads((out / "runs" / "rope1" / "learning" / "trial_0000_a0.json").read_text())
    assert rec["metadata"]["dry_run"] is True
    assert 1.2 < rec["metadata"]["preflight"]["tip_speed_peak_m_s"] < 4.0 * 0.95


@pytest.mark.slow
def test_a_velocity_stream_dry_run_passes_and_view_opens_its_run(
    egl, tmp_path, capsys, monkeypatch
):
    import flyknot_app.viewer.server as viewer

    served = []
    monkeypatch.setattr(viewer, "serve", lambda path, **kw: served.append((Path(path), kw)))
    lab = tmp_path / "velocity_lab.toml"
    lab.write_text(LAB.read_text().replace('stream = "servo"', 'stream = "velocity"'))
    out = tmp_path / "dry"
    args = ["run", "quick", "--cell", str(lab), "--dry-run", "--set", "max_trials=0"]
    assert cli.main([*args, "--out", str(out)]) == 0  # C60 is servo mode's: not checked
    assert capsys.readouterr().out.rstrip().endswith(f"flyknot view {out}")
    assert served == []
    assert cli.main([*args, "--out", str(tmp_path / "dry2"), "--view", "--port", "8123"]) == 0
    assert served == [(tmp_path / "dry2", {"port": 8123})]


def test_calibration_recovers_a_base_pose(kin):
    rng = np.random.default_rng(1)
    true_pose = np.array([0.4, -0.3, 0.8, *(q := rng.normal(size=4)) / np.linalg.norm(q)])
    R, t = quat_to_matrix(true_pose[3:]), true_pose[:3]

    def measure(q):  # the fingertip the motion capture would see, with 0.2 mm noise
        return R @ kin.positions(q[None])[0] + t + rng.normal(scale=2e-4, size=3)

    poses = HOME_Q + rng.normal(scale=0.4, size=(6, 7))
    cal = calibrate(measure, poses, kinematics=kin)
    np.testing.assert_allclose(cal.base_pose[:3], t, atol=2e-3)
    np.testing.assert_allclose(quat_to_matrix(cal.base_pose[3:]), R, atol=5e-3)
    assert cal.residual_rms < 1e-3 and cal.toml().startswith("[base]\npose = [")
    with pytest.raises(ConfigError, match=r"^poses: must be at least 3 joint poses"):
        calibrate(measure, poses[:2], kinematics=kin)


def test_calibrate_command_prints_the_base_table(tmp_path, capsys, kin):
    rng = np.random.default_rng(4)
    poses = HOME_Q + rng.normal(scale=0.4, size=(5, 7))
    t = np.array([0.3, 0.1, 0.75])
    np.savetxt(tmp_path / "poses.csv", poses, delimiter=",", header="q1,q2,q3,q4,q5,q6,q7")
    np.save(tmp_path / "measured.npy", kin.positions(poses) + t)
    args = ["calibrate", "--cell", str(LAB), "--poses", str(tmp_path / "poses.csv")]
    assert cli.main([*args, "--measured", str(tmp_path / "measured.npy")]) == 0
    out = capsys.readouterr().out
    assert "residual rms 0.00 mm" in out
    assert "[base]\npose = [0.300000, 0.100000, 0.750000, 1.000000, " in out
    np.save(tmp_path / "few.npy", (kin.positions(poses) + t)[:4])
    assert cli.main([*args, "--measured", str(tmp_path / "few.npy")]) == 2
    assert "--measured: has 4 rows for 5 poses" in capsys.readouterr().err


def test_calibrate_command_file_fit_options(tmp_path, capsys, kin):
    """The fit of two files: per-pose residuals, --out, and the options it refuses."""
    rng = np.random.default_rng(5)
    poses = HOME_Q + rng.normal(scale=0.4, size=(6, 7))
    measured = kin.positions(poses) + np.array([0.2, -0.1, 0.9])
    measured[2] += [0.0, 0.004, 0.0]  # pose 3 off by 4 mm
    np.save(tmp_path / "poses.npy", poses)
    np.save(tmp_path / "measured.npy", measured)
    out = tmp_path / "base.toml"
    args = ["calibrate", "--cell", str(LAB), "--poses", str(tmp_path / "poses.npy")]
    assert cli.main([*args, "--measured", str(tmp_path / "measured.npy"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = [line.split() for line in text.splitlines() if line[:4].strip().isdigit()]
    per_pose = {int(r[0]): float(r[1]) for r in rows}
    assert len(per_pose) == 6 and max(per_pose, key=per_pose.get) == 3
    pose = tomllib.loads(out.read_text())["base"]["pose"]
    np.testing.assert_allclose(pose[:3], [0.2, -0.1, 0.9], atol=3e-3)
    assert f"Written: {out}" in text
    lab_only = ["calibrate", "--cell", str(LAB)]
    refused = [
        ([*lab_only, "--measured", "m.npy"], "--measured: needs --poses"),
        ([*args, "--measured", "m.npy", "--dry-run"], "--dry-run: moves nothing with --measured"),
        ([*args, "--out", str(LAB), "--dry-run"], "--out: must not be the lab file"),
    ]
    for argv, message in refused:
        assert cli.main(argv) == 2
        assert message in capsys.readouterr().err


def test_the_learner_keeps_the_limits_its_cell_plays(kin):
    from flyknot.limits import JointLimits
    from flyknot_app.runner import command_limits
    from flyknot_hw.preflight import effective_limits

    cell = DryRunCell(_lab(), kinematics=kin)
    margins = cell.config.safety.margins
    assert command_limits(cell).qd_max == pytest.approx(
        (1 - margins.velocity) * effective_limits().qd_max
    )
    assert command_limits(cell) == margins.apply(effective_limits())
    assert command_limits(object()) == JointLimits()  # a simulated lab: the controller's own

"""The simulated lab's records and a learning run's costs, bit for bit.

``tests/data/lab_fingerprints.json`` holds SHA-256 digests of the records of a fixed set of
trials (the robot demonstration's seed command on ropes 1 and 7, lab seed 3, two trials each,
0.3 s settle: every array the record carries, the truth, the fault, the first contact and
the verdict) and the exact critical-point costs of a short learning run. A refactor must not
change them; a change of the lab's physics or variation does, on purpose: then regenerate
the file (``python tests/test_lab_fingerprint.py > tests/data/lab_fingerprints.json``) and
say why in the commit.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from flyknot.record import TrialRecord
from flyknot_app.trial_cli import load_command
from flyknot_sim.lab import LabParams, SimLab

ROOT = Path(__file__).resolve().parent.parent
STORED = ROOT / "tests" / "data" / "lab_fingerprints.json"
ARRAYS = ("q_cmd", "q_meas", "t_marker", "markers", "fingertip_pos", "fingertip_quat")


def fingerprint(rec: TrialRecord) -> str:
    """SHA-256 of a record's arrays, truth, fault, first contact and verdict."""
    h = hashlib.sha256()
    for name in ARRAYS:
        h.update(np.ascontiguousarray(getattr(rec, name)).tobytes())
    for k in sorted(rec.truth):
        h.update(np.ascontiguousarray(rec.truth[k]).tobytes())
    verdict = None if rec.verdict is None else rec.verdict.to_json()
    h.update(json.dumps([rec.fault, rec.first_contact_time, rec.knot, verdict]).encode())
    return h.hexdigest()


def fingerprints() -> dict[str, list[str]]:
    """The digests of the fixed set of trials (module docstring)."""
    command = load_command(ROOT / "assets" / "demos" / "seeds" / "robot_command.npz")
    out = {}
    for rope in (1, 7):
        lab = SimLab(LabParams(rope=rope, seed=3, settle_s=0.3))
        out[f"rope{rope}"] = [fingerprint(lab.run(command)) for _ in range(2)]
    return out


def learning_costs() -> list[str]:
    """The critical-point costs (exact, as hex) of 3 ILC trials on rope 1 from the robot
    demonstration's seed command (the scenarios' learner settings, lab seed 3)."""
    from flyknot_app.runner import prepare_target
    from learner.ilc import ILCParams, learn
    from learner.inverse_qp import InverseModelWeights
    from learner.kinematics import RobotModel
    from learner.rope_model import RopeModelParams
    from learner.update import UpdateSettings

    rope_model = RopeModelParams(stiffness=100.0, damping=0.5)
    _, target = prepare_target("robot", rope_model.dt, (0.25, 0.0))
    with np.load(ROOT / "assets" / "demos" / "seeds" / "robot_command.npz") as z:
        knots0 = z["knots"]
    params = ILCParams(
        max_trials=3,
        stop_at_success=False,
        rope_model=rope_model,
        gain=0.5,
        update=UpdateSettings(weights=InverseModelWeights(w_control=5.0)),
    )
    lab = SimLab(LabParams(rope=1, seed=3, settle_s=0.3))
    res = learn(lab, target, knots0, RobotModel.from_mjcf(), params)
    return [None if c is None else float(c).hex() for c in res.costs]


def test_the_fixed_trials_are_bit_identical():
    assert fingerprints() == json.loads(STORED.read_text())["records"]


def test_a_learning_runs_costs_are_bit_identical():
    assert learning_costs() == json.loads(STORED.read_text())["learning_costs"]


if __name__ == "__main__":
    print(json.dumps({"records": fingerprints(), "learning_costs": learning_costs()}, indent=1))

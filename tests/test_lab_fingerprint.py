"""The simulated lab's records and a learning run's costs, bit for bit.

``tests/data/lab_fingerprints.json`` holds, per machine class
(:func:`flyknot.numerics.numerics_class`: the lab is bit-reproducible on one class, not across
CPUs of different vector extensions), SHA-256 digests of the records of a fixed set of trials
(the robot demonstration's seed command on ropes 1 and 7, lab seed 3, two trials each, 0.3 s
settle: every array the record carries, the truth, the fault, the first contact and the
verdict) and the exact critical-point costs of a short learning run. A refactor must not
change them; a change of the lab's physics or variation does, on purpose: then regenerate the
entry of each class at hand (``python tests/test_lab_fingerprint.py``, which rewrites this
machine's entry and keeps the others) and say why in the commit. The ``x86_64-avx512`` entry
was made on the machine the project was developed on before (its class inferred: its digests
differ from an AVX2 machine's from the first trial on); a class without an entry fails the
tests with the command that writes one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from flyknot.numerics import numerics_class
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


def stored() -> dict:
    """This machine class's stored fingerprints (the test fails on a class without any)."""
    by_class = json.loads(STORED.read_text())["by_numerics_class"]
    here = numerics_class()
    assert here in by_class, (
        f"no fingerprints for machine class {here!r} (stored: {sorted(by_class)}): "
        "write them with `python tests/test_lab_fingerprint.py` on a commit whose lab is known good"
    )
    return by_class[here]


def test_the_fixed_trials_are_bit_identical():
    assert fingerprints() == stored()["records"]


def test_a_learning_runs_costs_are_bit_identical():
    assert learning_costs() == stored()["learning_costs"]


@pytest.mark.parametrize(
    ("machine", "features", "expected"),
    [
        ("x86_64", {"AVX512F": True, "AVX2": True, "FMA3": True}, "x86_64-avx512"),
        ("x86_64", {"AVX512F": False, "AVX2": True, "FMA3": True}, "x86_64-avx2"),
        ("x86_64", {"AVX2": False}, "x86_64-base"),
        ("AMD64", {"AVX2": True, "FMA3": True}, "amd64-avx2"),
        ("aarch64", {"AVX512F": True}, "aarch64"),
    ],
)
def test_the_machine_class_names_the_widest_vector_extension(
    monkeypatch, machine, features, expected
):
    import flyknot.numerics as numerics

    monkeypatch.setattr(numerics.platform, "machine", lambda: machine)
    monkeypatch.setattr(numerics, "_numpy_cpu_features", lambda: features)
    assert numerics.numerics_class() == expected


if __name__ == "__main__":
    data = json.loads(STORED.read_text()) if STORED.exists() else {"by_numerics_class": {}}
    data["by_numerics_class"][numerics_class()] = {
        "records": fingerprints(),
        "learning_costs": learning_costs(),
    }
    STORED.write_text(json.dumps(data, indent=1) + "\n")
    print(f"wrote the {numerics_class()} fingerprints to {STORED}")

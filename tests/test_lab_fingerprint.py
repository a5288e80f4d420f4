"""The simulated lab's records and a learning run's costs: bit for bit on a stored machine
class, within measured tolerances on any other.

``tests/data/lab_fingerprints.json`` holds, per machine class
(:func:`flyknot.numerics.numerics_class`: the lab is bit-reproducible on one class, not across
classes), for a fixed set of trials (the robot demonstration's seed command on ropes 1 and 7,
lab seed 3, two trials each, 0.3 s settle): SHA-256 digests of the records (every array the
record carries, the truth, the fault, the first contact and the verdict), each record's motion
up to the rope's first self-contact (:func:`motion`), and the exact critical-point costs of a
short learning run.

On a stored class the digests and the costs must be equal. On any other class the lab is
another sample after the first contact (module :mod:`flyknot.numerics`), so the records'
motion up to it and the costs are compared with every stored class within the tolerances
below; a class without an entry is never a failure for lacking one. A refactor must not change
the entries; a change of the lab's physics or variation does, on purpose: then rewrite the
entry of each class at hand (``python tests/test_lab_fingerprint.py [CLASS]``, which writes
this machine's class, or CLASS, and keeps the others) and say why in the commit.

The entries: ``x86_64-avx512-skylakex`` and ``x86_64-avx512-haswell`` (an AVX-512 CPU on
OpenBLAS's SkylakeX or Haswell kernels; ``OPENBLAS_CORETYPE`` picks them), and
``x86_64-avx2-haswell``, written on an AVX-512 machine with AVX-512 off in NumPy
(``NPY_DISABLE_CPU_FEATURES=X86_V4,AVX512_ICL,AVX512_SPR``), Numba (``NUMBA_CPU_FEATURES``
without any ``avx512`` feature) and OpenBLAS (``OPENBLAS_CORETYPE=Haswell``); its digests and
costs are those an AVX2 machine wrote.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import re
import subprocess
import sys
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
STEP_S = 0.1
"""The stored motion's spacing [s] (and the last sample before the first contact)."""

# The tolerances of another class. Measured between the stored classes on the fixed trials
# (each pair of x86_64-avx512-skylakex, x86_64-avx2-haswell and x86_64-avx512-haswell, on full
# records): the first contact at the same time in every trial, and up to it the fingertip
# within 7.8e-8 m and the markers within 2.5e-4 m (rope 1's first trial; rope 7 within 4e-15
# m); the learning costs within 2.2e-4 relative between skylakex and avx2, 3.7e-4 at most
# between any two.
CONTACT_TOL_S = 5e-3
"""The rope's first self-contact [s] (equal in the measurement)."""
HAND_TOL_M = 1e-5
"""The fingertip up to the first contact [m] (7.8e-8 measured)."""
MARKER_TOL_M = 2e-3
"""Every marker seen in both, up to the first contact [m] (2.5e-4 measured)."""
COST_RTOL = 5e-3
"""A learning trial's critical-point cost, relative (3.7e-4 measured)."""


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


def _until_contact(t: np.ndarray, x: np.ndarray, t_c: float | None) -> dict:
    """``x`` every :data:`STEP_S` up to ``t_c`` and at its last sample before it (the whole
    record without a contact), with the sample indices."""
    end = len(t) if t_c is None else int(np.searchsorted(t, t_c, side="right"))
    step = max(1, round(STEP_S / float(t[1] - t[0])))
    index = sorted({*range(0, end, step), end - 1})
    return {"index": index, "value": x[index].tolist()}


def motion(rec: TrialRecord) -> dict:
    """What another class must reproduce within the tolerances: the fault, the record's
    length (set by the fixed settle), the first contact and the fingertip and markers up to
    it."""
    t_c = rec.first_contact_time
    return {
        "fault": rec.fault,
        "samples": [len(rec.t_joint), len(rec.t_marker)],
        "first_contact_time": t_c,
        "fingertip": _until_contact(rec.t_joint, rec.fingertip_pos, t_c),
        "markers": _until_contact(rec.t_marker, rec.markers, t_c),
    }


def lab_records() -> dict[str, list[TrialRecord]]:
    """The fixed set of trials (module docstring)."""
    command = load_command(ROOT / "assets" / "demos" / "seeds" / "robot_command.npz")
    out = {}
    for rope in (1, 7):
        lab = SimLab(LabParams(rope=rope, seed=3, settle_s=0.3))
        out[f"rope{rope}"] = [lab.run(command) for _ in range(2)]
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


def stored_classes() -> dict[str, dict]:
    """Every stored class's entry, by class."""
    return json.loads(STORED.read_text())["by_numerics_class"]


def _assert_rows_close(found: dict, stored: dict, tol: float, what: str) -> None:
    """The rows both stored at the same sample index within ``tol`` where both are finite."""
    common, i, j = np.intersect1d(found["index"], stored["index"], return_indices=True)
    assert len(common) >= len(stored["index"]) - 1, f"{what}: {len(common)} common samples"
    a = np.asarray(found["value"], dtype=float)[i]
    b = np.asarray(stored["value"], dtype=float)[j]
    seen = np.isfinite(a) & np.isfinite(b)
    assert seen.mean() > 0.9, f"{what}: seen in {seen.mean():.0%} of the samples"
    worst = float(np.abs(a - b)[seen].max())
    assert worst <= tol, f"{what} differs by {worst:.3g} (tolerance {tol:g})"


def assert_motion_close(found: dict, stored: dict, where: str) -> None:
    """``found`` is ``stored`` within the tolerances of another class (``where`` names the
    trial and the class in a failure)."""
    assert found["fault"] == stored["fault"], f"{where}: fault"
    assert found["samples"] == stored["samples"], f"{where}: samples"
    t_c, t_c_stored = found["first_contact_time"], stored["first_contact_time"]
    assert (t_c is None) == (t_c_stored is None), f"{where}: first contact {t_c}"
    if t_c is not None:
        assert abs(t_c - t_c_stored) <= CONTACT_TOL_S, f"{where}: first contact {t_c}"
    _assert_rows_close(found["fingertip"], stored["fingertip"], HAND_TOL_M, f"{where}: fingertip")
    _assert_rows_close(found["markers"], stored["markers"], MARKER_TOL_M, f"{where}: markers")


def check_records(records: dict[str, list[TrialRecord]]) -> None:
    """The records bit for bit on a stored class; else within the tolerances of each."""
    by_class = stored_classes()
    here = numerics_class()
    if here in by_class:
        found = {rope: [fingerprint(r) for r in recs] for rope, recs in records.items()}
        assert found == by_class[here]["records"], f"the records of class {here}"
        return
    for name, entry in by_class.items():
        assert sorted(records) == sorted(entry["motion"]), name
        for rope, recs in records.items():
            assert len(recs) == len(entry["motion"][rope]), f"{rope} of {name}"
            for k, rec in enumerate(recs):
                assert_motion_close(motion(rec), entry["motion"][rope][k], f"{rope}[{k}] of {name}")


def check_costs(costs: list[str]) -> None:
    """The costs bit for bit on a stored class; else within :data:`COST_RTOL` of each."""
    by_class = stored_classes()
    here = numerics_class()
    if here in by_class:
        assert costs == by_class[here]["learning_costs"], f"the costs of class {here}"
        return
    found = np.array([float.fromhex(c) for c in costs])
    for name, entry in by_class.items():
        stored = np.array([float.fromhex(c) for c in entry["learning_costs"]])
        np.testing.assert_allclose(found, stored, rtol=COST_RTOL, err_msg=f"costs of {name}")


@pytest.fixture(scope="module")
def records() -> dict[str, list[TrialRecord]]:
    return lab_records()


def test_the_fixed_trials_match_the_stored_ones(records):
    check_records(records)


def test_a_learning_runs_costs_match_the_stored_ones():
    check_costs(learning_costs())


def _moved(records: dict, field: str, by: float) -> dict:
    """``records`` with rope 1's first trial's ``field`` moved by ``by`` (fingertip and
    markers [m] along x at every sample, the first contact [s])."""
    rec = records["rope1"][0]
    if field == "first_contact_time":
        moved = dataclasses.replace(rec, first_contact_time=rec.first_contact_time + by)
    else:
        values = getattr(rec, field).copy()
        values[..., 0] += by
        moved = dataclasses.replace(rec, **{field: values})
    return {**records, "rope1": [moved, *records["rope1"][1:]]}


SHIFTS = [
    pytest.param("fingertip_pos", HAND_TOL_M, "fingertip", id="fingertip"),
    pytest.param("markers", MARKER_TOL_M, "markers", id="markers"),
    pytest.param("first_contact_time", CONTACT_TOL_S, "first contact", id="first_contact"),
]


@pytest.mark.parametrize(("field", "tol", "message"), SHIFTS)
def test_without_an_entry_the_trials_are_held_to_the_tolerances(
    monkeypatch, records, field, tol, message
):
    """On an unstored class (``aarch64`` here) this machine's trials pass against every
    stored class, one moved by half a tolerance too; moved by twice a tolerance it fails."""
    monkeypatch.setattr(sys.modules[__name__], "numerics_class", lambda: "aarch64")
    assert "aarch64" not in stored_classes()
    check_records(records)
    check_records(_moved(records, field, 0.5 * tol))
    with pytest.raises(AssertionError, match=f"rope1\\[0\\] of .*: {message}"):
        check_records(_moved(records, field, 2.0 * tol))


def test_a_stored_class_is_held_to_every_bit(monkeypatch, records):
    """A stored class compares digests: a change far within the tolerances fails."""
    name = sorted(stored_classes())[0]
    monkeypatch.setattr(sys.modules[__name__], "numerics_class", lambda: name)
    with pytest.raises(AssertionError, match=f"the records of class {name}"):
        check_records(_moved(records, "fingertip_pos", 1e-12))
    with pytest.raises(AssertionError, match=f"the costs of class {name}"):
        check_costs([*stored_classes()[name]["learning_costs"][:2], (1.0).hex()])


def test_without_an_entry_the_costs_are_held_to_the_tolerance(monkeypatch):
    """On an unstored class the costs of every stored class pass against each other (the
    measurement), moved by half the tolerance too; moved by twice it they fail."""
    monkeypatch.setattr(sys.modules[__name__], "numerics_class", lambda: "aarch64")
    for entry in stored_classes().values():
        costs = np.array([float.fromhex(c) for c in entry["learning_costs"]])
        check_costs([float(c).hex() for c in costs * (1 + 0.5 * COST_RTOL)])
        with pytest.raises(AssertionError, match="costs of"):
            check_costs([float(c).hex() for c in costs * (1 + 2.0 * COST_RTOL)])


AVX512 = {"AVX512F": True, "AVX2": True, "FMA3": True}
AVX2 = {"AVX512F": False, "AVX2": True, "FMA3": True}


@pytest.mark.parametrize(
    ("machine", "features", "core", "expected"),
    [
        ("x86_64", AVX512, "skylakex", "x86_64-avx512-skylakex"),
        ("x86_64", AVX512, "haswell", "x86_64-avx512-haswell"),
        ("x86_64", AVX2, "haswell", "x86_64-avx2-haswell"),
        ("x86_64", {"AVX2": False}, None, "x86_64-base"),
        ("AMD64", {"AVX2": True, "FMA3": True}, "zen", "amd64-avx2-zen"),
        ("aarch64", {"AVX512F": True}, "neoversen1", "aarch64-neoversen1"),
        ("arm64", {}, None, "arm64"),
    ],
)
def test_the_machine_class_names_the_vector_extension_and_the_blas_kernels(
    monkeypatch, machine, features, core, expected
):
    import flyknot.numerics as numerics

    monkeypatch.setattr(numerics.platform, "machine", lambda: machine)
    monkeypatch.setattr(numerics, "_numpy_cpu_features", lambda: features)
    monkeypatch.setattr(numerics, "_openblas_core", lambda: core)
    assert numerics.numerics_class() == expected


def _dumps(data: dict) -> str:
    """``data`` as indented JSON with every innermost list on one line."""
    text = json.dumps(data, indent=1)
    return re.sub(r"\[\s*([^\[\]{}]*?)\s*\]", lambda m: f"[{' '.join(m[1].split())}]", text)


X86_64 = platform.machine().lower() in ("x86_64", "amd64")


@pytest.mark.skipif(not X86_64, reason="forces OpenBLAS's x86-64 kernel sets")
@pytest.mark.parametrize(("coretype", "expected"), [("Nehalem", "nehalem"), ("Haswell", "haswell")])
def test_the_blas_kernels_are_the_ones_openblas_runs(coretype, expected):
    """NumPy's OpenBLAS is asked which kernels it runs: a process that sets them with
    ``OPENBLAS_CORETYPE`` reads those."""
    code = "from flyknot.numerics import numerics_class; print(numerics_class())"
    env = {**os.environ, "OPENBLAS_CORETYPE": coretype, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip().endswith(f"-{expected}"), out.stderr


def test_without_a_bundled_openblas_the_class_names_no_kernels(monkeypatch):
    import flyknot.numerics as numerics

    monkeypatch.setattr(numerics, "_bundled_openblas", lambda: [])
    assert numerics._openblas_core.__wrapped__() is None


if __name__ == "__main__":
    name = sys.argv[1] if len(sys.argv) > 1 else numerics_class()
    data = json.loads(STORED.read_text()) if STORED.exists() else {"by_numerics_class": {}}
    found = lab_records()
    data["by_numerics_class"][name] = {
        "records": {rope: [fingerprint(r) for r in recs] for rope, recs in found.items()},
        "motion": {rope: [motion(r) for r in recs] for rope, recs in found.items()},
        "learning_costs": learning_costs(),
    }
    STORED.write_text(_dumps(data) + "\n")
    print(f"wrote the {name} fingerprints to {STORED}")

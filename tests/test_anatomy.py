"""Failure anatomy (flyknot_app.anatomy.diagnosis, _trials, _report): labels, a real trial, files,
CLI.

Constructed records carry a truth centreline history written as a string, one character per
10 ms frame: ``l`` a straight hanging rope (unknot), ``T`` the hanging overhand knot of
``tests/data/knots/overhand_41.csv`` (a trefoil, checked in tests/test_knot.py).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

import flyknot_app.anatomy.diagnosis as an
import flyknot_app.anatomy.report as ar
from flyknot.errors import ConfigError, RecordError
from flyknot.knot import load_centreline
from flyknot.record import TrialRecord
from flyknot.verdict import Verdict
from flyknot_app.cli import main
from tests.knot_curves import verdict

DATA = Path(__file__).parent / "data" / "knots"
DT = 0.01  # [s] truth frame interval of the constructed records
HAND = np.array([0.0, 0.0, 1.5])  # [m]
LINE = HAND + np.column_stack([np.zeros(41), np.zeros(41), -np.linspace(0.0, 1.1, 41)])
OVERHAND = load_centreline(DATA / "overhand_41.csv")
SHAPES = {"l": LINE, "T": OVERHAND}


def frames(spec: str) -> tuple[np.ndarray, np.ndarray]:
    """(t_truth (k,), centreline (k, 41, 3)) of a history string (module docstring)."""
    return np.arange(len(spec)) * DT, np.stack([SHAPES[c] for c in spec])


def judged_as(knot: str) -> Verdict:
    """The verdict a lab records for a rope whose knot is ``knot``, in the hanging rope."""
    if knot in ("trefoil", "unknot"):
        return verdict("knot" if knot == "trefoil" else "unknot")
    return Verdict("other_knot", knot, {knot: 31}, (12, 30), 0.4)


def record(
    spec: str | None = "l" * 40,
    *,
    contact: float | None = 0.1,
    knot: str | None = "unknot",
    fault: str | None = None,
    lost_from: float | None = None,
    metadata: dict | None = None,
) -> TrialRecord:
    """A constructed record: markers at 200 Hz over the history (NaN from ``lost_from``)."""
    duration = 0.4 if spec is None else len(spec) * DT
    t_marker = np.arange(0.0, duration, 0.005)
    markers = np.tile(LINE[::4][:11], (len(t_marker), 1, 1))
    if lost_from is not None:
        markers[t_marker >= lost_from - 1e-9] = np.nan
    truth = {}
    if spec is not None:
        t_truth, centreline = frames(spec)
        truth = {"t_truth": t_truth, "centreline": centreline}
    n = 3
    return TrialRecord(
        t_joint=np.arange(n) / 250.0,
        q_cmd=np.zeros((n, 7)),
        q_meas=np.zeros((n, 7)),
        t_marker=t_marker,
        markers=markers,
        fingertip_pos=np.tile(HAND, (n, 1)),
        fingertip_quat=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        base_pose=np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]),
        fault=fault,
        fault_time=None if fault is None else 0.1,
        first_contact_time=contact,
        knot=knot,
        verdict=None if knot is None else judged_as(knot),
        metadata={"cell": "sim", "rope": 1} if metadata is None else metadata,
        truth=truth,
    )


# ------------------------------------------------------------------------------------------
# Every label from constructed records


def test_every_label_is_documented_and_coloured():
    assert set(an.DESCRIPTIONS) == set(an.COLOURS) == set(an.LABELS)
    assert len(set(an.LABELS)) == len(an.LABELS) == 12
    for label in an.LABELS:
        assert f"``{label}``" in an.__doc__


def test_success_and_faulted_need_no_history():
    assert an.diagnose(record(None, knot="trefoil")).label == an.SUCCESS
    d = an.diagnose(record(None, knot=None, fault="joint 2 velocity limit"))
    assert (d.label, d.outcome) == (an.FAULTED, an.FAULTED)
    assert d.reason == "fault: joint 2 velocity limit"
    # A trefoil with a fault is a fault, not a success.
    assert an.diagnose(record(None, knot="trefoil", fault="torque")).label == an.FAULTED


def test_no_contact():
    d = an.diagnose(record("l" * 30, contact=None))
    assert d.label == an.NO_CONTACT and d.history_source is None


def test_touched_but_never_through():
    d = an.diagnose(record("l" * 40, contact=0.1))
    assert d.label == an.NOT_THROUGH
    assert d.history_source == "truth" and d.trefoil_runs == ()
    assert d.reason.startswith("contact at 0.100 s; no trefoil in 9 verdicts (truth)")


def test_trefoil_that_appears_then_disappears_slipped_out():
    # 8 frames = 0.08 s of trefoil, judged every 0.04 s from the contact at 0.1 s.
    d = an.diagnose(record("l" * 20 + "T" * 8 + "l" * 20, contact=0.1))
    assert d.label == an.SLIPPED_OUT
    ((start, end),) = d.trefoil_runs
    assert end - start == pytest.approx(0.08) and end - start < an.PERSIST_S
    assert start == pytest.approx(0.2)


def test_trefoil_that_persists_then_is_lost_shaken_loose():
    d = an.diagnose(record("l" * 20 + "T" * 40 + "l" * 20, contact=0.1))
    assert d.label == an.SHAKEN_LOOSE
    ((start, end),) = d.trefoil_runs
    assert (start, end) == pytest.approx((0.2, 0.6))
    assert "lost at 0.60 s" in d.reason


def test_a_trefoil_at_the_end_is_a_success_even_after_slipping():
    d = an.diagnose(record("l" * 20 + "T" * 8 + "l" * 8 + "T" * 10, knot="trefoil"))
    assert d.label == an.SUCCESS


def test_end_verdict_from_truth_when_the_record_has_none():
    assert an.diagnose(record("l" * 10 + "T" * 10, knot=None)).label == an.SUCCESS
    assert an.diagnose(record("l" * 10 + "T" * 30 + "l" * 2, knot=None)).knot == "unknot"


def test_other_knot():
    for name in ("4_1", "other"):
        d = an.diagnose(record(None, knot=name))
        assert d.label == an.OTHER_KNOT and d.knot == name


def test_a_knot_on_the_floor_is_its_own_failure():
    rec = record("l" * 10 + "T" * 30, knot="trefoil")
    on_floor = Verdict("on_floor", "trefoil", {"trefoil": 31}, (20, 30), 0.8)
    d = an.diagnose(dataclasses.replace(rec, verdict=on_floor))
    assert (d.label, d.knot) == (an.ON_FLOOR, "trefoil")
    assert an.diagnose(rec).label == an.SUCCESS


def test_markers_lost_before_t_c_keeps_the_outcome():
    rec = record("l" * 12 + "T" * 24 + "l" * 8, contact=0.1, lost_from=0.12)
    d = an.diagnose(rec, t_c=0.3)
    assert (d.label, d.outcome) == (an.MARKERS_LOST, an.SHAKEN_LOOSE)
    assert d.tracking_lost_time == pytest.approx(0.12)
    assert d.reason.startswith("tracking lost at 0.120 s <= t_c 0.300 s; then shaken_loose")
    assert an.diagnose(rec, t_c=0.1).label == an.SHAKEN_LOOSE  # lost after t_c
    assert an.diagnose(rec).label == an.SHAKEN_LOOSE  # no t_c: not checked


def test_tracking_lost_time_bridges_short_dropouts():
    t = np.arange(40) * 0.005
    m = np.zeros((40, 11, 3))
    m[5, 3] = np.nan  # one marker, one frame: bridged
    m[10:12, 0] = np.nan  # 10 ms: bridged
    assert an.tracking_lost_time(t, m) is None
    m[20:23, 7] = np.nan  # 15 ms: lost
    assert an.tracking_lost_time(t, m) == pytest.approx(0.1)
    m2 = np.zeros((40, 11, 3))
    m2[39] = np.nan  # one frame, but through the end of the record
    assert an.tracking_lost_time(t, m2) == pytest.approx(0.195)


def test_trefoil_runs_last_from_midpoint_to_midpoint():
    h = an.KnotHistory(
        (0.0, 1.0, 2.0, 3.0, 4.0), ("trefoil", "trefoil", "unknot", "unknot", "trefoil"), "metadata"
    )
    assert h.trefoil_runs() == ((0.0, 1.5), (3.5, 4.0))
    h = an.KnotHistory((0.0, 0.1, 0.2), ("unknot", "trefoil", "unknot"), "truth")
    ((start, end),) = h.trefoil_runs()
    assert (start, end) == pytest.approx((0.05, 0.15))


def test_history_frames_every_step_from_start_and_the_last():
    t, c = frames("l" * 23)
    h = an.knot_history_from_truth(t, c, start=0.05, step=0.04)
    assert h.t == pytest.approx((0.05, 0.09, 0.13, 0.17, 0.21, 0.22))
    assert set(h.verdicts) == {"unknot"} and h.source == "truth"


def test_thresholds_are_parameters():
    rec = record("l" * 20 + "T" * 8 + "l" * 20, contact=0.1)
    params = an.AnatomyParams(persist_s=0.05)
    assert an.diagnose(rec, params=params).label == an.SHAKEN_LOOSE
    with pytest.raises(ConfigError, match=r"^persist_s: must be a finite number > 0, got 0$"):
        an.AnatomyParams(persist_s=0)
    with pytest.raises(ConfigError, match=r"^n_directions: must be an integer >= 1, got 2.5$"):
        an.AnatomyParams(n_directions=2.5)
    with pytest.raises(ConfigError, match=r"^t_c: must be a finite number >= 0, got -1$"):
        an.diagnose(rec, t_c=-1)
    with pytest.raises(ConfigError, match=r"^trial: must be a TrialRecord or TrialEvidence"):
        an.diagnose({"knot": "unknot"})


# ------------------------------------------------------------------------------------------
# Without truth (the hardware cell)


def hardware(history: dict | None = None, nested: bool = False, **kw) -> TrialRecord:
    meta: dict = {"cell": "hardware", "rope": 1}
    if history is not None:
        if nested:
            meta["settle"] = {"settled": True, "knot_history": history}
        else:
            meta["knot_history"] = history
    return record(None, contact=None, metadata=meta, **kw)


def test_hardware_without_truth_says_unknown_where_truth_is_needed():
    d = an.diagnose(hardware())
    assert d.label == an.UNKNOWN and "needs truth" in d.reason
    assert an.diagnose(hardware(knot="trefoil")).label == an.SUCCESS
    assert an.diagnose(hardware(knot=None, fault="torque")).label == an.FAULTED
    assert an.diagnose(hardware(knot="4_1")).label == an.OTHER_KNOT
    d = an.diagnose(hardware(lost_from=0.2), t_c=0.25)
    assert (d.label, d.outcome) == (an.MARKERS_LOST, an.UNKNOWN)
    # An operator-annotated contact does not make a history appear.
    assert an.diagnose(record(None, contact=0.1, metadata={"cell": "hardware"})).label == (
        an.UNKNOWN
    )


@pytest.mark.parametrize("nested", [False, True])
def test_hardware_uses_the_labs_knot_history(nested):
    t = [0.9, 1.15, 1.4, 1.65, 1.9]
    held = {"t": t, "verdict": ["trefoil", "trefoil", "trefoil", "unknot", "unknot"]}
    d = an.diagnose(hardware(held, nested))
    assert d.label == an.SHAKEN_LOOSE and d.history_source == "metadata"
    brief = {"t": t, "verdict": ["unknot", "trefoil", "unknot", "unknot", "unknot"]}
    assert an.diagnose(hardware(brief, nested), params=an.AnatomyParams(persist_s=0.3)).label == (
        an.SLIPPED_OUT
    )
    # No trefoil in a history that starts 0.8 s after the contact: a slip may hide before it.
    never = {"t": t, "verdict": ["unknot"] * 5}
    assert an.diagnose(hardware(never, nested)).label == an.UNKNOWN
    d = an.diagnose(hardware(never, nested))
    assert d.reason == (
        "no contact time; no trefoil in the metadata history (without a contact time a slip "
        "before it cannot be ruled out)"
    )
    # A fine history from the contact on rules a slip out.
    dense = {"t": list(np.arange(0.88, 1.2, 0.04)), "verdict": ["unknot"] * 8}
    rec = record(None, contact=0.85, metadata={"cell": "hardware", "knot_history": dense})
    assert an.diagnose(rec).label == an.NOT_THROUGH
    rec = record(None, contact=0.8, metadata={"cell": "hardware", "knot_history": dense})
    d = an.diagnose(rec)
    assert d.label == an.UNKNOWN
    assert d.reason.endswith(
        "(its verdicts are up to 0.08 s apart from the contact on, a slip could fall between them)"
    )


def test_a_malformed_knot_history_names_the_problem():
    bad = {"t": [0.0, 1.0], "verdict": ["unknot"]}
    with pytest.raises(RecordError, match=r"^knot history: 2 times but 1 verdicts"):
        an.diagnose(hardware(bad))


def test_settle_metadata_adds_a_note():
    meta = {
        "cell": "sim",
        "settle": {"settled": False, "settle_s": 15.0, "free_end_speed_m_s": 0.12},
    }
    d = an.diagnose(record("l" * 30, contact=0.1, metadata=meta))
    assert d.label == an.NOT_THROUGH
    assert d.reason.endswith("; judged not at rest (after 15.0 s, free end up to 0.12 m/s)")
    meta["settle"] = {**meta["settle"], "knot_set": True, "settle_s": 4.0}
    d = an.diagnose(record("l" * 30, contact=0.1, metadata=meta))
    assert d.reason.endswith("; judged with its knot set (after 4.0 s, free end up to 0.12 m/s)")
    settle = {**meta["settle"], "knot_set": False, "unknot_held": True, "settle_s": 3.5}
    meta["settle"] = {**settle, "criterion": {"unknot_held_s": 3.0}}
    d = an.diagnose(record("l" * 30, contact=0.1, metadata=meta))
    assert d.reason.endswith(
        "; judged unknotted at every verdict of the last 3 s (after 3.5 s, free end up to 0.12 m/s)"
    )


# ------------------------------------------------------------------------------------------
# A real trial of the simulated lab


def test_real_sim_trial(tmp_path):
    from flyknot.constants import DEMOS_DIR
    from flyknot_sim.lab import LabParams, SimLab
    from learner.bezier import BezierCommand

    z = np.load(DEMOS_DIR / "seeds" / "robot_command.npz")
    command = BezierCommand(z["knots"], float(z["T"])).joint_command()
    rec = SimLab(LabParams(rope=1, seed=0, settle_s=0.3)).run(command)
    rec.save(tmp_path / "trial")
    anatomy = ar.explain_directory(tmp_path, t_c=0.65)
    (d,) = anatomy.diagnoses
    assert d.name == "trial" and d.group == "rope 1" and d.t_c == 0.65
    assert (d.label == an.SUCCESS) == rec.succeeded
    assert d.first_contact_time == rec.first_contact_time
    if rec.first_contact_time is not None:
        # The lab loses the markers 20 ms after the first contact.
        assert d.tracking_lost_time == pytest.approx(rec.first_contact_time + 0.02, abs=0.006)
    if not rec.succeeded and rec.fault is None and rec.first_contact_time is not None:
        assert d.history_source == "truth"
        assert d.outcome in (an.NOT_THROUGH, an.SLIPPED_OUT, an.SHAKEN_LOOSE, an.OTHER_KNOT)
    # Without truth the same record still gets a label; only history-based ones degrade.
    (tmp_path / "trial.truth.npz").unlink()
    (bare,) = ar.explain_directory(tmp_path, t_c=0.65).diagnoses
    if d.outcome in (an.SUCCESS, an.FAULTED, an.NO_CONTACT, an.OTHER_KNOT):
        assert bare.label == d.label
    else:
        assert bare.outcome in (d.outcome, an.UNKNOWN)


# ------------------------------------------------------------------------------------------
# Directories


def write_replay(path: Path, spec: str, *, contact, outcome, source: str, rope: int = 1):
    t_truth, centreline = frames(spec)
    t = np.arange(0.0, len(spec) * DT, 0.005)
    markers = np.tile(LINE[::4][:11], (len(t), 1, 1))
    if contact is not None:
        markers[t >= contact + 0.02 - 1e-9] = np.nan
    meta = {
        "format_version": 1,
        "t_c": contact,
        "rope": rope,
        "metadata": {"kind": "replay", "source": source, "outcome": outcome, "index": 0},
    }
    np.savez_compressed(
        path,
        t=t,
        hand_pos=np.tile(HAND, (len(t), 1)),
        hand_quat=np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1)),
        markers=markers,
        t_truth=t_truth,
        centreline=centreline,
        meta=np.array(json.dumps(meta)),
    )


def demo_file(path: Path, t_c: float) -> Path:
    from flyknot.demo import Demonstration

    t = np.arange(0.0, 0.5, 0.005)
    Demonstration(
        t=t,
        hand_pos=np.tile(HAND, (len(t), 1)),
        hand_quat=np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1)),
        markers=np.tile(LINE[::4][:11], (len(t), 1, 1)),
        t_c=t_c,
    ).save(path)
    return path


def test_replay_directory(tmp_path):
    demo = demo_file(tmp_path / "demo.npz", t_c=0.2)
    out = tmp_path / "replays"
    out.mkdir()
    write_replay(
        out / "replay_000.npz",
        "l" * 10 + "T" * 10,
        contact=0.1,
        outcome="trefoil",
        source=str(demo),
    )
    write_replay(out / "replay_001.npz", "l" * 30, contact=None, outcome="unknot", source=str(demo))
    # First contact 0.05 s: markers lost at 0.07 s, before the demonstration's t_c 0.2 s.
    write_replay(out / "replay_002.npz", "l" * 30, contact=0.05, outcome="unknot", source=str(demo))
    anatomy = ar.explain_directory(out)
    labels = [(d.name, d.label, d.outcome) for d in anatomy.diagnoses]
    assert labels == [
        ("replay_000", an.SUCCESS, an.SUCCESS),
        ("replay_001", an.NO_CONTACT, an.NO_CONTACT),
        ("replay_002", an.MARKERS_LOST, an.NOT_THROUGH),
    ]
    assert anatomy.groups() == ("rope 1",)
    assert anatomy.t_c_sources == ("rope 1: 0.200 s",)
    assert anatomy.counts() == {
        **dict.fromkeys(an.LABELS, 0),
        "success": 1,
        "no_contact": 1,
        "markers_lost": 1,
    }


def run_directory(root: Path) -> Path:
    """A run directory as ``flyknot run`` writes it: two runs with result.json (t_c)."""
    specs = {
        "rope1": [("trefoil", "l" * 20), ("unknot", "l" * 20)],
        "rope2": [("unknot", "l" * 20 + "T" * 8 + "l" * 10), (None, None)],
    }
    for run, trials in specs.items():
        rd = root / "runs" / run
        for k, (knot, spec) in enumerate(trials):
            fault = "joint 4 torque limit" if spec is None else None
            record(spec, knot=knot, fault=fault).save(rd / "learning" / f"trial_{k:04d}_a0")
        (rd / "result.json").write_text(json.dumps({"name": run, "t_c": 0.15}))
    (root / "manifest.json").write_text("{}")
    (root / "initial_guess").mkdir()
    np.savez(root / "initial_guess" / "robot.npz", knots=np.zeros((10, 8)))
    return root


def test_run_directory_groups_by_run(tmp_path):
    root = run_directory(tmp_path)
    # Without its result.json a run's t_c comes from the run directory's summary.json.
    (root / "runs" / "rope2" / "result.json").unlink()
    summary = {"runs": [{"name": "rope1", "t_c": 0.5}, {"name": "rope2", "t_c": 0.25}]}
    (root / "summary.json").write_text(json.dumps(summary))
    anatomy = ar.explain_directory(root)
    assert anatomy.groups() == ("rope1", "rope2")
    assert [d.label for d in anatomy.diagnoses] == [
        an.SUCCESS,
        an.NOT_THROUGH,
        an.SLIPPED_OUT,
        an.FAULTED,
    ]
    assert [d.t_c for d in anatomy.diagnoses] == [0.15, 0.15, 0.25, 0.25]
    assert anatomy.t_c_sources == ("rope1: 0.150 s", "rope2: 0.250 s")
    # Diagnosed on two worker processes: the same anatomy, in the same order; a progress
    # wrapper sees every file.
    seen = []

    def count(files):
        for f in files:
            seen.append(f.name)
            yield f

    assert ar.explain_directory(root, workers=2, progress=count) == anatomy
    assert len(seen) == 4
    with pytest.raises(ConfigError, match=r"^workers: must be an integer >= 1, got 0$"):
        ar.explain_directory(root, workers=0)
    # A run's own learning folder finds the run's result.json one level up.
    (d,) = ar.explain_directory(root / "runs" / "rope1" / "learning").diagnoses[1:]
    assert (d.t_c, d.group) == (0.15, "rope 1")
    assert anatomy.counts("rope2")[an.FAULTED] == 1
    with pytest.raises(
        ConfigError, match=r"^group: unknown value 'rope3' \(valid choices: rope1, rope2\)$"
    ):
        anatomy.counts("rope3")


def test_bad_directories_name_the_path(tmp_path):
    missing = tmp_path / "missing"
    with pytest.raises(ConfigError) as e:
        ar.explain_directory(missing)
    assert str(e.value) == f"directory: {str(missing)!r} does not exist"
    a_file = tmp_path / "f.txt"
    a_file.write_text("x")
    with pytest.raises(ConfigError) as e:
        ar.explain_directory(a_file)
    assert str(e.value) == f"directory: {str(a_file)!r} is not a directory"
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError) as e:
        ar.explain_directory(empty)
    assert str(e.value) == (
        f"directory: {str(empty)!r} holds no trial records (<stem>.json with <stem>.npz) "
        "and no replay files (replay_*.npz)"
    )


def test_malformed_files_name_the_file(tmp_path):
    bad = tmp_path / "replay_000.npz"
    np.savez(bad, t=np.zeros(3), meta=np.array("{}"))
    with pytest.raises(RecordError) as e:
        ar.explain_directory(tmp_path)
    assert str(e.value) == f"replay file {str(bad)!r} lacks arrays: markers"
    bad.unlink()
    (tmp_path / "trial.npz").write_bytes(b"")
    (tmp_path / "trial.json").write_text("{not json")
    with pytest.raises(RecordError, match=r"^'.*trial.json' is not a readable record \("):
        ar.explain_directory(tmp_path)


# ------------------------------------------------------------------------------------------
# CLI and report


def assert_png_not_blank(path: Path) -> None:
    import matplotlib.image as mpimg

    assert path.is_file() and path.stat().st_size > 1000
    img = mpimg.imread(path)[..., :3]
    assert img.std() > 0.05
    assert (img.min(axis=-1) < 0.9).mean() > 0.02  # more than 2 % of pixels not white


def test_cli_explain_prints_the_table_and_writes_the_figure(tmp_path, capsys):
    root = run_directory(tmp_path / "run")
    assert main(["explain", str(root)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0] == f"failure anatomy of {root}: 4 trials"
    assert "  t_c: rope1: 0.150 s" in lines and "  t_c: rope2: 0.150 s" in lines
    row = next(line for line in lines if line.startswith("success "))
    assert row.split()[-3:] == ["1", "25", "%"]
    assert any(line.startswith("slipped_out ") for line in lines)
    assert "per group (count, share):" in lines
    assert lines[-1] == f"figure: {root / 'anatomy.png'}"
    assert_png_not_blank(root / "anatomy.png")
    # --out puts the figure elsewhere, --tc overrides t_c, --json prints one object.
    fig = tmp_path / "fig" / "a.png"
    assert main(["explain", str(root), "--json", "--out", str(fig), "--tc", "0.5"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["figure"] == str(fig) and data["t_c_sources"] == ["t_c 0.500 s (given)"]
    assert data["counts"]["faulted"] == 1 and len(data["trials"]) == 4
    assert data["groups"]["rope2"]["slipped_out"] == 1
    assert_png_not_blank(fig)


def test_format_table_lists_trials_on_request(tmp_path):
    anatomy = ar.explain_directory(run_directory(tmp_path))
    text = ar.format_table(anatomy, trials=True)
    assert "runs/rope2/learning/trial_0001_a0  faulted          fault: joint 4 torque limit" in text
    assert "trials:" not in ar.format_table(anatomy)


def test_cli_explain_errors_are_one_line(tmp_path, capsys):
    assert main(["explain", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert err == f"flyknot: error: directory: {str(tmp_path / 'nope')!r} does not exist\n"
    assert main(["explain", str(tmp_path), "--out", str(tmp_path / "a.jpg")]) == 2
    assert "--out: must be a .png file" in capsys.readouterr().err
    assert main(["explain", str(tmp_path), "--tc", "-1"]) == 2
    assert (
        capsys.readouterr().err == "flyknot: error: --tc: must be a finite number >= 0, got -1.0\n"
    )


def test_report_has_an_anatomy_section(egl, tmp_path):
    from flyknot_app.reports.report import write_report
    from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary

    root = run_directory(tmp_path)
    runs = tuple(
        RunSummary(
            {"name": name, "label": name, "rope": rope, "demo": "robot"},
            costs=[1.0, 0.5],
            knots=[False, name == "rope1"],
            trials_to_success=2 if name == "rope1" else None,
            t_c=0.15,
        )
        for name, rope in (("rope1", 1), ("rope2", 2))
    )
    text = write_report(root, ScenarioSummary("s", "learn", runs)).read_text()
    section = text.split("## Failure anatomy")[1].split("## Figures")[0]
    assert "| success | knot in the hanging rope, no fault | 1 | 25 % |" in section
    assert "| run | n | success | faulted | not_through | slipped_out |" in section
    assert "| rope2 | 2 | 0 | 1 | 0 | 1 |" in section
    assert "![anatomy](anatomy.png)" in section
    assert_png_not_blank(root / "anatomy.png")


def test_report_section_without_trials_says_why(tmp_path):
    lines = ar.report_section(tmp_path)
    assert lines[0] == "## Failure anatomy"
    assert lines[2].startswith("Not available: directory: ")
    assert not (tmp_path / "anatomy.png").exists()


def test_stored_diagnoses_are_read_back_only_when_they_still_fit(tmp_path):
    from flyknot.constants import DEMOS_DIR
    from flyknot_sim.lab import LabParams, SimLab
    from learner.bezier import BezierCommand

    z = np.load(DEMOS_DIR / "seeds" / "robot_command.npz")
    command = BezierCommand(z["knots"], float(z["T"])).joint_command()
    SimLab(LabParams(rope=1, seed=0, settle_s=0.3)).run(command).save(tmp_path / "trial")
    fresh = ar.explain_directory(tmp_path)
    assert ar.store_diagnoses(tmp_path) == 1
    sidecar = tmp_path / "trial.diagnosis"
    assert sidecar.is_file()
    assert ar.explain_directory(tmp_path) == fresh  # read back: the same diagnosis
    # A stored diagnosis that says something else is what a later read returns ...
    data = json.loads(sidecar.read_text())
    data["diagnosis"]["reason"] = "stored"
    sidecar.write_text(json.dumps(data))
    assert ar.explain_directory(tmp_path).diagnoses[0].reason == "stored"
    # ... but not for another t_c, and not once the record is newer than it.
    assert ar.explain_directory(tmp_path, t_c=0.5).diagnoses[0].reason != "stored"
    record = tmp_path / "trial.json"
    later = sidecar.stat().st_mtime + 5
    os.utime(record, (later, later))
    assert ar.explain_directory(tmp_path) == fresh

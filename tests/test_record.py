"""JointCommand and TrialRecord: validation, files, round trips."""

from __future__ import annotations

import numpy as np
import pytest

from flyknot.errors import CommandError, RecordError
from flyknot.record import JointCommand, TrialRecord
from tests.knot_curves import verdict


def _record(n=25, m=20, truth=True, **kw):
    rng = np.random.default_rng(0)
    markers = rng.normal(size=(m, 11, 3))
    markers[12:] = np.nan
    fields = dict(
        t_joint=np.arange(n) / 250.0,
        q_cmd=rng.normal(size=(n, 7)),
        q_meas=rng.normal(size=(n, 7)),
        t_marker=np.arange(m) / 200.0,
        markers=markers,
        fingertip_pos=rng.normal(size=(n, 3)),
        fingertip_quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        base_pose=np.array([0, 0, 1.0, 1, 0, 0, 0]),
        fault=None,
        first_contact_time=0.05,
        knot="trefoil",
        verdict=verdict("knot"),
        metadata={"cell": "sim", "rope": 1, "seed": 3},
        truth={"centreline": rng.normal(size=(4, 30, 3))} if truth else {},
    )
    fields.update(kw)
    return TrialRecord(**fields)


def test_record_round_trip(tmp_path):
    rec = _record()
    rec.save(tmp_path / "trial_0000")
    back = TrialRecord.load(tmp_path / "trial_0000.json", with_truth=True)
    for name in TrialRecord._ARRAYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert back.knot == "trefoil" and back.fault is None and back.first_contact_time == 0.05
    assert back.metadata == {"cell": "sim", "rope": 1, "seed": 3}
    np.testing.assert_array_equal(back.truth["centreline"], rec.truth["centreline"])
    # Without asking for truth, none is loaded.
    assert TrialRecord.load(tmp_path / "trial_0000").truth == {}
    assert back.succeeded and back.verdict == rec.verdict
    # A trefoil wrapped round the held end is not a success, nor is a record without verdict.
    assert not _record(verdict=verdict("wrapped_at_grip")).succeeded
    assert not _record(verdict=None).succeeded


def test_record_arrays_are_read_only():
    rec = _record()
    with pytest.raises(ValueError):
        rec.q_cmd[0, 0] = 1.0


def test_record_shape_error_names_field():
    with pytest.raises(
        RecordError, match=r"TrialRecord.q_meas must have shape \(25, 7\), got \(25, 6\)"
    ):
        _record(q_meas=np.zeros((25, 6)))


def test_record_load_missing(tmp_path):
    with pytest.raises(RecordError, match="does not exist"):
        TrialRecord.load(tmp_path / "nope")


def test_faulted_record_is_not_a_success():
    assert not _record(fault="joint 2 velocity 4 rad/s exceeds limit").succeeded


@pytest.mark.parametrize("suffix", [".csv", ".npy"])
def test_command_round_trip(tmp_path, suffix):
    q = np.random.default_rng(1).normal(size=(50, 7))
    JointCommand(q).save(tmp_path / f"c{suffix}")
    back = JointCommand.load(tmp_path / f"c{suffix}")
    np.testing.assert_allclose(back.q, q, rtol=1e-9, atol=1e-9)
    assert back.rate_hz == pytest.approx(250.0)


def test_command_shape_error():
    with pytest.raises(CommandError, match=r"command q must have shape \(n, 7\), got \(10, 6\)"):
        JointCommand(np.zeros((10, 6)))


def test_command_nan_error():
    q = np.zeros((10, 7))
    q[4, 2] = np.nan
    with pytest.raises(CommandError, match="1 non-finite value\\(s\\); first at sample 4, joint 3"):
        JointCommand(q)


def test_command_csv_errors(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t,a,b\n0,1,2\n")
    with pytest.raises(CommandError, match="header must be 't,q1,q2,q3,q4,q5,q6,q7'"):
        JointCommand.load(p)
    p.write_text("t,q1,q2,q3,q4,q5,q6,q7\n0,0,0,0,0,0,0,0\n0.004,0,0,0,x,0,0,0\n")
    with pytest.raises(CommandError, match="line 3"):
        JointCommand.load(p)
    p.write_text(
        "t,q1,q2,q3,q4,q5,q6,q7\n0,0,0,0,0,0,0,0\n0.004,0,0,0,0,0,0,0\n0.010,0,0,0,0,0,0,0\n"
    )
    with pytest.raises(CommandError, match="uniformly spaced"):
        JointCommand.load(p)
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(
        CommandError, match=r"unknown extension '.txt' \(valid choices: .csv, .npy\)"
    ):
        JointCommand.load(tmp_path / "x.txt")
    with pytest.raises(CommandError, match="does not exist"):
        JointCommand.load(tmp_path / "missing.csv")


def test_a_record_cut_short_is_not_written(tmp_path):
    """A truth file truncated by a kill (a writer without atomic renames) is unreadable: the
    record counts as not written, and resuming plays the trial again."""
    from flyknot.errors import RecordError
    from flyknot_app.runner import _written_with_truth
    from learner.run_directory import written_record

    rec = _record()
    stem = tmp_path / "trial_0001_a0"
    json_path = rec.save(stem)
    assert written_record(stem) is not None and _written_with_truth(stem) is not None
    truth = tmp_path / "trial_0001_a0.truth.npz"
    truth.write_bytes(truth.read_bytes()[:100])
    with pytest.raises(RecordError, match=r"truth\.npz' is not a readable array file"):
        TrialRecord.load(stem, with_truth=True)
    assert _written_with_truth(stem) is None  # the application reads truth, the learner not
    arrays = tmp_path / "trial_0001_a0.npz"
    arrays.write_bytes(arrays.read_bytes()[:100])
    assert written_record(stem) is None
    json_path.unlink()
    assert written_record(stem) is None
    assert not list(tmp_path.glob(".*.tmp"))  # the writer leaves no temporary file


def test_a_ledger_line_cut_short_is_dropped(tmp_path):
    from flyknot.errors import RecordError
    from learner.run_directory import RunDirectory, TrialSummary

    rd = RunDirectory(tmp_path)
    row = TrialSummary(0, 0, None, "unknot", False, 0.5, True, "solved", 0.4, "update", 1.0)
    rd.append_ledger(row)
    with open(tmp_path / "ledger.jsonl", "a") as f:
        f.write('{"trial": 1, "att')
    assert rd.ledger() == [row]
    rd.append_ledger(row)  # the cut line is dropped before the next is written
    assert rd.ledger() == [row, row]
    (tmp_path / "ledger.jsonl").write_text('{"trial": 1}\n' + "x\n")
    with pytest.raises(RecordError, match=r"ledger\.jsonl' line 1 is not a ledger line"):
        rd.ledger()


def test_a_records_outcome_is_read_from_its_json_alone(tmp_path):
    from flyknot.record import read_outcome

    stem = tmp_path / "trial_0001"
    rec = _record(fault="joint 2 velocity 4 rad/s exceeds limit", verdict=None)
    rec.save(stem)
    (tmp_path / "trial_0001.npz").unlink()  # the arrays are not read
    assert read_outcome(stem) == (rec.fault, "trefoil", None)
    _record().save(tmp_path / "trial_0002")
    for name in ("trial_0002", "trial_0002.json", "trial_0002.npz"):
        assert read_outcome(tmp_path / name) == (None, "trefoil", verdict("knot"))
    with pytest.raises(RecordError) as err:
        read_outcome(tmp_path / "nope")
    assert str(err.value) == f"trial record file {str(tmp_path / 'nope.json')!r} does not exist"
    (tmp_path / "old.json").write_text(
        '{"format_version": 0, "fault": null, "fault_time": null, "first_contact_time": null,'
        ' "knot": "unknot", "metadata": {}}'
    )
    with pytest.raises(RecordError, match=r"format_version 0 is not supported \(valid choices"):
        read_outcome(tmp_path / "old")

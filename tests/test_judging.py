"""``flyknot judge``: a run directory judged again, its pictures, and bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from flyknot.geometry import matrix_to_quat, min_rotation
from flyknot.record import TrialRecord
from flyknot_app.cli import main
from flyknot_app.judging import picture_rows, rejudge_directory, totals
from tests.knot_curves import verdict

DATA = Path(__file__).parent / "data" / "verdicts"

# Recorded trials of the lab with the knot their runs were given by the plurality of free
# ray closures (the coin flip of a wrap at the grip said "trefoil" here).
TRIALS = {
    "trial_0000_a0": ("unknot_rope1_trial1", "unknot"),
    "trial_0001_a0": ("wrapped_rope1_main_job_trial4", "trefoil"),
    "trial_0002_a0": ("knot_rope1_repeat", "trefoil"),
}


def _record(stem: str, knot: str | None, fault: str | None = None) -> TrialRecord:
    c = np.load(DATA / f"{stem}.npy")
    n, m = 5, 3
    quat = matrix_to_quat(min_rotation([0.0, 0.0, 1.0], c[1] - c[0]))  # z out of the tube
    markers = c[np.linspace(1, len(c) - 1, 11).round().astype(int)]
    return TrialRecord(
        t_joint=np.arange(n) / 250.0,
        q_cmd=np.zeros((n, 7)),
        q_meas=np.zeros((n, 7)),
        t_marker=np.arange(m) / 200.0,
        markers=np.tile(markers, (m, 1, 1)),
        fingertip_pos=np.tile(c[0], (n, 1)),
        fingertip_quat=np.tile(quat, (n, 1)),
        base_pose=np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]),
        fault=fault,
        knot=knot,
        metadata={"cell": "sim", "rope": 1},
        truth={"t_truth": np.array([0.0, 1.0]), "centreline": np.stack([c, c])},
    )


@pytest.fixture
def run_dir(tmp_path):
    learning = tmp_path / "run" / "runs" / "rope1" / "learning"
    for name, (stem, knot) in TRIALS.items():
        _record(stem, knot).save(learning / name)
    _record("knot_rope1_repeat", None, fault="joint 4 torque limit").save(
        learning / "trial_0003_a0"
    )
    return tmp_path / "run"


def test_old_and_new_verdicts_per_trial_and_the_totals(run_dir, capsys):
    assert main(["judge", str(run_dir)]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split()[1:3] for line in out[2:6]}
    assert rows["runs/rope1/learning/trial_0000_a0"] == ["unknot", "unknot"]
    assert rows["runs/rope1/learning/trial_0001_a0"] == ["trefoil", "wrapped_at_grip"]
    assert rows["runs/rope1/learning/trial_0002_a0"] == ["trefoil", "knot"]
    assert rows["runs/rope1/learning/trial_0003_a0"] == ["fault", "fault"]
    assert "31/31 trefoil  0.00 m (vertices 0-10)" in out[3]
    assert out[6] == "knots: 2 counted when run, 1 now"
    assert out[7] == "now: fault 1, knot 1, unknot 1, wrapped_at_grip 1"
    assert not (run_dir / "judge").exists()  # nothing written without --pictures


def test_json_and_pictures(egl, run_dir, capsys, tmp_path):
    assert main(["judge", str(run_dir), "--json", "--pictures", "--out", str(tmp_path / "p")]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["totals"]["knots_new"] == 1 and data["totals"]["knots_old"] == 2
    assert data["totals"]["old_to_new"]["trefoil -> wrapped_at_grip"] == 1
    new = {t["name"].split("/")[-1]: t["new"] for t in data["trials"]}
    assert new["trial_0002_a0"]["klass"] == "knot" and new["trial_0002_a0"]["core"] is not None
    assert new["trial_0003_a0"] is None
    # Every knot and one trial of each other class, captioned renders side by side.
    names = sorted(Path(p).name for p in data["pictures"])
    assert names == [
        "runs__rope1__learning__trial_0000_a0.unknot.png",
        "runs__rope1__learning__trial_0001_a0.wrapped_at_grip.png",
        "runs__rope1__learning__trial_0002_a0.knot.png",
    ]
    knot = imageio.imread(tmp_path / "p" / names[2])
    assert knot.shape == (480, 1280, 3) and knot.std() > 10  # the rope, and a zoom on its core
    wrap = imageio.imread(tmp_path / "p" / names[1])
    assert wrap.shape == (480, 1280, 3)


def test_picture_rows_are_every_knot_then_one_per_class(run_dir):
    rows = rejudge_directory(run_dir)
    assert [r.new_class for r in picture_rows(rows)] == ["knot", "unknot", "wrapped_at_grip"]
    assert totals(rows)["classes_new"] == {
        "unknot": 1,
        "wrapped_at_grip": 1,
        "knot": 1,
        "fault": 1,
    }


def _listing(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


@pytest.mark.parametrize("case", ["missing", "empty", "corrupt"])
def test_bad_input_is_one_line_exit_2_nothing_written(case, run_dir, tmp_path, capsys):
    target = {"missing": tmp_path / "nowhere", "empty": tmp_path / "empty", "corrupt": run_dir}[
        case
    ]
    bad = run_dir / "runs" / "rope1" / "learning" / "trial_0002_a0.json"
    if case == "empty":
        target.mkdir()
    if case == "corrupt":
        bad.write_text('{"format_version": 1, "fault": nu')
    before = _listing(tmp_path)
    assert main(["judge", str(target), "--pictures"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    expected = {
        "missing": f"flyknot: error: directory: {str(target)!r} does not exist",
        "empty": f"flyknot: error: directory: {str(target)!r} holds no trial records",
        "corrupt": f"flyknot: error: '{bad}' is not a readable record (",
    }[case]
    assert err[0].startswith(expected), err[0]
    assert _listing(tmp_path) == before


def test_a_stored_verdict_is_the_old_class(run_dir, capsys):
    learning = run_dir / "runs" / "rope1" / "learning"
    rec = TrialRecord.load(learning / "trial_0001_a0", with_truth=True)
    dataclasses.replace(rec, verdict=verdict("wrapped_at_grip")).save(learning / "trial_0001_a0")
    (row,) = [r for r in rejudge_directory(run_dir) if r.name.endswith("trial_0001_a0")]
    assert row.old_class == "wrapped_at_grip" and not row.old_success


def test_the_viewer_shows_the_verdict(run_dir):
    from flyknot_app.viewer.server import _title
    from flyknot_app.viewer.trials import ViewTrial

    rec = _record("knot_rope1_repeat", "trefoil")
    rec = dataclasses.replace(rec, verdict=verdict("knot"))
    text = _title(ViewTrial("t", run_dir, 0.6), rec)
    assert "verdict: knot (trefoil 31/31, 0.40 m down)" in text
    assert "verdict: not judged" in _title(
        ViewTrial("t", run_dir, None), _record("unknot_rope1_trial1", None)
    )


def test_the_report_shows_every_knot_and_one_trial_per_class(egl, run_dir):
    from flyknot_app.judging import report_section

    learning = run_dir / "runs" / "rope1" / "learning"
    rec = TrialRecord.load(learning / "trial_0001_a0", with_truth=True)
    # A stored verdict (e.g. an operator's) is the one the report shows.
    dataclasses.replace(rec, verdict=verdict("knot")).save(learning / "trial_0001_a0")
    # A picture of a verdict no longer given (the trial judged or played again) goes.
    stale = run_dir / "verdicts" / "runs__rope1__learning__trial_0001_a0.on_floor.png"
    stale.parent.mkdir(exist_ok=True)
    stale.write_bytes(b"old")
    lines = report_section(run_dir)
    assert not stale.exists()
    assert lines[0] == "## Verdicts"
    assert lines[2].startswith("2 of 3 trials without a fault left an overhand knot")
    rows = [x for x in lines if x.startswith("| runs/")]
    assert [r.split(" | ")[1].split(" (")[0] for r in rows] == ["knot", "knot", "unknot"]
    pictures = sorted((run_dir / "verdicts").glob("*.png"))
    assert len(pictures) == 3 and all(
        f"]({p.relative_to(run_dir)})" in "".join(rows) for p in pictures
    )


def test_a_learned_command_replays_from_its_run(tmp_path):
    """``flyknot trial --command RUN/runs/NAME/final_knots.npy`` plays the learned command."""
    from flyknot.errors import CommandError
    from flyknot_app.trial_cli import load_command
    from learner.bezier import BezierCommand

    knots = np.load(Path(__file__).parent.parent / "assets/demos/seeds/robot_command.npz")["knots"]
    run = tmp_path / "runs" / "rope1"
    run.mkdir(parents=True)
    np.save(run / "final_knots.npy", knots)
    with pytest.raises(CommandError, match=r"result\.json beside it, which is missing"):
        load_command(run / "final_knots.npy")
    (run / "result.json").write_text(json.dumps({"T": 0.9}))
    got = load_command(run / "final_knots.npy")
    np.testing.assert_array_equal(got.q, BezierCommand(knots, 0.9).joint_command().q)
    np.savez(tmp_path / "k.npz", knots=knots, T=0.9)
    np.testing.assert_array_equal(load_command(tmp_path / "k.npz").q, got.q)


def test_a_learning_trial_s_command_replays_with_its_run_s_duration(tmp_path):
    """``RUN/learning/knots_NNNN.npy`` takes T from ``RUN/result.json``, not from beside it."""
    from flyknot.errors import CommandError
    from flyknot_app.trial_cli import load_command
    from learner.bezier import BezierCommand

    knots = np.load(Path(__file__).parent.parent / "assets/demos/seeds/robot_command.npz")["knots"]
    learning = tmp_path / "rope4" / "learning"
    learning.mkdir(parents=True)
    np.save(learning / "knots_0002.npy", knots)
    with pytest.raises(CommandError) as e:
        load_command(learning / "knots_0002.npy")
    assert str(e.value).startswith(
        f"command file {str(learning / 'knots_0002.npy')!r} holds Bezier knots (10, 8): their "
        f"duration T is read from the run's {str(tmp_path / 'rope4' / 'result.json')!r}, "
        "which is missing (or give an .npz with knots and T)"
    )
    (learning / "result.json").write_text(json.dumps({"T": 0.5}))
    (tmp_path / "rope4" / "result.json").write_text(json.dumps({"t_c": 0.8}))
    with pytest.raises(CommandError) as e:
        load_command(learning / "knots_0002.npy")
    assert str(e.value).startswith(
        f"command file {str(learning / 'knots_0002.npy')!r} holds Bezier knots (10, 8), but "
        f"{str(tmp_path / 'rope4' / 'result.json')!r} holds no duration T (KeyError: 'T')"
    )
    (tmp_path / "rope4" / "result.json").write_text(json.dumps({"T": 1.044}))
    got = load_command(learning / "knots_0002.npy")
    np.testing.assert_array_equal(got.q, BezierCommand(knots, 1.044).joint_command().q)


def test_pictures_draw_the_rope_at_its_true_size():
    from flyknot_app.viewer.render import rope_radius_of

    rec = _record("knot_rope1_repeat", "trefoil")
    assert rope_radius_of(rec) == pytest.approx(0.0045)  # rope 1: 9 mm
    custom = dataclasses.replace(
        rec, metadata={"rope": "my cord", "rope_params": {"diameter": 0.006}}
    )
    assert rope_radius_of(custom) == pytest.approx(0.003)
    assert rope_radius_of(dataclasses.replace(rec, metadata={})) is None


def test_a_record_without_truth_is_judged_and_pictured_from_its_markers(egl, tmp_path, capsys):
    """A real lab's record: no simulator truth, the markers' last fully tracked frame."""
    learning = tmp_path / "run" / "runs" / "rope1" / "learning"
    rec = _record("knot_rope1_repeat", "trefoil")
    dataclasses.replace(rec, truth={}, metadata={"cell": "xarm", "rope": 1}).save(
        learning / "trial_0000_a0"
    )
    assert main(["judge", str(tmp_path / "run"), "--json", "--pictures"]) == 0
    data = json.loads(capsys.readouterr().out)
    (trial,) = data["trials"]
    assert trial["new"]["source"] == "markers"
    assert len(data["pictures"]) == 1 and Path(data["pictures"][0]).is_file()


def test_kept_verdicts_come_from_the_records_json_and_match_the_full_load(run_dir):
    from flyknot.verdict import judge_centreline
    from flyknot_app.judging import rejudge_directory

    learning = run_dir / "runs" / "rope1" / "learning"
    stored = _record("knot_rope1_repeat", "trefoil")
    stored = dataclasses.replace(stored, verdict=judge_centreline(stored.truth["centreline"][-1]))
    stored.save(learning / "trial_0004_a0")
    full = rejudge_directory(run_dir, keep_stored=True)
    (learning / "trial_0004_a0.npz").write_bytes(b"cut")  # a kept verdict needs no arrays
    (learning / "trial_0003_a0.npz").write_bytes(b"cut")  # nor does a fault
    fast = rejudge_directory(run_dir, keep_stored=True)
    assert [(r.name, r.fault, r.old_class, r.new) for r in fast] == [
        (r.name, r.fault, r.old_class, r.new) for r in full
    ]
    assert fast[-1].new == stored.verdict and fast[-2].fault == "joint 4 torque limit"


def test_a_runs_worker_draws_its_knots_as_the_report_would_and_the_report_keeps_them(egl, run_dir):
    from flyknot_app.judging import draw_run_knots, report_section

    learning = run_dir / "runs" / "rope1" / "learning"
    (drawn,) = draw_run_knots(run_dir / "runs" / "rope1", run_dir)
    assert drawn == run_dir / "verdicts" / "runs__rope1__learning__trial_0002_a0.knot.png"
    first = drawn.read_bytes()
    stamp = drawn.stat().st_mtime_ns
    report_section(run_dir)
    assert drawn.stat().st_mtime_ns == stamp  # kept, not drawn again
    assert len(list((run_dir / "verdicts").glob("*.png"))) == 3
    drawn.unlink()
    report_section(run_dir)  # the report draws it itself: the same image
    assert drawn.read_bytes() == first
    # A trial played again after its picture is drawn again.
    again = drawn.stat().st_mtime_ns
    rec = TrialRecord.load(learning / "trial_0002_a0", with_truth=True)
    rec.save(learning / "trial_0002_a0")
    report_section(run_dir)
    assert drawn.stat().st_mtime_ns > again
    # A run without knots draws nothing (its other classes are the report's choice).
    _record("unknot_rope1_trial1", None).save(run_dir / "runs" / "rope2" / "learning" / "t0")
    assert draw_run_knots(run_dir / "runs" / "rope2", run_dir) == []


def test_a_run_ends_with_its_knots_drawn(egl, monkeypatch, tmp_path):
    from flyknot_app import runner
    from flyknot_app.scenario import parse_scenario

    monkeypatch.setattr(runner, "open_cell", lambda kind, spec: object())

    def play(lab, spec, out_dir, knots0, **kw):
        _record("knot_rope1_repeat", "trefoil").save(out_dir / "runs" / "a" / "learning" / "t0")
        return "summary"

    monkeypatch.setattr(runner, "_execute_on", play)
    spec = parse_scenario({"run": [{"name": "a"}]}, name="x").runs[0]
    assert runner.execute_run(spec, tmp_path, None, resume=False, progress=False) == "summary"
    assert (tmp_path / "verdicts" / "runs__a__learning__t0.knot.png").is_file()


def _no_opengl(monkeypatch):
    """Every offscreen context refused, as on a machine without EGL or OSMesa."""
    from flyknot.errors import RenderError
    from flyknot_app.viewer import render

    def refuse(width, height):
        raise RenderError("no offscreen OpenGL context (egl: ImportError: libEGL.so.1)")

    monkeypatch.setattr(render, "_gl_context", refuse)


def test_without_opengl_a_run_ends_whole_and_its_report_says_why(run_dir, monkeypatch, capsys):
    """No pictures can be drawn: the run's post-run work and its report end all the same,
    the verdicts listed without pictures and the reason named once in each."""
    from flyknot.options import from_mapping
    from flyknot_app.judging import report_section
    from flyknot_app.runner import FINISHED, finish_run
    from flyknot_app.scenario import RunSpec

    _no_opengl(monkeypatch)
    finish_run(from_mapping(RunSpec, {"name": "rope1"}), run_dir, summary=None)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "flyknot: warning: no offscreen OpenGL context (egl: ImportError: libEGL.so.1); "
        "the knots' pictures are not drawn"
    ]
    assert (run_dir / "runs" / "rope1" / FINISHED).is_file()
    lines = report_section(run_dir)
    knot_rows = [line for line in lines if line.startswith("| runs/rope1/learning/trial_0002")]
    assert len(knot_rows) == 1 and knot_rows[0].endswith("| - |")
    reason = "no offscreen OpenGL context (egl: ImportError: libEGL.so.1)"
    assert f"Pictures not drawn: {reason}." in lines
    assert not (run_dir / "verdicts").exists()

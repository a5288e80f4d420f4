"""Re-judging trials with :mod:`flyknot.verdict`, and the pictures a person audits them by.

``flyknot judge DIR [--pictures] [--out OUT] [--json]`` reads every trial under a run or
replay directory (:func:`flyknot_app.anatomy.trials.find_trials`), judges the rope as it was
at the end (the simulator's last centreline frame; without truth, the last fully tracked
marker frame with the fingertip's tube axis) and prints, per trial, the verdict it was given
when it ran (``old``: its stored knot type and class, if any), the new verdict, its closure
vote and where the knot sits, then the totals. With ``--pictures`` it writes a close-up
render of every trial the new judge counts as a knot and of one trial per other class
(:func:`write_pictures`); each picture is captioned with its verdict.
"""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flyknot.errors import FlyknotError, RenderError
from flyknot.judge import MarkerJudge
from flyknot.record import TrialRecord, read_outcome
from flyknot.verdict import KNOT, JudgeParams, Verdict, judge_centreline, tube_axis_of
from flyknot_app.anatomy.trials import (
    TrialFile,
    find_trials,
    judge_params_of,
    load_record,
    load_replay,
    require_trials,
)

if TYPE_CHECKING:
    from flyknot_app.viewer.render import RendererCache

FAULT = "fault"
"""The class column of a faulted trial (no verdict)."""


@dataclass(frozen=True)
class Rejudged:
    """One trial judged again.

    Attributes:
        name: The trial's path under the directory, without suffix.
        path: Its record ``.json`` or replay ``.npz``.
        kind: ``"record"`` or ``"replay"``.
        fault: The controller's fault, or None.
        old_knot: The knot type stored when it ran (None: not judged).
        old_class: The verdict class stored when it ran (None: stored without a verdict).
        new: The verdict now (None: faulted, or nothing to judge).
    """

    name: str
    path: Path
    kind: str
    fault: str | None
    old_knot: str | None
    old_class: str | None
    new: Verdict | None

    @property
    def old_success(self) -> bool:
        """Counted as a knot when it ran: its stored class, else its stored knot type."""
        if self.fault is not None:
            return False
        return self.old_class == KNOT if self.old_class else self.old_knot == "trefoil"

    @property
    def new_class(self) -> str:
        """The new verdict's class, ``"fault"``, or ``"-"`` (nothing to judge)."""
        if self.fault is not None:
            return FAULT
        return "-" if self.new is None else self.new.klass

    def as_dict(self) -> dict[str, Any]:
        """Plain data (JSON-ready)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "fault": self.fault,
            "old_knot": self.old_knot,
            "old_class": self.old_class,
            "old_success": self.old_success,
            "new": None if self.new is None else self.new.to_json(),
            "new_class": self.new_class,
        }


def final_frame(centreline: np.ndarray) -> np.ndarray | None:
    """The last frame of a centreline history with every point finite."""
    for frame in np.asarray(centreline, dtype=float)[::-1]:
        if np.all(np.isfinite(frame)):
            return frame
    return None


def rejudge(f: TrialFile, *, keep_stored: bool = False) -> Rejudged:
    """Judge one trial found by :func:`find_trials` again (module docstring); with
    ``keep_stored`` a verdict stored with the trial is kept as the new one (a report shows
    the verdicts a run counted, an operator's included).

    Raises:
        RecordError: The file is malformed (the message names it).
    """
    if f.kind == "replay":
        ev = load_replay(f.path)
        old = ev.verdict
        frame = None if ev.centreline is None else final_frame(ev.centreline)
        new = None if frame is None else judge_centreline(frame, None, judge_params_of(ev.metadata))
        new = old if keep_stored and old is not None else new
        return Rejudged(
            f.name, f.path, f.kind, None, ev.knot, None if old is None else old.klass, new
        )
    if keep_stored:  # a stored verdict or a fault: the record's JSON says all
        end = read_outcome(f.path)
        if end.fault is not None or end.verdict is not None:
            old_class = None if end.verdict is None else end.verdict.klass
            new = end.verdict if end.fault is None else None
            return Rejudged(f.name, f.path, f.kind, end.fault, end.knot, old_class, new)
    rec = load_record(f.path)
    new = None
    if rec.fault is None:
        frame = final_frame(rec.truth["centreline"]) if "centreline" in rec.truth else None
        if frame is not None:
            params = judge_params_of(rec.metadata)
            new = judge_centreline(frame, tube_axis_of(rec.fingertip_quat[-1]), params)
        else:
            new = MarkerJudge(judge_params_of(rec.metadata))(rec)
    old = rec.verdict
    return Rejudged(
        f.name, f.path, f.kind, rec.fault, rec.knot, None if old is None else old.klass, new
    )


def rejudge_directory(
    directory: str | Path,
    progress: Callable[[Iterable[TrialFile]], Iterable[TrialFile]] | None = None,
    *,
    keep_stored: bool = False,
) -> list[Rejudged]:
    """Every trial under ``directory`` judged again, in path order (:func:`rejudge`).

    Raises:
        ConfigError: ``directory`` is missing, not a directory, or holds no trials.
        RecordError: A trial file is malformed (the message names it).
    """
    files = require_trials(directory)
    it = files if progress is None else progress(files)
    return [rejudge(f, keep_stored=keep_stored) for f in it]


def totals(rows: Sequence[Rejudged]) -> dict[str, Any]:
    """Counts: trials, knots before and now, and old knot type -> new class pairs."""
    pairs = Counter(
        f"{FAULT if r.fault else (r.old_class or r.old_knot)} -> {r.new_class}" for r in rows
    )
    return {
        "trials": len(rows),
        "knots_old": sum(r.old_success for r in rows),
        "knots_new": sum(r.new_class == KNOT for r in rows),
        "classes_new": dict(Counter(r.new_class for r in rows)),
        "old_to_new": dict(sorted(pairs.items())),
    }


def _vote_text(v: Verdict | None) -> str:
    if v is None or not v.votes:
        return "-"
    return f"{v.votes.get(v.knot, 0)}/{sum(v.votes.values())} {v.knot}"


def format_rejudged(rows: Sequence[Rejudged], directory: str | Path) -> str:
    """The per-trial table and the totals, as printed by ``flyknot judge``."""
    width = max([len(r.name) for r in rows] + [5])
    head = f"{'trial':<{width}}  {'old':<15}  {'new':<15}  {'vote':<13}  knot from held end"
    lines = [f"re-judged {len(rows)} trials under {directory}", head]
    for r in rows:
        old = FAULT if r.fault else (r.old_class or r.old_knot or "-")
        where = "-"
        if r.new is not None and r.new.core is not None:
            where = f"{r.new.core_from_held_m:.2f} m (vertices {r.new.core[0]}-{r.new.core[1]})"
        elif r.new is not None and r.new.klass == "wrapped_at_grip":
            where = "round the held end"
        lines.append(
            f"{r.name:<{width}}  {old:<15}  {r.new_class:<15}  {_vote_text(r.new):<13}  {where}"
        )
    t = totals(rows)
    lines.append(f"knots: {t['knots_old']} counted when run, {t['knots_new']} now")
    lines.append("now: " + ", ".join(f"{k} {v}" for k, v in sorted(t["classes_new"].items())))
    lines.append("old -> new: " + ", ".join(f"{k}: {v}" for k, v in t["old_to_new"].items()))
    return "\n".join(lines)


def picture_rows(rows: Sequence[Rejudged]) -> list[Rejudged]:
    """Every trial judged a knot, then the first of each other class (faults excepted)."""
    chosen = [r for r in rows if r.new_class == KNOT]
    seen: set[str] = set()
    for r in rows:
        if r.new is not None and r.new_class != KNOT and r.new_class not in seen:
            seen.add(r.new_class)
            chosen.append(r)
    return chosen


def _replay_record(path: Path) -> TrialRecord:
    """A hand-lab replay as a record the renderer draws (no arm: joints zero, hidden)."""
    with np.load(path, allow_pickle=False) as z:
        t, pos, quat, markers = z["t"], z["hand_pos"], z["hand_quat"], z["markers"]
        truth = {"t_truth": z["t_truth"], "centreline": z["centreline"]}
    n = len(t)
    return TrialRecord(
        t_joint=t,
        q_cmd=np.zeros((n, 7)),
        q_meas=np.zeros((n, 7)),
        t_marker=t,
        markers=markers,
        fingertip_pos=pos,
        fingertip_quat=quat,
        base_pose=np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]),
        truth=truth,
    )


def picture_name(row: Rejudged) -> str:
    """File name of a trial's picture: its path with ``/`` as ``__``, class appended."""
    return f"{row.name.replace('/', '__')}.{row.new_class}.png"


def verdict_picture(
    record: TrialRecord,
    verdict: Verdict,
    out: Path,
    *,
    arm: bool = True,
    renderers: RendererCache | None = None,
) -> Path:
    """The rope at the end of a trial for a person to check ``verdict``: the rope and the
    fingertip, and beside it a zoom on the knot's core when the verdict has one; captioned
    with the verdict. Written as ``out`` (.png). ``renderers``: open renderers to draw with
    (many pictures: set up once); None: opened and closed here."""
    import imageio.v2 as imageio

    from flyknot_app.viewer.render import RendererCache, RenderParams, rope_radius_of, trial_end

    if renderers is None:
        with RendererCache() as own:
            return verdict_picture(record, verdict, out, arm=arm, renderers=own)

    radius = rope_radius_of(record) or RenderParams().rope_radius  # drawn at its true size
    views = [RenderParams(close_up=True, show_arm=arm, rope_radius=radius)]
    if verdict.core is not None:
        first, last = verdict.core
        if "centreline" not in record.truth:  # the markers' polyline starts at the fingertip
            first, last = first - 1, last - 1
        focus = (max(first - 2, 0), last + 2)
        views.append(RenderParams(show_arm=arm, focus=focus, rope_radius=radius))
    images = []
    for k, params in enumerate(views):
        caption = verdict.describe() if k == 0 else "the knot's core"
        images.append(renderers.get(record, params).render(trial_end(record), caption))
    out.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(out, np.hstack(images))
    return out


def _drawn_since(picture: Path, trial: Path) -> bool:
    """True when ``picture`` exists and was written after the trial's file (a record's JSON
    is written last): a trial played again is drawn again."""
    return picture.is_file() and picture.stat().st_mtime_ns >= trial.stat().st_mtime_ns


def write_pictures(rows: Sequence[Rejudged], out: str | Path) -> list[Path]:
    """:func:`verdict_picture` of every row of :func:`picture_rows`, into ``out``; a picture
    already there and drawn after its trial (by the run's worker, :func:`draw_run_knots`) is
    kept as it is (the same trial, verdict and file name: the same image).

    Returns:
        The files, in the order of :func:`picture_rows`.
    """
    from flyknot_app.viewer.render import RendererCache

    out = Path(out)
    written = []
    with RendererCache() as renderers:
        for r in picture_rows(rows):
            path = out / picture_name(r)
            if not _drawn_since(path, r.path):
                replay = r.kind == "replay"
                record = _replay_record(r.path) if replay else load_record(r.path)
                verdict_picture(record, r.new, path, arm=not replay, renderers=renderers)
            written.append(path)
    return written


def draw_run_knots(run_dir: str | Path, root: str | Path) -> list[Path]:
    """The pictures of a finished run's knots, drawn where and as the report of the scenario
    directory ``root`` draws them (``root/verdicts``; :func:`report_section` keeps them): each
    run's worker draws its own knots instead of the report drawing every run's, one after the
    other, once all have ended.

    Returns:
        The files (none for a run without trials or knots).
    """
    run_dir, root = Path(run_dir), Path(root)
    if not find_trials(run_dir):
        return []
    prefix = run_dir.relative_to(root).as_posix()
    knots = [
        dataclasses.replace(r, name=f"{prefix}/{r.name}")
        for r in rejudge_directory(run_dir, keep_stored=True)
        if r.new_class == KNOT
    ]
    return write_pictures(knots, root / "verdicts") if knots else []


def report_section(out_dir: str | Path) -> list[str]:
    """``report.md`` lines: the run's verdicts (stored ones kept), a picture of every knot
    and of one trial per other class (written to ``out_dir/verdicts``)."""
    out_dir = Path(out_dir)
    if not find_trials(out_dir):
        return []
    rows = [r for r in rejudge_directory(out_dir, keep_stored=True) if r.fault is None]
    t, p = totals(rows), JudgeParams()
    lines = [
        "## Verdicts",
        "",
        f"{t['knots_new']} of {len(rows)} trials without a fault left an overhand knot in the "
        "hanging rope (`flyknot.verdict`: the held end continued along the tube, a "
        f"{p.supermajority:.2f} supermajority of {p.n_directions} closures, the knot's core at "
        f"least {p.clearance_m:.2f} m from the held end and clear of the floor by "
        f"{p.floor_clearance_m * 1000:.0f} mm over the rope's radius). Classes: "
        + ", ".join(f"{k} {v}" for k, v in sorted(t["classes_new"].items()))
        + ". Every knot, and one trial of each other class, as the rope hung at the end:",
        "",
        "| trial | verdict | picture |",
        "|---|---|---|",
    ]
    chosen = picture_rows(rows)
    try:
        files = write_pictures(chosen, out_dir / "verdicts")
    except RenderError as e:  # no OpenGL here: the verdicts without their pictures
        lines += [f"| {r.name} | {r.new.describe()} | - |" for r in chosen]
        return [*lines, "", f"Pictures not drawn: {e}.", ""]
    _remove_stale(out_dir / "verdicts", keep=files)
    for r, f in zip(chosen, files, strict=True):
        rel = f.relative_to(out_dir)
        lines.append(f"| {r.name} | {r.new.describe()} | [{rel.name}]({rel}) |")
    lines += [""] + [f"![{f.stem}]({f.relative_to(out_dir)})" for f in files] + [""]
    return lines


def _remove_stale(folder: Path, keep: Sequence[Path]) -> None:
    """Delete the pictures in ``folder`` that are not ``keep``: a run played again, or a
    verdict judged again, leaves its old picture under an old class otherwise."""
    kept = {Path(k).resolve() for k in keep}
    for f in folder.glob("*.png"):
        if f.resolve() not in kept:
            f.unlink()


def judge_command(
    directory: str | Path, *, pictures: bool, out: str | Path | None, as_json: bool
) -> str:
    """What ``flyknot judge`` prints (pictures written first when asked for)."""
    rows = rejudge_directory(directory)
    files: list[Path] = []
    if pictures:
        files = write_pictures(rows, Path(directory) / "judge" if out is None else out)
    if as_json:
        data = {
            "directory": str(directory),
            "trials": [r.as_dict() for r in rows],
            "totals": totals(rows),
            "pictures": [str(p) for p in files],
        }
        return json.dumps(data, indent=2)
    text = format_rejudged(rows, directory)
    if files:
        text += "\npictures: " + ", ".join(str(p) for p in files)
    return text


__all__ = [
    "FAULT",
    "FlyknotError",
    "Rejudged",
    "final_frame",
    "format_rejudged",
    "judge_command",
    "picture_rows",
    "rejudge",
    "rejudge_directory",
    "report_section",
    "totals",
    "verdict_picture",
    "write_pictures",
]

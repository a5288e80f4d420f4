"""Running scenarios: joins a demonstration, the learner and the simulated lab.

The orchestration above both sides of the seam: it builds a :class:`flyknot_sim.lab.SimLab`
(the cell) and hands it to :func:`learner.ilc.learn`, which sees only the cell's records.

Output layout of ``flyknot run SCENARIO --out DIR``::

    DIR/manifest.json              scenario, overrides, versions, start, commit, resumes
    DIR/initial_guess/<demo>.npz   kappa_0 per demonstration (cached)
    DIR/runs/<run>/learning/...    the ILC run directory (learner.run_directory.RunDirectory)
    DIR/runs/<run>/repeats/...     records of the repeated final command, if any
    DIR/runs/<run>/result.json     this run's summary
    DIR/summary.json               every run's summary
    DIR/*.png, DIR/report.md       figures and the report (flyknot_app.reports.report)
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from flyknot import __version__
from flyknot.cache import cache_root
from flyknot.constants import DEMOS_DIR, FOLLOW_THROUGH_S, PATH_FRAC
from flyknot.demo_formats import read_demonstration
from flyknot.errors import ConfigError, FlyknotError, RecordError, RenderError
from flyknot.judge import CellVerdict
from flyknot.limits import JointLimits
from flyknot.progress import bar_disable
from flyknot.record import TrialRecord, atomic_save_npy, atomic_write_text
from flyknot.verdict import JUDGE_NAME
from flyknot_app.cells import check_oracle, open_cell, oracle_provider
from flyknot_app.guess_cache import cached_guess, guess_cache_name, guess_key, store_guess
from flyknot_app.reports.results import git_commit
from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary
from flyknot_app.scenario import RunSpec, Scenario, find_named_file


def demo_path(demo: str) -> Path:
    """A demonstration by path or by name under ``assets/demos`` (error lists names)."""
    return find_named_file("demo", demo, DEMOS_DIR, ".npz")


def prepare_target(
    demo_name: str,
    rope_dt: float,
    window: tuple[float, float] = (FOLLOW_THROUGH_S, PATH_FRAC),
):
    """Trim the demonstration (paper's timing selection with ``window`` =
    (follow-through t_f - t_c [s], path fraction at t_0)) and build the learner's target."""
    from learner.demo_timing import select_demo_window, trim_demonstration
    from learner.target import DemoTarget

    demo = read_demonstration(demo_path(demo_name))
    follow_through, path_frac = window
    window = select_demo_window(
        demo.t, demo.hand_pos, demo.t_c, follow_through=follow_through, path_frac=path_frac
    )
    trimmed = trim_demonstration(demo, window)
    return trimmed, DemoTarget.from_demonstration(trimmed, dt=rope_dt)


def initial_knots(
    demo_name: str,
    out_dir: Path,
    robot,
    rope_dt: float,
    base_height: float,
    window: tuple[float, float] = (FOLLOW_THROUGH_S, PATH_FRAC),
    progress: bool = False,
) -> tuple[np.ndarray, dict]:
    """kappa_0 for a demonstration, cached in the run directory (``initial_guess/``, kept
    with the run) and in the machine's cache (:func:`guess_key`), so that a scenario run into
    a new directory reuses a guess this machine has made before from the same inputs.

    ``progress``: show IPOPT's iterations (a bar on a terminal; nothing otherwise).

    ``base_height`` is the lab's robot base height above its floor, so that the fingertip
    starts at least z_min above the real floor (the rope hangs clear); ``window`` as in
    :func:`prepare_target`.
    """
    from scipy.spatial.transform import Rotation

    from learner import initial_guess as guess_module
    from learner.initial_guess import InitialGuessParams

    cache = out_dir / "initial_guess" / guess_cache_name(demo_name, window, base_height)
    digest = hashlib.sha256(demo_path(demo_name).read_bytes()).hexdigest()
    cached = cached_guess(cache)
    if cached is not None and cached[1].get("demo_sha256") == digest:
        return cached
    params = InitialGuessParams(base_height=base_height)
    key = guess_key(digest, window, rope_dt, params, robot, guess_module.initial_guess)
    shared = cache_root() / "initial_guess" / f"{key}.npz"
    cached = cached_guess(shared)
    if cached is not None and cached[1].get("demo_sha256") == digest:
        store_guess(cache, *cached)
        return cached
    trimmed, target = prepare_target(demo_name, rope_dt, window)
    t = trimmed.t - trimmed.t[0]
    R = Rotation.from_quat(trimmed.hand_quat, scalar_first=True).as_matrix()
    from tqdm import tqdm

    bar = tqdm(
        total=params.max_iter,
        desc=f"initial guess {demo_name}",
        unit="it",
        disable=bar_disable(progress),
        leave=False,
    )

    def on_iteration(k: int, f: float) -> None:
        bar.set_postfix_str(f"objective {f:.4g}", refresh=False)
        bar.update(1)

    try:
        res = guess_module.initial_guess(
            t, trimmed.hand_pos, R, target.T, robot, params=params, on_iteration=on_iteration
        )
    finally:
        bar.close()
    info = {
        "status": res.status,
        "success": bool(res.success),
        "cost": float(res.cost),
        "max_errors": dict(res.max_errors),
        "rms_errors": dict(res.rms_errors),
        "solve_time": float(res.solve_time),
        "T": float(target.T),
        "t_c": float(target.t_c),
        "demo_sha256": digest,  # a guess cached for another version of the file is made again
    }
    if not res.success:
        raise FlyknotError(f"initial guess for demo {demo_name!r} failed: {res.status}")
    for path in (cache, shared):
        store_guess(path, res.knots, info)
    return np.asarray(res.knots), info


def execute_run(
    spec: RunSpec,
    out_dir: Path,
    knots0: np.ndarray | None,
    *,
    resume: bool,
    progress: bool,
    figure: bool = False,
) -> RunSummary:
    """:func:`play_run`, then :func:`finish_run`: one run and its post-run work, here."""
    summary = play_run(spec, out_dir, knots0, resume=resume, progress=progress)
    finish_run(spec, out_dir, summary, figure=figure)
    return summary


def play_run(
    spec: RunSpec, out_dir: Path, knots0: np.ndarray | None, *, resume: bool, progress: bool
) -> RunSummary:
    """Learn (and optionally repeat) one run; write and return its summary.

    The run's cell is opened here and closed when the run ends, however it ends (a real
    lab's connection to the controller and the motion capture).
    """
    result_path = out_dir / "runs" / spec.name / "result.json"
    if resume:
        done = _finished_run(result_path)
        if done is not None:
            return done
    lab = open_cell(spec.cell, spec.cell_spec())
    try:
        return _execute_on(lab, spec, out_dir, knots0, resume=resume, progress=progress)
    finally:
        close = getattr(lab, "close", None)
        if callable(close):
            close()


FINISHED = "post_run.done"
"""Written into a run's directory when :func:`finish_run` has done its work."""


def finish_run(spec: RunSpec, out_dir: Path, summary: RunSummary, *, figure: bool = False) -> None:
    """A finished run's post-run work, which the scenario's report would otherwise do for
    every run, one at a time, after the last: its trials' failure-anatomy diagnoses stored
    beside their records, the pictures of its knots drawn into the scenario's ``verdicts/``
    and, with ``figure``, its critical-point figure. Done once: a resumed scenario skips the
    runs whose directory holds :data:`FINISHED`.
    """
    from flyknot_app.anatomy.report import store_diagnoses
    from flyknot_app.judging import draw_run_knots
    from flyknot_app.reports.report import critical_figure_path, plot_critical_overlays

    run_dir = out_dir / "runs" / spec.name
    if (run_dir / FINISHED).is_file():
        return
    store_diagnoses(run_dir)
    try:
        draw_run_knots(run_dir, out_dir)
    except RenderError as e:  # no OpenGL here: the run is whole, its pictures are not drawn
        print(f"flyknot: warning: {e}; the knots' pictures are not drawn", file=sys.stderr)
    if figure:
        plot_critical_overlays(run_dir, summary, critical_figure_path(out_dir, spec.name))
    if run_dir.is_dir():
        atomic_write_text(run_dir / FINISHED, "")


def command_limits(lab: Any) -> JointLimits:
    """The joint limits the ILC updates must keep for ``lab`` to play their commands: the
    cell's own (a hardware cell's: the stricter of the paper's and the robot's less the safety
    margins its preflight allows), else the paper's, beyond which the simulated controller
    faults."""
    own = getattr(lab, "command_limits", None)
    return own() if callable(own) else JointLimits()


def _execute_on(
    lab: Any,
    spec: RunSpec,
    out_dir: Path,
    knots0: np.ndarray | None,
    *,
    resume: bool,
    progress: bool,
) -> RunSummary:
    """Learn on ``lab``, play the final command's repeats, write ``result.json``."""
    from learner.bezier import BezierCommand
    from learner.kinematics import RobotModel

    run_dir = out_dir / "runs" / spec.name
    t_start = time.perf_counter()
    robot = RobotModel.from_mjcf()
    dt = spec.learner.rope_model.dt
    _, target = prepare_target(spec.demo, dt, spec.window)
    ig_info: dict[str, Any] = {}
    judge = CellVerdict()  # the verdict the cell recorded (simulated truth, or the operator's)
    if knots0 is None:
        base_height = float(lab.base_pose[2])
        knots0, ig_info = initial_knots(spec.demo, out_dir, robot, dt, base_height, spec.window)
    res = _learn(lab, spec, target, knots0, robot, run_dir, judge, resume=resume, progress=progress)
    atomic_save_npy(run_dir / "final_knots.npy", res.final_knots)
    command = BezierCommand(res.final_knots, target.T).joint_command() if spec.repeats else None
    # Repeat i is the cell's trial len(learning trials) + i, resumed or not.
    classes, verdicts = _play_repeats(
        lab, spec, command, len(res.trials), run_dir, judge, resume=resume, progress=progress
    )
    counted = [s for _, s in sorted({s.trial: s for s in res.trials}.items())]
    first = res.first_success_trial
    summary = RunSummary(
        options=spec.to_json(),
        costs=res.costs,
        knots=res.knots,
        faults=[s.fault for s in counted],
        verdicts=[s.verdict for s in counted],
        trials_to_success=None if first is None else first + 1,
        stopped_because=res.stopped_because,
        attempts=len(res.trials),
        repeat_classes=classes,
        repeat_verdicts=verdicts,
        judge=JUDGE_NAME,
        initial_guess=ig_info,
        T=target.T,
        t_c=target.t_c,
        wall_s=time.perf_counter() - t_start,
        custom_rope=_custom_rope_summary(lab) if spec.cell == "sim" else {},
    )
    atomic_write_text(run_dir / "result.json", json.dumps(summary.to_json(), indent=2))
    return summary


def _learn(lab, spec: RunSpec, target, knots0, robot, run_dir: Path, judge, *, resume, progress):
    """The run's ILC loop (:func:`learner.ilc.learn`) with a progress bar per trial."""
    from tqdm import tqdm

    from learner.ilc import learn

    bar = tqdm(
        total=spec.learner.trials,
        desc=spec.name,
        unit="trial",
        disable=bar_disable(progress),
        leave=False,
    )

    def on_trial(s) -> None:
        bar.set_postfix_str(
            f"knot={s.knot} cost={'-' if s.cost is None else f'{s.cost:.3g}'}"
            + (" FAULT" if s.fault else "")
        )
        bar.n = s.trial + 1
        bar.refresh()

    try:
        return learn(
            lab,
            target,
            knots0,
            robot,
            spec.learner,
            limits=command_limits(lab),
            run_dir=run_dir / "learning",
            resume=resume,
            on_trial=on_trial,
            judge=judge,
            jacobian=_measured_jacobian(spec, target.t_c),
        )
    finally:
        bar.close()


def _measured_jacobian(spec: RunSpec, t_c: float):
    """The run's measured M(t_c) provider when its ``jacobian`` source needs one (the
    oracle: :mod:`flyknot_app.diagnose.oracle`), else None."""
    from learner.jacobians import jacobian_kind

    if not jacobian_kind(spec.learner.update.jacobian).needs_provider:
        return None
    return oracle_provider(spec.cell, spec.cell_spec(), t_c)


def check_jacobians(scen: Scenario) -> None:
    """Refuse, before anything is written, a run whose Jacobian source its cell cannot give."""
    from learner.jacobians import jacobian_kind

    for spec in scen.runs:
        if jacobian_kind(spec.learner.update.jacobian).needs_provider:
            check_oracle(spec.cell, dry_run=bool(getattr(spec.cell_spec(), "dry_run", False)))


def _play_repeats(
    lab, spec: RunSpec, command, first: int, run_dir: Path, judge, *, resume, progress
) -> tuple[list[str | None], list[dict[str, Any] | None]]:
    """Play the final command ``spec.repeats`` times as the cell's trials ``first``,
    ``first + 1``...; each repeat's verdict class (``"fault"`` for a faulted one, None without
    a verdict) and verdict. On resume a repeat a kill left whole is read, not played."""
    from tqdm import tqdm

    classes: list[str | None] = []
    verdicts: list[dict[str, Any] | None] = []
    bar = tqdm(
        range(spec.repeats),
        desc=f"{spec.name} repeats",
        disable=bar_disable(progress),
        leave=False,
    )
    for i in bar:
        lab.trial_index = first + i
        stem = run_dir / "repeats" / f"repeat_{i:03d}"
        rec = _written_with_truth(stem) if resume else None
        if rec is None:  # not written, or cut short by a kill: play it (again)
            rec = lab.run(command)
            rec.save(stem)
        verdict = None if rec.fault else judge(rec)
        classes.append("fault" if rec.fault else None if verdict is None else verdict.klass)
        verdicts.append(None if verdict is None else verdict.to_json())
    return classes, verdicts


def _finished_run(path: Path) -> RunSummary | None:
    """The summary a finished run left, or None when it is absent or unreadable (a kill while
    it was written: the run resumes from its run directory)."""
    try:
        return RunSummary.from_json(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def _written_with_truth(stem: Path) -> TrialRecord | None:
    """A repeat's record a killed run left, truth included, or None when it is absent or any
    of its files is unreadable (the repeat is played again on the same trial index)."""
    if not stem.with_name(stem.name + ".json").is_file():
        return None
    try:
        return TrialRecord.load(stem, with_truth=True)
    except RecordError:
        return None


def _custom_rope_summary(lab) -> dict[str, Any]:
    """A custom rope's parameters and file for a run's summary (nothing for the paper's)."""
    from flyknot_sim.rope_custom import rope_record

    rec = rope_record(lab.rope_params, lab.params.ropes)
    return {k: rec[k] for k in ("rope_name", "rope_params", "ropes_file") if "rope_params" in rec}


def _ropes_manifest(scen: Scenario) -> dict[str, Any]:
    """The custom ropes the scenario's runs use: ``{"ropes": {file: {name: params}}}``."""
    from flyknot_sim.rope_custom import resolve_rope

    used: dict[str, dict[str, Any]] = {}
    for r in scen.runs:
        if r.ropes is not None and isinstance(r.rope, str):
            used.setdefault(r.ropes, {})[r.rope] = resolve_rope(r.rope, r.ropes).to_dict()
    return {"ropes": used} if used else {}


def make_initial_guesses(scen: Scenario, out_dir: Path, *, progress: bool = False) -> None:
    """The initial guess of every simulated run of ``scen`` that starts from its
    demonstration, cached in ``out_dir`` (one per demonstration and window; another cell's
    runs make their own for that cell's base height)."""
    from flyknot_sim.scene import SceneParams, robot_base_pose
    from learner.kinematics import RobotModel

    robot = RobotModel.from_mjcf()
    z = float(robot_base_pose(SceneParams())[2])
    sim_runs = [r for r in scen.runs if r.start_from is None and r.cell == "sim"]
    for demo, window in sorted({(r.demo, r.window) for r in sim_runs}):
        dt = next(r.learner.rope_model.dt for r in scen.runs if r.demo == demo)
        if progress:
            print(f"initial guess for demo {demo!r} (trajectory optimisation)...", flush=True)
        initial_knots(demo, out_dir, robot, dt, z, window, progress=progress)


class ScenarioDone(NamedTuple):
    """A finished scenario: its summary, the wall seconds its runs took in the workers (their
    sum) and the seconds from the start of :func:`run_scenarios` until its report was written."""

    summary: ScenarioSummary
    run_s: float
    done_s: float


def run_scenario(
    scen: Scenario,
    out_dir: str | Path,
    *,
    workers: int = 1,
    resume: bool = False,
    overrides: dict | None = None,
    progress: bool = True,
    executor: str = "process",
    address: str | None = None,
) -> ScenarioSummary:
    """Run every run of a scenario on ``workers`` (:func:`run_scenarios` with one scenario).

    ``executor``: ``"process"`` (a local process pool of ``workers``) or ``"ray"`` (Ray tasks
    on a local Ray with ``workers`` CPUs, or on the existing cluster at ``address``; each
    task writes its run into ``out_dir`` as it finishes, so the cluster's workers must see
    that directory).
    """
    done = run_scenarios(
        [(scen, Path(out_dir))],
        workers=workers,
        resume=resume,
        overrides=overrides,
        progress=progress,
        executor=executor,
        address=address,
    )
    return done[0].summary


def run_scenarios(
    items: Sequence[tuple[Scenario, Path]],
    *,
    workers: int = 1,
    resume: bool | Sequence[bool] = False,
    overrides: dict | None = None,
    progress: bool = True,
    executor: str = "process",
    address: str | None = None,
) -> list[ScenarioDone]:
    """Run several scenarios' runs on one pool of ``workers`` (:mod:`flyknot_app.schedule`:
    each run as soon as the run it starts from has finished, the longest remaining chain of
    work first), and write each scenario's summary and report as soon as its last run ends.

    ``items``: (scenario, its output directory) pairs, the directories distinct. ``resume``:
    continue the scenarios in their directories (each must hold a manifest); one flag for all,
    or one per item.
    """
    from tqdm import tqdm

    from flyknot_app.reports.report import CRITICAL_FIGURES
    from flyknot_app.schedule import EXECUTORS, RunJob, run_jobs

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("--workers", f"must be an integer >= 1, got {workers!r}")
    if executor not in EXECUTORS:
        raise ConfigError("--executor", f"unknown executor {executor!r}", EXECUTORS)
    keys = [str(Path(d)) for _, d in items]
    if len(set(keys)) != len(keys):
        raise ConfigError("out_dir", "two scenarios would write into the same directory")
    again = [resume] * len(items) if isinstance(resume, bool) else list(resume)
    if len(again) != len(items):
        raise ConfigError("resume", f"needs one flag per scenario ({len(items)}), got {len(again)}")
    jobs: list[RunJob] = []
    for (scen, out_dir), more in zip(items, again, strict=True):
        prepare_scenario(scen, Path(out_dir), resume=more, overrides=overrides, progress=progress)
        drawn = {r.name for r in scen.runs[:CRITICAL_FIGURES]}  # the report's figures
        jobs += [
            RunJob(str(Path(out_dir)), spec, Path(out_dir), more, spec.name in drawn)
            for spec in scen.runs
        ]
    one = len(items) == 1
    desc = items[0][0].name if one else f"{len(items)} scenarios"
    overall = tqdm(total=len(jobs), desc=desc, unit="run", disable=bar_disable(progress))
    results: dict[str, dict[str, RunSummary]] = {k: {} for k in keys}
    run_s = dict.fromkeys(keys, 0.0)
    done: dict[str, ScenarioDone] = {}
    t0 = time.perf_counter()
    for job, res, wall in run_jobs(
        jobs,
        play_run,
        finish=finish_run,
        executor=executor,
        workers=workers,
        address=address,
        progress=progress,
    ):
        results[job.scenario][job.spec.name] = res
        run_s[job.scenario] += wall
        overall.update(1)
        _print_run(res, overall, "" if one else f"{Path(job.scenario).name}/")
        for (scen, out_dir), key in zip(items, keys, strict=True):
            if key not in done and len(results[key]) == len(scen.runs):
                summary = finish_scenario(scen, Path(out_dir), results[key], workers)
                done[key] = ScenarioDone(summary, run_s[key], time.perf_counter() - t0)
    overall.close()
    return [done[k] for k in keys]


def prepare_scenario(
    scen: Scenario,
    out_dir: Path,
    *,
    resume: bool = False,
    overrides: dict | None = None,
    progress: bool = True,
) -> None:
    """Check the output directory, write the scenario's manifest and make its initial
    guesses (cached)."""
    import mujoco

    from flyknot.numerics import numerics_class

    if resume and not (out_dir / "manifest.json").is_file():
        raise ConfigError(
            "--resume", f"{str(out_dir)!r} holds no run to resume (no manifest.json there)"
        )
    if not resume and (out_dir / "manifest.json").is_file():
        raise ConfigError("--out", f"{str(out_dir)!r} already holds a run; use --resume")
    scen.order()  # runs that wait on each other in a cycle fail here, before any work
    check_jacobians(scen)
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest = {
        "scenario": scen.name,
        "kind": scen.kind,
        "source": scen.source,
        "description": scen.description,
        "overrides": overrides or {},
        "runs": [r.to_json() for r in scen.runs],
        **_ropes_manifest(scen),
        "versions": {
            "flyknot": __version__,
            "mujoco": mujoco.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        "numerics": numerics_class(),
        "commit": git_commit(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    if resume:  # the code a resumed scenario's further runs are made with, beside the first
        now = {k: manifest[k] for k in ("commit", "started")}
        manifest = json.loads((out_dir / "manifest.json").read_text())
        manifest["resumed"] = [*manifest.get("resumed", []), now]
    atomic_write_text(out_dir / "manifest.json", json.dumps(manifest, indent=2))
    make_initial_guesses(scen, out_dir, progress=progress)


def finish_scenario(
    scen: Scenario, out_dir: Path, results: dict[str, RunSummary], workers: int
) -> ScenarioSummary:
    """Every run has finished: write the scenario's summary and report."""
    from flyknot_app.reports.report import write_report

    runs = tuple(results[r.name] for r in scen.runs)
    summary = ScenarioSummary(scen.name, scen.kind, runs, scen.paper)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary.to_json(), indent=2))
    write_report(out_dir, summary, workers=max(1, workers))
    return summary


def _print_run(res: RunSummary, bar, prefix: str = "") -> None:
    n = res.trials_to_success
    msg = (
        f"{prefix}{res.name}: rope {res.rope}, "
        + (f"knot at trial {n}" if n is not None else "no knot")
        + f" ({len(res.costs)} trials)"
    )
    if res.repeat_success_rate is not None:
        msg += f", repeats {res.repeat_success_rate * 100:.0f} % of {len(res.repeat_classes)}"
    bar.write(msg)

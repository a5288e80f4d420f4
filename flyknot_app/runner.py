"""Running scenarios: joins a demonstration, the learner and the simulated lab.

This module is the orchestration layer above both sides of the seam: it builds a
:class:`flyknot_sim.lab.SimLab` (the cell) and hands it to :func:`learner.ilc.learn`, which
sees only what the cell's records carry.

Output layout of ``flyknot run SCENARIO --out DIR``::

    DIR/manifest.json              scenario, overrides, versions, start time
    DIR/initial_guess/<demo>.npz   kappa_0 per demonstration (cached)
    DIR/runs/<run>/learning/...    the ILC run directory (learner.run_directory.RunDirectory)
    DIR/runs/<run>/repeats/...     records of the repeated final command, if any
    DIR/runs/<run>/result.json     this run's summary
    DIR/summary.json               every run's summary
    DIR/*.png, DIR/report.md       figures and the report (flyknot_app.report)
"""

from __future__ import annotations

import json
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from flyknot import __version__
from flyknot.constants import DEMOS_DIR, FOLLOW_THROUGH_S, PATH_FRAC
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, FlyknotError, RecordError
from flyknot.judge import CellVerdict
from flyknot.limits import JointLimits
from flyknot.progress import bar_disable
from flyknot.record import TrialRecord
from flyknot.verdict import JUDGE_NAME, KNOT
from flyknot_app.cells import open_cell
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

    demo = Demonstration.load(demo_path(demo_name))
    follow_through, path_frac = window
    window = select_demo_window(
        demo.t, demo.hand_pos, demo.t_c, follow_through=follow_through, path_frac=path_frac
    )
    trimmed = trim_demonstration(demo, window)
    return trimmed, DemoTarget.from_demonstration(trimmed, dt=rope_dt)


def guess_cache_name(demo_name: str, window: tuple[float, float], base_height: float) -> str:
    """File name of a cached initial guess: the demo's stem, the window when it is not the
    paper's, and the robot base's height [m] (the guess keeps the fingertip z_min above the
    floor, so a lab with another base height needs its own)."""
    stem = Path(demo_name).stem
    if tuple(window) != (FOLLOW_THROUGH_S, PATH_FRAC):
        stem += f"_ft{window[0]:g}_p{window[1]:g}"
    return f"{stem}_base{base_height:.4f}.npz"


def initial_knots(
    demo_name: str,
    out_dir: Path,
    robot,
    rope_dt: float,
    base_height: float,
    window: tuple[float, float] = (FOLLOW_THROUGH_S, PATH_FRAC),
    progress: bool = False,
) -> tuple[np.ndarray, dict]:
    """kappa_0 for a demonstration, computed once per run directory and cached there.

    ``progress``: show IPOPT's iterations (a bar on a terminal; nothing otherwise).

    ``base_height`` is the lab's robot base height above its floor, so that the fingertip
    starts at least z_min above the real floor (the rope hangs clear); ``window`` as in
    :func:`prepare_target`.
    """
    from scipy.spatial.transform import Rotation

    from learner.initial_guess import InitialGuessParams, initial_guess

    cache = out_dir / "initial_guess" / guess_cache_name(demo_name, window, base_height)
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            return z["knots"], json.loads(str(z["info"]))
    trimmed, target = prepare_target(demo_name, rope_dt, window)
    t = trimmed.t - trimmed.t[0]
    R = Rotation.from_quat(trimmed.hand_quat, scalar_first=True).as_matrix()
    params = InitialGuessParams(base_height=base_height)
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
        res = initial_guess(
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
    }
    if not res.success:
        raise FlyknotError(f"initial guess for demo {demo_name!r} failed: {res.status}")
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, knots=res.knots, info=np.array(json.dumps(info)))
    return np.asarray(res.knots), info


def _rope_model(spec: RunSpec):
    return spec.ilc_params().rope_model


def execute_run(
    spec: RunSpec,
    out_dir: Path,
    knots0: np.ndarray | None,
    *,
    resume: bool,
    progress: bool,
    figure: bool = False,
) -> dict[str, Any]:
    """Learn (and optionally repeat) one run; write and return its summary.

    When the run ends, its trials' failure-anatomy diagnoses are stored beside their records
    and, with ``figure``, its critical-point figure is drawn for the scenario's report: work
    the report would otherwise do after every run, one at a time.

    The run's cell is opened here and closed when the run ends, however it ends (a real
    lab's connection to the controller and the motion capture).
    """
    result_path = out_dir / "runs" / spec.name / "result.json"
    if resume and result_path.is_file():
        return json.loads(result_path.read_text())
    lab = open_cell(spec.cell, spec.cell_spec())
    try:
        summary = _execute_on(lab, spec, out_dir, knots0, resume=resume, progress=progress)
    finally:
        close = getattr(lab, "close", None)
        if callable(close):
            close()
    from flyknot_app.anatomy_report import store_diagnoses
    from flyknot_app.report import critical_figure_path, plot_critical_overlays

    run_dir = out_dir / "runs" / spec.name
    store_diagnoses(run_dir)
    if figure:
        plot_critical_overlays(run_dir, summary, critical_figure_path(out_dir, spec.name))
    return summary


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
) -> dict[str, Any]:
    from tqdm import tqdm

    from learner.bezier import BezierCommand
    from learner.ilc import learn
    from learner.kinematics import RobotModel

    run_dir = out_dir / "runs" / spec.name
    result_path = run_dir / "result.json"
    t_start = time.perf_counter()
    robot = RobotModel.from_mjcf()
    rope_model = _rope_model(spec)
    _, target = prepare_target(spec.demo, rope_model.dt, spec.window)
    ig_info: dict[str, Any] = {}
    judge = CellVerdict()  # the verdict the cell recorded (simulated truth, or the operator's)
    if knots0 is None:
        knots0, ig_info = initial_knots(
            spec.demo, out_dir, robot, rope_model.dt, float(lab.base_pose[2]), spec.window
        )
    params = spec.ilc_params()
    bar = tqdm(
        total=params.max_trials,
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

    res = learn(
        lab,
        target,
        knots0,
        robot,
        params,
        limits=command_limits(lab),
        run_dir=run_dir / "learning",
        resume=resume,
        on_trial=on_trial,
        judge=judge,
    )
    bar.close()
    # max_trials = 0: tracking alone; the initial command is the run's command (its one
    # trial's update is never played).
    final = np.asarray(knots0) if spec.max_trials == 0 else res.final_knots
    np.save(run_dir / "final_knots.npy", final)
    repeats: list[str | None] = []  # the verdict class of each repeat, or "fault"
    repeat_verdicts: list[dict[str, Any] | None] = []
    if spec.repeats:
        command = BezierCommand(final, target.T).joint_command()
        for i in tqdm(
            range(spec.repeats),
            desc=f"{spec.name} repeats",
            disable=bar_disable(progress),
            leave=False,
        ):
            # Repeat i is the cell's trial len(learning trials) + i, resumed or not.
            lab.trial_index = len(res.trials) + i
            stem = run_dir / "repeats" / f"repeat_{i:03d}"
            rec = _written_with_truth(stem) if resume else None
            if rec is None:  # not written, or cut short by a kill: play it (again)
                rec = lab.run(command)
                rec.save(stem)
            verdict = None if rec.fault else judge(rec)
            repeats.append("fault" if rec.fault else None if verdict is None else verdict.klass)
            repeat_verdicts.append(None if verdict is None else verdict.to_json())
    counted = {s.trial: s for s in res.trials}
    summary = {
        "name": spec.name,
        "label": spec.label,
        "rope": spec.rope,
        "seed": spec.seed,
        **(_custom_rope_summary(lab) if spec.cell == "sim" else {}),
        "demo": spec.demo,
        "objective": spec.objective,
        "rope_model": asdict(rope_model),
        "gain": spec.gain,
        "trust_region": spec.trust_region,
        "follow_through_s": spec.follow_through_s,
        "path_frac": spec.path_frac,
        "weights": dict(spec.weights),
        "start_from": spec.start_from,
        "costs": res.costs,
        "knots": res.knots,
        "faults": [counted[k].fault for k in sorted(counted)],
        "verdicts": [counted[k].verdict for k in sorted(counted)],
        "trials_to_success": None
        if res.first_success_trial is None
        else res.first_success_trial + 1,
        "stopped_because": res.stopped_because,
        "confirm": None if spec.confirm is None else list(spec.confirm),
        "confirmed": res.stopped_because == "confirmed",
        "safeguard": spec.safeguard,
        "average": spec.average,
        "attempts": len(res.trials),
        "repeats": repeats,
        "repeat_verdicts": repeat_verdicts,
        "judge": JUDGE_NAME,
        "repeat_success_rate": (sum(r == KNOT for r in repeats) / len(repeats))
        if repeats
        else None,
        "initial_guess": ig_info,
        "T": target.T,
        "t_c": target.t_c,
        "wall_s": time.perf_counter() - t_start,
    }
    result_path.write_text(json.dumps(summary, indent=2))
    return summary


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
        dt = next(_rope_model(r).dt for r in scen.runs if r.demo == demo)
        if progress:
            print(f"initial guess for demo {demo!r} (trajectory optimisation)...", flush=True)
        initial_knots(demo, out_dir, robot, dt, z, window, progress=progress)


def _worker(args):
    spec, out_dir, knots0, resume, figure = args
    return execute_run(spec, out_dir, knots0, resume=resume, progress=False, figure=figure)


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
) -> dict[str, Any]:
    """Run every run of a scenario (waves in order, runs of a wave in parallel).

    ``executor``: ``"process"`` (a local process pool of ``workers``) or ``"ray"`` (Ray tasks
    on a local Ray with ``workers`` CPUs, or on the existing cluster at ``address``; each
    task writes its run into ``out_dir`` as it finishes, so the cluster's workers must see
    that directory).
    """
    import mujoco
    from tqdm import tqdm

    out_dir = Path(out_dir)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("--workers", f"must be an integer >= 1, got {workers!r}")
    if executor not in EXECUTORS:
        raise ConfigError("--executor", f"unknown executor {executor!r}", EXECUTORS)
    if resume and not (out_dir / "manifest.json").is_file():
        raise ConfigError(
            "--resume", f"{str(out_dir)!r} holds no run to resume (no manifest.json there)"
        )
    if not resume and (out_dir / "manifest.json").is_file():
        raise ConfigError("--out", f"{str(out_dir)!r} already holds a run; use --resume")
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest = {
        "scenario": scen.name,
        "kind": scen.kind,
        "source": scen.source,
        "description": scen.description,
        "overrides": overrides or {},
        "runs": [asdict(r) for r in scen.runs],
        **_ropes_manifest(scen),
        "versions": {
            "flyknot": __version__,
            "mujoco": mujoco.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    if not (resume and (out_dir / "manifest.json").is_file()):
        (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2))
    make_initial_guesses(scen, out_dir, progress=progress)
    results: dict[str, dict[str, Any]] = {}
    overall = tqdm(total=len(scen.runs), desc=scen.name, unit="run", disable=bar_disable(progress))
    from flyknot_app.report import CRITICAL_FIGURES

    drawn = {r.name for r in scen.runs[:CRITICAL_FIGURES]}  # the report's figures
    for wave in scen.order():
        jobs = []
        for spec in wave:
            knots0 = None
            if spec.start_from is not None:
                knots0 = np.load(out_dir / "runs" / spec.start_from / "final_knots.npy")
            jobs.append((spec, out_dir, knots0, resume, spec.name in drawn))
        if executor == "ray":
            for name, res in _ray_results(jobs, workers, address):
                results[name] = res
                overall.update(1)
                _print_run(res, overall)
        elif workers == 1 or len(jobs) == 1:
            for spec, o, k0, r, fig in jobs:
                results[spec.name] = execute_run(
                    spec, o, k0, resume=r, progress=progress, figure=fig
                )
                overall.update(1)
                _print_run(results[spec.name], overall)
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futs = {pool.submit(_worker, j): j[0].name for j in jobs}
                for fut in as_completed(futs):
                    results[futs[fut]] = fut.result()
                    overall.update(1)
                    _print_run(results[futs[fut]], overall)
    overall.close()
    summary = {
        "scenario": scen.name,
        "kind": scen.kind,
        "paper": scen.paper,
        "runs": [results[r.name] for r in scen.runs],
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    from flyknot_app.report import write_report

    write_report(out_dir, summary, workers=max(1, workers))
    return summary


EXECUTORS = ("process", "ray")


def _ray_results(jobs: list, workers: int, address: str | None):
    """Run ``jobs`` as Ray tasks; yield (run name, result) as they finish."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--executor", "ray is not installed: pip install -e '.[ray]'") from None
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is None:
            kwargs["num_cpus"] = workers
        ray.init(address=address, **kwargs)
    task = ray.remote(num_cpus=1)(_worker)
    names = {task.remote(j): j[0].name for j in jobs}
    pending = list(names)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield names[done[0]], ray.get(done[0])


def _print_run(res: dict[str, Any], bar) -> None:
    n = res["trials_to_success"]
    msg = (
        f"{res['name']}: rope {res['rope']}, "
        + (f"knot at trial {n}" if n is not None else "no knot")
        + f" ({len(res['costs'])} trials)"
    )
    if res.get("repeat_success_rate") is not None:
        msg += f", repeats {res['repeat_success_rate'] * 100:.0f} % of {len(res['repeats'])}"
    bar.write(msg)

"""The ``flyknot`` command line: a few subcommands, each reading files plus a few overrides."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

from flyknot.errors import ConfigError
from flyknot_app.bench.sim import BENCHMARKS
from flyknot_app.dispatch import dispatch
from flyknot_app.learner_settings import SCENARIO_DEMO
from flyknot_app.reports.paper import add_paper_parser
from flyknot_app.scenario import parse_rope_arg, parse_seeds
from flyknot_app.trial_cli import add_trial_parsers


def _cmd_showcase(args: argparse.Namespace) -> int:
    from flyknot_sim.commands import swing_command
    from flyknot_sim.lab import LabParams, SimLab

    lab = SimLab(LabParams(rope=args.rope, seed=args.seed))
    record = lab.run(swing_command(), progress=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = record.save(out / "trial")
    swing_command().save(out / "command.csv")
    from flyknot_app.reports.plots import plot_trial

    fig_path = plot_trial(record, out / "trial.png")
    print(f"fault: {record.fault}")
    print(f"knot: {record.knot}")
    if record.verdict is not None:
        print(f"verdict: {record.verdict.describe()}")
    print(f"first self-contact: {record.first_contact_time}")
    print(f"record: {path}")
    print(f"figure: {fig_path}")
    return 0


def _default_run_dir(name: str, resume: bool) -> Path:
    """``runs/<name>``; a new run never overwrites an old one (``runs/<name>-2``, ...), and
    ``--resume`` without ``--out`` continues the newest."""
    base = Path("runs") / name
    taken = [
        base,
        *sorted(
            (p for p in base.parent.glob(f"{name}-*") if p.name[len(name) + 1 :].isdigit()),
            key=lambda p: int(p.name[len(name) + 1 :]),
        ),
    ]
    taken = [p for p in taken if (p / "manifest.json").is_file()]
    if resume:
        return taken[-1] if taken else base
    if not taken:
        return base
    n = 2
    while (base.parent / f"{name}-{n}" / "manifest.json").is_file():
        n += 1
    return base.parent / f"{name}-{n}"


def _cmd_run(args: argparse.Namespace) -> int:
    from flyknot_app.runner import run_scenario
    from flyknot_app.scenario import load_scenario, parse_overrides

    overrides = parse_overrides(args.set, paper_settings=args.paper_settings)
    cell = None
    if args.cell is not None:
        cell = {"kind": "xarm", "lab": str(Path(args.cell).resolve()), "dry_run": args.dry_run}
    elif args.dry_run:
        raise ConfigError("--dry-run", "needs --cell LAB.toml (the real lab it stands in for)")
    scen = load_scenario(args.scenario, overrides, ropes=args.ropes, cell=cell)
    if args.seeds is not None:
        from flyknot_app.scenario import expand_seeds

        scen = expand_seeds(scen, parse_seeds(args.seeds))
    out = Path(args.out) if args.out else _default_run_dir(scen.name, args.resume)
    print(f"scenario {scen.name!r} ({scen.kind}, {len(scen.runs)} runs) -> {out}")
    summary = run_scenario(
        scen,
        out,
        workers=args.workers,
        resume=args.resume,
        overrides=overrides,
        executor=args.executor,
        address=args.address,
    )
    from flyknot_app.reports.report import outcome_line

    print(f"{outcome_line(scen.kind, summary.runs)} Report: {out / 'report.md'}")
    if args.view:
        from flyknot_app.viewer.server import serve

        serve(out, port=args.port)
    elif args.dry_run:
        print(f"look at the dry run's motions: flyknot view {out}")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from flyknot_app.viewer.server import serve

    serve(args.path, host=args.host, port=args.port)
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from flyknot_app.viewer.render import RenderParams, render_trial

    params = RenderParams(width=args.width, height=args.height, fps=args.fps)
    out = render_trial(args.record, args.out, time=args.time, params=params)
    print(f"rendered: {out}")
    return 0


def _cmd_explain(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from flyknot.errors import check_nonnegative
    from flyknot_app.anatomy.report import explain_directory, format_table, plot_anatomy

    def progress(files):
        return tqdm(
            files, desc="explain", unit="trial", leave=False, disable=True if args.json else None
        )

    if args.tc is not None:
        check_nonnegative("--tc", args.tc)
    figure = Path(args.out) if args.out else Path(args.dir) / "anatomy.png"
    if figure.suffix.lower() != ".png":
        raise ConfigError("--out", f"must be a .png file, got {str(figure)!r}")
    anatomy = explain_directory(args.dir, t_c=args.tc, progress=progress, workers=args.workers)
    plot_anatomy(anatomy, figure)
    if args.json:
        print(json.dumps({**anatomy.as_dict(), "figure": str(figure)}))
    else:
        print(format_table(anatomy, trials=args.trials))
        print(f"figure: {figure}")
    return 0


def _cmd_baseline(args: argparse.Namespace) -> int:
    from flyknot_app.baselines import BaselineParams, search_seeds, write_results

    params = BaselineParams(
        budget=args.budget, sigma=args.sigma, scale=args.scale, repeats=args.repeats
    )
    seeds = parse_seeds(args.seeds)
    results, settings = search_seeds(
        args.name,
        seeds,
        params,
        rope=args.rope,
        demo=args.demo,
        settle_s=args.settle,
        progress=not args.quiet,
    )
    out = Path(args.out or f"runs/baseline-{args.name}-rope{args.rope}")
    table = write_results(out, results, params, args.rope, settings)
    print(table.read_text(), end="")
    print(f"Written: {out / 'baseline.json'}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from flyknot_app.hardware import calibrate_command

    return calibrate_command(args)


def _cmd_compare(args: argparse.Namespace) -> int:
    from flyknot_app.reports.compare import compare

    path = compare(args.dirs, args.out)
    print(path.read_text().split("\n\n![")[0].removeprefix("# Comparison\n\n"))
    print(f"Written: {path} and figures beside it")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from flyknot_app.bench import sim as bench

    return bench.main(
        args.what,
        as_json=args.json,
        ropes=args.ropes,
        repeats=args.repeats,
        workers=args.workers,
        quick=args.quick,
        out=args.out,
    )


DEFAULT_CHECK_MODELS = ("1e5,50", "100,0.5", "2,0")
"""The paper's rope model, a middle one and the scenario files' (identified with ``--grid``)."""


def _parse_model(text: str) -> tuple[float, ...]:
    """``STIFFNESS,DAMPING`` or ``STIFFNESS,DAMPING,END_MASS`` of ``--model``."""
    parts = text.split(",")
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        values = ()
    if len(values) not in (2, 3):
        raise ConfigError("--model", f"expected STIFFNESS,DAMPING[,END_MASS], got {text!r}")
    return values


def _cmd_model_check(args: argparse.Namespace) -> int:
    from flyknot_app.diagnose.model_check import check_models, format_table, grid_models, load_knots

    knots = None if args.knots is None else load_knots(args.knots)
    if args.grid and args.model:
        raise ConfigError("--grid", "give either --grid or --model, not both")
    models = (
        grid_models()
        if args.grid
        else [_parse_model(m) for m in (args.model or DEFAULT_CHECK_MODELS)]
    )
    res = check_models(
        args.demo,
        args.rope,
        models,
        knots=knots,
        window=(args.follow_through, args.path_frac),
        n_directions=args.directions,
        step=args.step,
        seed=args.seed,
        progress=not args.json,
    )
    print(json.dumps(res) if args.json else format_table(res))
    return 0


def _run_epilog() -> str:
    """The scenarios and the ``--set`` fields, for ``flyknot run --help``."""
    import textwrap

    from flyknot.constants import SCENARIOS_DIR
    from flyknot.options import option_keys
    from flyknot_app.scenario import RunSpec

    names = sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml"))
    fields = [k for k in option_keys(RunSpec) if k != "name"]

    def wrap(items: list[str]) -> str:
        return textwrap.fill(", ".join(items), 88, initial_indent="  ", subsequent_indent="  ")

    return (
        "scenarios:\n"
        + wrap(names)
        + "\n\n--set fields (KEY=VALUE, repeatable):\n"
        + wrap(fields)
        + "\n\nscenario fields are explained in flyknot_app/scenario.py "
        "(RunSpec) and the README."
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``flyknot`` (exposed for tests and docs)."""
    p = argparse.ArgumentParser(
        prog="flyknot",
        description="Learn the overhand flying knot with Task-Level ILC (simulated or real lab).",
    )
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    _add_run_parser(sub)
    add_trial_parsers(sub)
    add_paper_parser(sub)
    _add_showcase_parser(sub)
    from flyknot_app.demo_cli import add_demo_parser

    add_demo_parser(sub)
    _add_view_parser(sub)
    _add_render_parser(sub)
    _add_model_check_parser(sub)
    _add_explain_parser(sub)
    _add_baseline_parser(sub)
    _add_calibrate_parser(sub)
    _add_compare_parser(sub)
    _add_bench_parser(sub)
    from flyknot_app.diagnose.cli import add_diagnose_parser

    add_diagnose_parser(sub)
    return p


def _add_run_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot run``: a scenario headless."""
    r = sub.add_parser(
        "run",
        help="run a scenario (an experiment of the paper) headless",
        epilog=_run_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    r.add_argument("scenario", help="scenario name under scenarios/ or a .toml path")
    r.add_argument("--out", default=None, help="run directory (default runs/<scenario>)")
    r.add_argument("--workers", type=int, default=1, help="processes for independent runs")
    r.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a run field, e.g. max_trials=3 or rope_model.stiffness=1e3",
    )
    r.add_argument(
        "--paper-settings",
        action="store_true",
        help="the paper's learner settings (gain 1, w_control 0.5, rope model 1e5/50, the "
        "paper's demonstration window) instead of the scenario's; --set still overrides",
    )
    r.add_argument("--resume", action="store_true", help="continue an interrupted run")
    r.add_argument(
        "--ropes",
        default=None,
        help="your own ropes file (.toml), replacing the scenario's `ropes` "
        "(see assets/ropes_example.toml)",
    )
    r.add_argument(
        "--seeds",
        default=None,
        metavar="A-B",
        help="run every run once per lab seed (A-B or A,B,...); runs are named NAME-seedS",
    )
    from flyknot_app.schedule import EXECUTORS

    r.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="process",
        help="process pool (default) or Ray tasks (pip install -e '.[ray]')",
    )
    r.add_argument("--address", default=None, help="with --executor ray: an existing cluster")
    r.add_argument(
        "--cell",
        default=None,
        metavar="LAB.toml",
        help="run on the real lab described by this lab file (assets/lab_example.toml) "
        "instead of the scenario's cell",
    )
    r.add_argument(
        "--dry-run",
        action="store_true",
        help="with --cell: preflight every command as on the arm, then play it in the "
        "simulated lab; nothing connects to the robot",
    )
    r.add_argument(
        "--view",
        action="store_true",
        help="when the run ends, serve the 3D viewer on its run directory (Ctrl-C stops it); "
        "with --dry-run: look at the motions before the arm makes them",
    )
    r.add_argument("--port", type=int, default=8080, help="with --view: the viewer's port")
    r.set_defaults(func=_cmd_run)


def _add_showcase_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot showcase``: one fast showcase trial."""
    s = sub.add_parser("showcase", help="one fast showcase trial on the simulated lab")
    s.add_argument(
        "--rope", type=parse_rope_arg, default=1, help="rope id 1..7 or a rope's name (default 1)"
    )
    s.add_argument("--seed", type=int, default=0, help="trial-to-trial variation seed")
    s.add_argument("--out", default="runs/showcase", help="output directory")
    s.set_defaults(func=_cmd_showcase)


def _add_view_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot view``: the 3D viewer."""
    v = sub.add_parser(
        "view", help="3D viewer of a trial record or a run directory in the browser (viser)"
    )
    v.add_argument(
        "path",
        metavar="PATH",
        help="trial record (.json/.npz or stem, e.g. runs/x/trial) or run directory (flyknot run)",
    )
    v.add_argument("--host", default="127.0.0.1", help="address to serve on")
    v.add_argument("--port", type=int, default=8080, help="port to serve on")
    v.set_defaults(func=_cmd_view)


def _add_render_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot render``: a trial offscreen."""
    rn = sub.add_parser("render", help="render a trial offscreen (MuJoCo) to a .png or an .mp4")
    rn.add_argument("record", help="trial record (.json/.npz or stem)")
    rn.add_argument("--out", required=True, help="image (.png, one frame) or video (.mp4)")
    rn.add_argument(
        "--time", type=float, default=None, help="time of a .png [s] (default: end of motion)"
    )
    rn.add_argument("--width", type=int, default=640, help="pixels (default 640)")
    rn.add_argument("--height", type=int, default=480, help="pixels (default 480)")
    rn.add_argument(
        "--fps", type=float, default=30.0, help="frames per second of an .mp4 (default 30)"
    )
    rn.set_defaults(func=_cmd_render)


def _add_model_check_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot model-check``: the learner's rope model against the lab."""
    from flyknot_app.diagnose.cli import add_window_arguments

    m = sub.add_parser(
        "model-check",
        help="compare the learner's rope-model Jacobian with the lab's measured response",
    )
    m.add_argument(
        "--demo",
        default=SCENARIO_DEMO,
        help=f"demonstration name or file (default {SCENARIO_DEMO})",
    )
    m.add_argument(
        "--rope", type=parse_rope_arg, default=1, help="rope id 1..7 or a rope's name (default 1)"
    )
    m.add_argument(
        "--knots", default=None, help="command knots (.npy/.npz; default: initial guess)"
    )
    m.add_argument("--directions", type=int, default=8, help="random directions (default 8)")
    add_window_arguments(m)
    m.add_argument("--step", type=float, default=0.01, help="direction size [rad] (default 0.01)")
    m.add_argument("--seed", type=int, default=1, help="seed of the directions (default 1)")
    m.add_argument(
        "--model",
        action="append",
        default=None,
        help="STIFFNESS,DAMPING[,END_MASS] of a rope model to score (end mass in link masses, "
        "default 5; repeatable; default: " + " ".join(DEFAULT_CHECK_MODELS) + ")",
    )
    m.add_argument(
        "--grid",
        action="store_true",
        help="score the identification grid of models (stiffness x damping) and name the best",
    )
    m.add_argument("--json", action="store_true", help="print one JSON object")
    m.set_defaults(func=_cmd_model_check)


def _add_explain_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot explain``: the failure anatomy."""
    e = sub.add_parser(
        "explain",
        help="failure anatomy: why each trial under a run or replay directory failed",
    )
    e.add_argument("dir", help="run directory (flyknot run) or replay directory (demo replay)")
    e.add_argument("--out", default=None, help="figure (.png; default DIR/anatomy.png)")
    e.add_argument(
        "--tc",
        type=float,
        default=None,
        help="critical time t_c [s] for every trial (default: each run's, or the replayed "
        "demonstration's)",
    )
    e.add_argument("--trials", action="store_true", help="also list every trial and why")
    e.add_argument("--workers", type=int, default=1, help="worker processes for the diagnoses")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_cmd_explain)


def _add_baseline_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot baseline``: a baseline through the gym envs."""
    bl = sub.add_parser(
        "baseline",
        help="a baseline through the gym envs: random search, CMA-ES, PPO (the rl extra)",
    )
    from flyknot_app.baselines import BASELINES

    bl.add_argument("name", choices=BASELINES)
    bl.add_argument(
        "--rope", type=parse_rope_arg, default=1, help="rope id 1..7 or a rope's name (default 1)"
    )
    bl.add_argument("--budget", type=int, default=30, help="trials per seed (default 30)")
    bl.add_argument(
        "--demo", default=SCENARIO_DEMO, help=f"the demonstration ILC starts from ({SCENARIO_DEMO})"
    )
    bl.add_argument("--seeds", default="0", help="lab seeds: A-B or A,B,... (default 0)")
    bl.add_argument(
        "--repeats", type=int, default=0, help="plays of the best command after (success rate)"
    )
    bl.add_argument("--sigma", type=float, default=0.3, help="search step (offset units)")
    bl.add_argument("--scale", type=float, default=0.1, help="knot change per unit [rad]")
    bl.add_argument("--out", default=None, help="directory (default runs/baseline-NAME-ropeR)")
    bl.add_argument(
        "--settle", type=float, default=None, help="fixed settling time [s] (default: at rest)"
    )
    bl.add_argument("--quiet", action="store_true", help="no progress bar")
    bl.set_defaults(func=_cmd_baseline)


def _add_calibrate_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot calibrate``: the robot base's pose in the mocap frame."""
    c = sub.add_parser(
        "calibrate",
        help="drive the arm through joint poses, see its fingertip in the motion capture, fit "
        "the robot base pose in the mocap frame (or fit fingertips measured elsewhere)",
    )
    c.add_argument("--cell", required=True, metavar="LAB.toml", help="the lab file")
    c.add_argument(
        "--poses",
        default=None,
        help="joint poses, (k, 7) [rad] (.csv or .npy); default: 8 poses around the lab "
        "file's calibration.start",
    )
    c.add_argument(
        "--measured",
        default=None,
        help="fit only, nothing moves: the fingertip the motion capture saw at each of "
        "--poses, (k, 3) [m], mocap frame",
    )
    c.add_argument(
        "--dry-run",
        action="store_true",
        help="preflight every pose and move and print the plan; connect to nothing",
    )
    c.add_argument("--out", default=None, help="also write the fitted [base] table to this file")
    c.set_defaults(func=_cmd_calibrate)


def _add_compare_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot compare``: run directories side by side."""
    cp = sub.add_parser("compare", help="several run directories side by side: table and figures")
    cp.add_argument("dirs", nargs="+", metavar="RUN_DIR", help="flyknot run or baseline output")
    cp.add_argument("--out", default="runs/compare", help="directory (default runs/compare)")
    cp.set_defaults(func=_cmd_compare)


def _add_bench_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot bench``: the benchmarks."""
    b = sub.add_parser(
        "bench",
        help="benchmarks: sim (lab speed per rope), learner, sweep (2 workers vs 1), protocol "
        "(the paper's scenarios at seed 0)",
    )
    b.add_argument("what", choices=BENCHMARKS)
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.add_argument("--ropes", type=int, nargs="*", default=None, help="rope ids (default all)")
    b.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="repeats per measurement (sweep: sweeps per worker count, timed 1, 2, 2, 1, ...)",
    )
    b.add_argument("--workers", type=int, default=2, help="protocol: worker processes (default 2)")
    b.add_argument(
        "--quick",
        action="store_true",
        help="protocol: a fixed small subset, with and without the knot-set settle end",
    )
    b.add_argument(
        "--out", default=None, help="protocol: keep the runs in this new directory (default: none)"
    )
    b.set_defaults(func=_cmd_bench)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``flyknot`` console script."""
    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())

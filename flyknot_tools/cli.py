"""The ``flyknot-tools`` command line: the offline tools that make demonstrations and study ropes.

* ``flyknot-tools demo synthesize --variant NAME --seed S --out FILE`` searches a hand motion
  of the variant (progress on stderr), saves the nominal trial as a demonstration (``.npz``)
  and checks it with ``--check-repeats`` varied replays (the rate goes into its metadata);
  ``docs/demo-synthesis.md``.
* ``flyknot-tools demo robot --out FILE [--start COMMAND.npz] [--seed S]`` searches a command
  the simulated arm ties the knot with and saves its nominal trial as a demonstration;
  ``docs/robot-feasibility.md``.
* ``flyknot-tools demo robot-rate --start COMMAND.npz --out FILE`` searches, from a robot
  command that ties, one that ties in more varied trials (:mod:`flyknot_tools.robot_rate`).
* ``flyknot-tools demo record --command COMMAND.npz --out FILE`` records a robot command's
  nominal trial as a demonstration.
* ``flyknot-tools rope-study [ARGS...]`` prints the rope-model comparison table of
  ``docs/rope-model.md`` (its own options: ``flyknot-tools rope-study --help``).
* ``flyknot-tools rope-validate [--ropes ...] [--table FILE] [--quick]`` runs the rope
  validation suite (:mod:`flyknot_tools.rope_validate`); exit 1 when a case fails.
* ``flyknot-tools lab-study`` plays the robot command and Swipe over the rope model's brackets
  and over the parts of the trial-to-trial variation (:mod:`flyknot_tools.lab_study`).
* ``flyknot-tools settle-compare [--demo NAME] [--trials A-B] [--rope R] [--rule RULE]`` plays
  a demonstration's trials with and without an early end of the settle (``knot_set`` or
  ``unknot_held``; :mod:`flyknot_tools.settle_compare`).

Replaying a demonstration is part of the application: ``flyknot demo replay``. Errors print
as ``flyknot``'s do (one line on stderr, exit status 2); this module also runs as
``python -m flyknot_tools.cli ...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from flyknot.errors import ConfigError, check_int
from flyknot_app.dispatch import dispatch
from flyknot_sim.rope_fields import FIELD, SETTABLE
from flyknot_tools.demo_cli import add_demo_parser

PROG = "flyknot-tools"
ROPE_STUDY = "rope-study"


def _cmd_rope_study(args: argparse.Namespace) -> int:
    from flyknot_tools.rope_study.cli import main as rope_study_main

    rope_study_main(args.args)
    return 0


def _cmd_lab_study(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from flyknot.progress import bar_disable
    from flyknot_tools.lab_study import (
        CANDIDATES,
        ROBOT_DEMO,
        run_study,
        table_markdown,
        write_outputs,
    )

    names = list(CANDIDATES) if not args.candidates else args.candidates
    sways = [float(s) for s in args.sway]
    bar = tqdm(
        total=len(args.demos) * len(names) * len(sways),
        desc="lab study",
        unit="cell",
        disable=bar_disable(True),
    )
    rows = run_study(
        names,
        sways,
        n=args.trials,
        seed=args.seed,
        rope=args.rope,
        workers=args.workers,
        robot_demo=args.robot_demo or ROBOT_DEMO,
        demos=args.demos,
        on_cell=lambda _cell: bar.update(1),
    )
    bar.close()
    if args.out is not None:
        write_outputs(rows, args.out)
    print(table_markdown(rows), end="")
    return 0


def _cmd_rope_validate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from flyknot.progress import bar_disable
    from flyknot_sim.rope_custom import resolve_rope
    from flyknot_tools.rope_validate.suite import (
        model_with,
        results_json,
        run_many,
        table_markdown,
    )

    check_int("--workers", args.workers, 1)
    changes = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError("--set", f"must be FIELD=VALUE, got {item!r}")
        changes[key] = value
    settings = None
    if args.table is not None:
        from flyknot_sim.rope_table import load_rope_table, load_sim_settings

        table = load_rope_table(args.table)
        settings = load_sim_settings(args.table)
        ropes = []
        for r in args.ropes:
            if not (r.isdigit() and int(r) in table):
                raise ConfigError("--ropes", f"no rope {r!r} in {args.table}", sorted(table))
            ropes.append(table[int(r)])
    else:
        ropes = [resolve_rope(r, args.ropes_file) for r in args.ropes]
    models = [model_with(p, changes, settings=settings) for p in ropes]
    suite = "quick" if args.quick else "full"
    bar = tqdm(total=len(models), desc="rope-validate", unit="rope", disable=bar_disable(True))
    results = run_many(
        models,
        suite,
        args.workers,
        on_done=lambda _r: bar.update(1),
        cases=args.cases,
        pictures=args.pictures,
    )
    bar.close()
    print(results_json(results) if args.json else table_markdown(results))
    return 0 if all(r.passed for r in results if r.applies) else 1


def _cmd_closure_study(args: argparse.Namespace) -> int:
    from flyknot_tools.closure_study import run

    print(run(args.dirs, args.json))
    return 0


def _cmd_settle_compare(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from flyknot_tools.settle_compare import compare_settles, format_compared

    first, _, last = args.trials.partition("-")
    try:
        trials = range(int(first), int(last or first) + 1)
    except ValueError:
        raise ConfigError("--trials", f"must be A-B or A, got {args.trials!r}") from None
    rows = compare_settles(args.demo, trials, args.rope, args.rule)
    print(json.dumps([asdict(r) for r in rows]) if args.json else format_compared(rows, args.rule))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``flyknot-tools`` (exposed for tests and docs).

    ``rope-study`` hands everything after it to the rope study's own parser (:func:`main`
    routes it there before this parser sees it).
    """
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Offline tools of flyknot: make demonstrations, study the rope model.",
    )
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    add_demo_parser(sub)
    _add_rope_study_parser(sub)
    _add_lab_study_parser(sub)
    _add_rope_validate_parser(sub)
    _add_closure_study_parser(sub)
    _add_settle_compare_parser(sub)
    return p


def _add_rope_study_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot-tools rope-study``: handed to the rope study's own parser."""
    rs = sub.add_parser(
        ROPE_STUDY,
        help="measure the rope model variants (the table of docs/rope-model.md)",
        add_help=False,
    )
    rs.add_argument("args", nargs=argparse.REMAINDER, help="the rope study's own options")
    rs.set_defaults(func=_cmd_rope_study)


def _add_lab_study_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot-tools lab-study``: the rope model's sensitivity."""
    ls = sub.add_parser(
        "lab-study",
        help="the rope model's sensitivity: the robot command and Swipe over the brackets",
    )
    ls.add_argument(
        "--candidates",
        nargs="*",
        metavar="NAME",
        help="rows to measure (default all; names in flyknot_tools.lab_study)",
    )
    ls.add_argument(
        "--sway",
        nargs="+",
        default=["0"],
        metavar="DEG",
        help="extra initial sways [deg] (0: the settled start, the default)",
    )
    ls.add_argument("--trials", type=int, default=20, help="trials per demonstration and row")
    ls.add_argument("--seed", type=int, default=0, help="lab seed")
    ls.add_argument("--rope", type=int, default=1, help="rope id")
    ls.add_argument("--workers", type=int, default=1, help="worker processes")
    ls.add_argument(
        "--robot-demo",
        default=None,
        metavar="FILE",
        help="robot demonstration whose stored command the arm plays (default the shipped one)",
    )
    ls.add_argument(
        "--demos",
        nargs="+",
        default=["robot", "hand"],
        metavar="KIND",
        help="which to play: robot (the arm's command), hand (Swipe); default both",
    )
    ls.add_argument("--out", default=None, help="directory for lab_study.json / .md")
    ls.set_defaults(func=_cmd_lab_study)


def _add_rope_validate_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot-tools rope-validate``: the rope validation suite."""
    rv = sub.add_parser(
        "rope-validate",
        help="what every real rope of its kind does, measured on the lab's ropes (exit 1 on a "
        "failed case)",
    )
    rv.add_argument(
        "--ropes", nargs="+", default=["1", "2", "3", "4", "5", "6", "7"], help="rope ids or names"
    )
    rv.add_argument("--ropes-file", default=None, help="a ropes file with your own ropes")
    rv.add_argument(
        "--table",
        default=None,
        help="a rope table instead of the lab's (e.g. assets/ropes_elastic.toml)",
    )
    rv.add_argument("--quick", action="store_true", help="one short run of each case")
    rv.add_argument("--cases", nargs="+", metavar="CASE", help="only these cases")
    rv.add_argument(
        "--set",
        action="append",
        metavar="FIELD=VALUE",
        help=f"change a rope field ({_rope_fields_help()}) or a [simulation] setting (e.g. "
        "bend_hysteresis=0)",
    )
    rv.add_argument("--workers", type=int, default=1, help="worker processes")
    rv.add_argument("--json", action="store_true", help="print the results as JSON")
    rv.add_argument(
        "--pictures",
        default=None,
        metavar="DIR",
        help="write the pictures of the cases that draw (rest_after_motion) into DIR",
    )
    rv.set_defaults(func=_cmd_rope_validate)


def _rope_fields_help() -> str:
    """The rope fields ``--set`` may change, with their units: ``diameter [m], ...``."""
    units = {n: FIELD[n].unit for n in SETTABLE}
    return ", ".join(f"{n} [{u}]" if u else n for n, u in units.items())


def _add_closure_study_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot-tools closure-study``: free-ray vs tube closures."""
    cs = sub.add_parser(
        "closure-study",
        help="the held end closed by free rays vs the tube, over recorded trials (docs/judge.md)",
    )
    cs.add_argument("dirs", nargs="+", help="run or replay directories")
    cs.add_argument("--json", action="store_true", help="print one JSON object, trial by trial")
    cs.set_defaults(func=_cmd_closure_study)


def _add_settle_compare_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot-tools settle-compare``: the settle with and without an early end."""
    sc = sub.add_parser(
        "settle-compare",
        help="a demonstration's trials with and without an early end of the settle "
        "(docs/performance.md)",
    )
    sc.add_argument("--demo", default="robot", help="a shipped demonstration (default robot)")
    sc.add_argument(
        "--trials", default="10-29", help="lab seeds (robot) or replays (hand): A-B (10-29)"
    )
    sc.add_argument("--rope", type=int, default=1, help="rope of the robot command (default 1)")
    sc.add_argument(
        "--rule",
        default="knot_set",
        help="the early end compared: knot_set (default) or unknot_held",
    )
    sc.add_argument("--json", action="store_true", help="print one JSON list, trial by trial")
    sc.set_defaults(func=_cmd_settle_compare)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``flyknot-tools`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == [ROPE_STUDY]:  # its options are the rope study's, parsed by it
        args = argparse.Namespace(cmd=ROPE_STUDY, args=argv[1:], func=_cmd_rope_study)
    else:
        args = build_parser().parse_args(argv)
    return dispatch(args, PROG)


if __name__ == "__main__":
    raise SystemExit(main())

"""``flyknot-tools demo``: make demonstrations (the actions of :mod:`flyknot_tools.cli`'s
``demo`` command: ``synthesize``, ``robot``, ``robot-rate``, ``record``, ``rerecord``)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from flyknot.errors import ConfigError, SolverError, check_int


def _cmd_synthesize(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from flyknot_sim.hand_params import HandParams
    from flyknot_sim.rope_table import get_rope
    from flyknot_tools.hand_demos.synthesis import SynthConfig, stage_keeper, synthesize
    from flyknot_tools.hand_demos.variants import get_variant

    variant = get_variant(args.variant)
    pace = {}
    if args.envelope:
        from flyknot_tools.hand_demos.envelope import arm_envelope, shared_envelope

        env = shared_envelope(arm_envelope().envelope)
        pace = {
            "speed_limit": env.speed,
            "axis_rate_limit": env.axis_rate,
            "accel_limit": env.accel,
        }
    for flag, f in (
        ("max_speed", "speed_limit"),
        ("max_axis_rate", "axis_rate_limit"),
        ("max_accel", "accel_limit"),
    ):
        value = getattr(args, flag)
        if value is not None:
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"--{flag.replace('_', '-')}", f"must be > 0, got {value!r}")
            pace[f] = value
    variant = replace(variant, **pace)
    check_int("--seed", args.seed, 0)
    check_int("--check-repeats", args.check_repeats, 0)
    get_rope(args.rope)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise ConfigError("--out", f"must be a .npz file, got {str(out)!r}")
    config = SynthConfig()
    if args.budget is not None:
        check_int("--budget", args.budget, 1)
        config = replace(config, total_budget=args.budget)
    search = replace(config.search, hand=HandParams(rope=args.rope))
    if args.throw_budget is not None:
        check_int("--throw-budget", args.throw_budget, 1)
        search = replace(search, budget=args.throw_budget)
    start = None
    if args.mirror_start and args.start is None:
        raise ConfigError("--mirror-start", "needs a start motion (--start)")
    if args.start is not None:
        start = _start_motion(args.start)
        if args.mirror_start:
            start = start.mirrored()
    if args.target_rate is not None:
        if not 0.0 < args.target_rate <= 1.0:
            raise ConfigError("--target-rate", f"must lie in (0, 1], got {args.target_rate!r}")
        search = replace(search, target_rate=args.target_rate)
    config = replace(config, search=replace(search, confirm_abort=args.confirm_abort))
    result = synthesize(
        variant,
        args.seed,
        config,
        check_repeats=args.check_repeats,
        progress=not args.quiet,
        start=start,
        last_stage=args.last_stage,
        first_stage=args.first_stage,
        on_stage=stage_keeper(
            args.seed, search.hand, out, lambda line: print(line, file=sys.stderr)
        ),
    )
    result.demo.save(out)
    summary = {"file": str(out), **result.summary()}
    _print_summary(summary, args.json)
    return 0


def _start_motion(path: str):
    """The hand motion stored in a synthesized demonstration's metadata (``--start``)."""
    from flyknot.demo import Demonstration
    from flyknot_sim.hand_motion import KnotMotion

    p = Path(path)
    if not p.is_file():
        raise ConfigError("--start", f"no file {str(p)!r}")
    motion = Demonstration.load(p).metadata.get("motion")
    if not isinstance(motion, dict):
        raise ConfigError("--start", f"{str(p)!r} holds no hand motion (made by demo synthesize?)")
    return KnotMotion.from_dict(motion)


def _load_command(path: str, field: str = "--command") -> tuple[object, float]:
    from flyknot_tools.hand_demos.envelope import load_command_file

    return load_command_file(path, field)


def _print_summary(summary: dict, as_json: bool) -> None:
    print(json.dumps(summary) if as_json else "\n".join(f"{k}: {v}" for k, v in summary.items()))


def _save_robot_demo(args: argparse.Namespace, knots, T: float, extra: dict) -> dict:
    from flyknot_tools.robot_demo import record_demonstration

    out = Path(args.out)
    if out.suffix != ".npz":
        raise ConfigError("--out", f"must be a .npz file, got {str(out)!r}")
    demo = record_demonstration(knots, T, rope=args.rope, metadata=extra)
    demo.save(out)
    return {"file": str(out), "t_c": round(demo.t_c, 4), "knot": demo.metadata["knot"], **extra}


def _cmd_robot(args: argparse.Namespace) -> int:
    import tempfile

    from flyknot_app.runner import initial_knots, prepare_target
    from flyknot_sim.scene import SceneParams, robot_base_pose
    from flyknot_tools.robot_demo import CommandSearchConfig, search_command
    from learner.kinematics import RobotModel
    from learner.rope_model import RopeModelParams

    check_int("--seed", args.seed, 0)
    config = CommandSearchConfig(
        rope=args.rope,
        evaluations=args.evaluations,
        local_evaluations=args.local_evaluations,
        target_rate=args.target_rate,
    )
    if args.start is not None:
        knots0, T0 = _load_command(args.start, "--start")
    else:
        dt = RopeModelParams().dt
        _, target = prepare_target(args.demo, dt)
        with tempfile.TemporaryDirectory() as tmp:
            z = float(robot_base_pose(SceneParams())[2])
            knots0, _ = initial_knots(args.demo, Path(tmp), RobotModel.from_mjcf(), dt, z)
        T0 = target.T
    res = search_command(knots0, T0, config, seed=args.seed, progress=not args.quiet)
    if not res.tied:
        raise SolverError(
            "robot demo search",
            "no knot",
            f"no command tied the knot in {res.evaluations} evaluations; try another --seed "
            "or more --evaluations",
        )
    start = args.start if args.start is not None else f"initial guess of demo {args.demo!r}"
    summary = _save_robot_demo(
        args,
        res.knots,
        res.T,
        {"search": {"seed": args.seed, "start": start, **res.summary(timing=False)}},
    )
    _print_summary(summary, args.json)
    return 0


def _cmd_robot_rate(args: argparse.Namespace) -> int:
    from flyknot_tools.robot_rate import RateSearchConfig, rate_search

    config = RateSearchConfig(
        rope=args.rope, generations=args.generations, popsize=args.popsize, trials=args.trials
    )
    knots0, T0 = _load_command(args.start, "--start")
    res = rate_search(
        knots0, T0, config, seed=args.seed, workers=args.workers, progress=not args.quiet
    )
    search = {"seed": args.seed, "start": args.start, **res.summary(timing=False)}
    summary = _save_robot_demo(args, res.knots, res.T, {"rate_search": search})
    _print_summary({**summary, "wall_s": round(res.wall_s, 1)}, args.json)
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    knots, T = _load_command(args.command)
    summary = _save_robot_demo(args, knots, T, {"command_file": str(args.command)})
    _print_summary(summary, args.json)
    return 0


def add_demo_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``demo synthesize|robot|robot-rate|record|rerecord`` to a ``flyknot-tools``
    subparser set.

    Args:
        subparsers: The object returned by ``parser.add_subparsers()``.

    Returns:
        The ``demo`` parser.
    """
    d = subparsers.add_parser(
        "demo", help="make a flying-knot demonstration (hand motion search, robot command)"
    )
    dsub = d.add_subparsers(dest="demo_cmd", required=True, metavar="ACTION")
    _add_demo_synthesize_parser(dsub)
    _add_demo_robot_parser(dsub)
    _add_demo_robot_rate_parser(dsub)
    _add_demo_record_parser(dsub)
    _add_demo_rerecord_parser(dsub)
    return d


def _add_demo_synthesize_parser(dsub: argparse._SubParsersAction) -> None:
    """``demo synthesize``: a hand motion searched."""
    from flyknot_tools.hand_demos.variants import VARIANTS

    s = dsub.add_parser(
        "synthesize", help="search a hand motion that ties the knot and save it as a demo"
    )
    s.add_argument("--variant", required=True, help=f"one of: {', '.join(VARIANTS)}")
    s.add_argument("--seed", type=int, default=0, help="search seed (default 0)")
    s.add_argument("--out", required=True, help="output file (.npz)")
    s.add_argument("--rope", type=int, default=1, help="rope id 1..7 (default 1)")
    s.add_argument("--budget", type=int, default=None, help="most simulated trials in total")
    s.add_argument("--max-speed", type=float, default=None, help="peak hand speed allowed [m/s]")
    s.add_argument(
        "--max-axis-rate",
        type=float,
        default=None,
        help="peak turn rate of the rope's exit axis allowed [rad/s] (a robot-paced demo)",
    )
    s.add_argument(
        "--start", default=None, help="start from this demonstration's hand motion (.npz)"
    )
    s.add_argument(
        "--mirror-start",
        action="store_true",
        help="start from the mirror image of --start's motion (y -> -y, a -> -a: the opposite "
        "twist, as Inverse is made from the reference)",
    )
    s.add_argument(
        "--throw-budget", type=int, default=None, help="most trials of the throw stage (900)"
    )
    s.add_argument("--max-accel", type=float, default=None, help="peak hand acceleration [m/s^2]")
    s.add_argument(
        "--last-stage",
        action="store_true",
        help="search the last stage alone from --start (a local search of a demonstration)",
    )
    s.add_argument(
        "--first-stage",
        action="store_true",
        help="search the first stage alone (a wind-up variant's throw), saved under its name",
    )
    s.add_argument(
        "--envelope",
        action="store_true",
        help="pace limits from the envelope the arm and a person share (the --max-* flags "
        "override its values; flyknot_tools/hand_demos/envelope.py)",
    )
    s.add_argument(
        "--target-rate",
        type=float,
        default=None,
        help="confirmation rate that ends the last stage (default 0.8)",
    )
    s.add_argument(
        "--confirm-abort",
        action="store_true",
        help="stop a candidate's confirmation once the target rate is out of reach",
    )
    s.add_argument(
        "--check-repeats",
        type=int,
        default=20,
        help="varied replays that check the saved demo (default 20; 0 skips)",
    )
    s.add_argument("--json", action="store_true", help="print a JSON summary")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synthesize)


def _add_demo_robot_parser(dsub: argparse._SubParsersAction) -> None:
    """``demo robot``: a robot command searched."""
    rb = dsub.add_parser(
        "robot",
        help="search a command the simulated arm ties the knot with; save its trial as a demo",
    )
    rb.add_argument(
        "--out", required=True, help="output file (.npz; the command is in its metadata)"
    )
    rb.add_argument("--demo", default="fast", help="start from this demo's initial guess")
    rb.add_argument("--start", default=None, help="start command (.npz with knots, T) instead")
    rb.add_argument("--seed", type=int, default=0, help="search seed (default 0)")
    rb.add_argument("--evaluations", type=int, default=1500, help="most candidates (default 1500)")
    rb.add_argument(
        "--local-evaluations",
        type=int,
        default=300,
        help="candidates of the robustness phase after the first knot (default 300)",
    )
    rb.add_argument(
        "--target-rate",
        type=float,
        default=0.6,
        help="stop the robustness phase at a command tying this fraction of 10 varied trials",
    )
    rb.add_argument("--rope", type=int, default=1, help="rope id 1..7 (default 1)")
    rb.add_argument("--json", action="store_true", help="print a JSON summary")
    rb.add_argument("--quiet", action="store_true", help="no progress bar")
    rb.set_defaults(func=_cmd_robot)


def _add_demo_robot_rate_parser(dsub: argparse._SubParsersAction) -> None:
    """``demo robot-rate``: a robot command that ties in most varied trials."""
    rr_ = dsub.add_parser(
        "robot-rate",
        help="from a tying robot command, search one that ties in most varied trials; save "
        "its nominal trial as a demo",
    )
    rr_.add_argument(
        "--start",
        required=True,
        help="start command (.npz with knots, T; or a run's final_knots.npy)",
    )
    rr_.add_argument("--out", required=True, help="output file (.npz)")
    rr_.add_argument("--generations", type=int, default=24, help="CMA-ES generations (24)")
    rr_.add_argument("--popsize", type=int, default=8, help="candidates per generation (8)")
    rr_.add_argument("--trials", type=int, default=8, help="varied trials per candidate (8)")
    rr_.add_argument("--seed", type=int, default=0, help="search seed (default 0)")
    rr_.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    rr_.add_argument("--rope", type=int, default=1, help="rope id 1..7 (default 1)")
    rr_.add_argument("--json", action="store_true", help="print a JSON summary")
    rr_.add_argument("--quiet", action="store_true", help="no progress bar")
    rr_.set_defaults(func=_cmd_robot_rate)


def _add_demo_record_parser(dsub: argparse._SubParsersAction) -> None:
    """``demo record``: a robot command's nominal trial."""
    rc = dsub.add_parser("record", help="record a robot command's nominal trial as a demo")
    rc.add_argument("--command", required=True, help="command file (.npz with knots, T)")
    rc.add_argument("--out", required=True, help="output file (.npz)")
    rc.add_argument("--rope", type=int, default=1, help="rope id 1..7 (default 1)")
    rc.add_argument("--json", action="store_true", help="print a JSON summary")
    rc.set_defaults(func=_cmd_record)


def _add_demo_rerecord_parser(dsub: argparse._SubParsersAction) -> None:
    """``demo rerecord``: a demonstration's stored motion recorded again."""
    rr = dsub.add_parser(
        "rerecord",
        help="record a demo's stored motion again in today's lab (no search) and check it",
    )
    rr.add_argument("file", help="demonstration (.npz) made by demo synthesize or demo robot")
    rr.add_argument("--out", help="output file (.npz; default: replace FILE)")
    rr.add_argument("--check", type=int, default=20, help="varied trials of the check (20)")
    rr.add_argument("--json", action="store_true", help="print a JSON summary")
    rr.set_defaults(func=_cmd_rerecord)


def _cmd_rerecord(args: argparse.Namespace) -> int:
    from flyknot.demo import Demonstration
    from flyknot_tools.demo_rerecord import rerecord

    src = Path(args.file)
    if not src.is_file():
        raise ConfigError("file", f"no demonstration {str(src)!r}")
    out = Path(args.out) if args.out else src
    if out.suffix != ".npz":
        raise ConfigError("--out", f"must be a .npz file, got {str(out)!r}")
    result = rerecord(Demonstration.load(src), args.check)
    result.demo.save(out)
    _print_summary({"file": str(out), **result.summary()}, args.json)
    return 0

"""``flyknot demo``: synthesize a flying-knot demonstration with the simulated hand, replay one.

The lead's ``flyknot_app/cli.py`` adds these with one call, ``add_demo_parser(sub)``; this module
also runs alone as ``python -m flyknot_app.demo_cli demo ...`` (same parser, same errors).

* ``flyknot demo synthesize --variant NAME --seed S --out FILE`` searches a motion of the
  variant (progress on stderr), saves the nominal trial as a demonstration (``.npz``) and
  checks it with ``--check-repeats`` varied replays (the rate goes into its metadata).
* ``flyknot demo replay FILE --rope N [--ropes ROPES] [--repeats K] [--out DIR] [--json]``
  (N: a rope id, or a rope's name, e.g. one of the ropes file ROPES) plays the stored
  motion again with the lab's trial-to-trial variation and reports the settled knot and t_c
  of each replay; ``--out`` saves each replay (``replay_000.npz``, ... ; format in
  ``assets/demos/README.md``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path

from flyknot.errors import ConfigError, SolverError
from flyknot_app.scenario import parse_rope_arg


def _positive_int(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(name, f"must be an integer >= {minimum}, got {value!r}")
    return value


def _cmd_synthesize(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from flyknot_tools import demo_synth as ds

    variant = ds.get_variant(args.variant)
    pace = {}
    for flag, f in (("max_speed", "speed_limit"), ("max_axis_rate", "axis_rate_limit")):
        value = getattr(args, flag)
        if value is not None:
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"--{flag.replace('_', '-')}", f"must be > 0, got {value!r}")
            pace[f] = value
    variant = replace(variant, **pace)
    _positive_int("--seed", args.seed, 0)
    _positive_int("--check-repeats", args.check_repeats, 0)
    from flyknot_sim.rope import get_rope

    get_rope(args.rope)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise ConfigError("--out", f"must be a .npz file, got {str(out)!r}")
    config = ds.SynthConfig()
    if args.budget is not None:
        config = replace(config, total_budget=_positive_int("--budget", args.budget))
    config = replace(config, search=replace(config.search, hand=ds.HandParams(rope=args.rope)))
    result = ds.synthesize(
        variant,
        args.seed,
        config,
        check_repeats=args.check_repeats,
        progress=not args.quiet,
    )
    result.demo.save(out)
    summary = {"file": str(out), **result.summary()}
    if args.json:
        print(json.dumps(summary))
    else:
        print("\n".join(f"{k}: {v}" for k, v in summary.items()))
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from flyknot.demo import Demonstration
    from flyknot_tools import demo_synth as ds

    _positive_int("--repeats", args.repeats)
    _positive_int("--seed", args.seed, 0)
    demo = Demonstration.load(args.file)
    result = ds.replay(
        demo,
        rope=args.rope,
        repeats=args.repeats,
        seed=args.seed,
        vary=not args.nominal,
        settle_s=args.settle,
        keep_trials=args.out is not None,
        progress=not args.json and not args.quiet,
        ropes=args.ropes,
    )
    if args.out is not None:
        from flyknot_sim.hand import HandLab

        hand = ds.hand_from_demo(demo, result.rope, vary=False, ropes=args.ropes)
        rope_binding = HandLab(hand).rope
        for i, trial in enumerate(result.trials):
            ds.save_replay(
                Path(args.out) / f"replay_{i:03d}.npz",
                trial,
                rope_binding,
                rope=result.rope,
                seed=args.seed,
                index=i,
                source=str(args.file),
            )
    if args.json:
        print(json.dumps(result.to_json()))
    else:
        for i, (o, t) in enumerate(zip(result.outcomes, result.t_c, strict=True)):
            tc = "none" if t is None else f"{t:.3f} s"
            print(f"replay {i}: {o}, t_c {tc}")
        print(f"knots: {result.knots}/{len(result.outcomes)} (rope {result.rope})")
    return 0


def _load_command(path: str) -> tuple[object, float]:
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise ConfigError("--command", f"no file {str(p)!r}")
    with np.load(p) as z:
        if "knots" not in z.files or "T" not in z.files:
            raise ConfigError("--command", f"{str(p)!r} needs arrays 'knots' and 'T'")
        return np.array(z["knots"]), float(z["T"])


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

    _positive_int("--seed", args.seed, 0)
    config = CommandSearchConfig(
        rope=args.rope,
        evaluations=args.evaluations,
        local_evaluations=args.local_evaluations,
        target_rate=args.target_rate,
    )
    if args.start is not None:
        knots0, T0 = _load_command(args.start)
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


def _cmd_record(args: argparse.Namespace) -> int:
    knots, T = _load_command(args.command)
    summary = _save_robot_demo(args, knots, T, {"command_file": str(args.command)})
    _print_summary(summary, args.json)
    return 0


def add_demo_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``demo synthesize`` and ``demo replay`` to a ``flyknot`` subparser set.

    Args:
        subparsers: The object returned by ``parser.add_subparsers()``.

    Returns:
        The ``demo`` parser.
    """
    from flyknot_tools.demo_synth import VARIANTS

    d = subparsers.add_parser("demo", help="synthesize or replay a flying-knot demonstration")
    dsub = d.add_subparsers(dest="demo_cmd", required=True, metavar="ACTION")

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
        "--check-repeats",
        type=int,
        default=20,
        help="varied replays that check the saved demo (default 20; 0 skips)",
    )
    s.add_argument("--json", action="store_true", help="print a JSON summary")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synthesize)

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

    rc = dsub.add_parser("record", help="record a robot command's nominal trial as a demo")
    rc.add_argument("--command", required=True, help="command file (.npz with knots, T)")
    rc.add_argument("--out", required=True, help="output file (.npz)")
    rc.add_argument("--rope", type=int, default=1, help="rope id 1..7 (default 1)")
    rc.add_argument("--json", action="store_true", help="print a JSON summary")
    rc.set_defaults(func=_cmd_record)

    r = dsub.add_parser("replay", help="replay a synthesized demo's hand motion")
    r.add_argument("file", help="demonstration file (.npz) made by `demo synthesize`")
    r.add_argument(
        "--rope",
        type=parse_rope_arg,
        default=None,
        help="rope id 1..7 or a rope's name, e.g. of --ropes (default: the demo's)",
    )
    r.add_argument(
        "--ropes", default=None, help="your own ropes file (.toml; see assets/ropes_example.toml)"
    )
    r.add_argument("--repeats", type=int, default=1, help="number of replays (default 1)")
    r.add_argument("--seed", type=int, default=0, help="variation seed (default 0)")
    r.add_argument(
        "--nominal", action="store_true", help="no trial-to-trial variation (exact replay)"
    )
    r.add_argument("--settle", type=float, default=None, help="settling time [s]")
    r.add_argument("--out", default=None, help="directory for one file per replay")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_replay)
    return d


def build_parser() -> argparse.ArgumentParser:
    """A ``flyknot`` parser with only the ``demo`` command (for running this module alone)."""
    p = argparse.ArgumentParser(prog="flyknot")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    add_demo_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``flyknot demo ...`` (errors as ``flyknot`` prints them, exit status 2)."""
    from flyknot_app.cli import dispatch

    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())

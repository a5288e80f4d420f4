"""``flyknot demo replay``: replay a synthesized flying-knot demonstration in the hand lab.

The lead's ``flyknot_app/cli.py`` adds it with one call, ``add_demo_parser(sub)``; this module
also runs alone as ``python -m flyknot_app.demo_cli demo replay ...`` (same parser, same
errors).

* ``flyknot demo replay FILE --rope N [--ropes ROPES] [--repeats K] [--out DIR] [--json]``
  (N: a rope id, or a rope's name, e.g. one of the ropes file ROPES) plays the stored
  motion again with the lab's trial-to-trial variation and reports the settled knot and t_c
  of each replay; ``--out`` saves each replay (``replay_000.npz``, ... ; format in
  ``assets/demos/README.md``).

Making demonstrations (``demo synthesize``, ``demo robot``, ``demo record``) is the offline
tools' work: ``flyknot-tools demo ...`` (``docs/demo-synthesis.md``).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

from flyknot.errors import check_int
from flyknot_app.scenario import parse_rope_arg


def _cmd_replay(args: argparse.Namespace) -> int:
    from flyknot.demo import Demonstration
    from flyknot_sim.hand import HandLab
    from flyknot_sim.hand_replay import hand_from_demo, replay, save_replay

    check_int("--repeats", args.repeats, 1)
    check_int("--seed", args.seed, 0)
    demo = Demonstration.load(args.file)
    result = replay(
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
        hand = hand_from_demo(demo, result.rope, vary=False, ropes=args.ropes)
        rope_binding = HandLab(hand).rope
        for i, trial in enumerate(result.trials):
            save_replay(
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


def add_demo_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``demo replay`` to a ``flyknot`` subparser set.

    Args:
        subparsers: The object returned by ``parser.add_subparsers()``.

    Returns:
        The ``demo`` parser.
    """
    d = subparsers.add_parser("demo", help="replay a synthesized flying-knot demonstration")
    dsub = d.add_subparsers(dest="demo_cmd", required=True, metavar="ACTION")

    r = dsub.add_parser("replay", help="replay a synthesized demo's hand motion")
    r.add_argument("file", help="demonstration file (.npz) made by `flyknot-tools demo synthesize`")
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
    """Run ``flyknot demo replay ...`` (errors as ``flyknot`` prints them, exit status 2)."""
    from flyknot_app.cli import dispatch

    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())

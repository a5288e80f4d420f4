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
from typing import Any

from flyknot.errors import ConfigError, check_int
from flyknot_app.scenario import parse_rope_arg


def _cmd_replay(args: argparse.Namespace) -> int:
    from flyknot.demo import Demonstration
    from flyknot_app.cells import variation_from, variation_pairs
    from flyknot_sim.hand import HandLab
    from flyknot_sim.hand_params import HandVariation
    from flyknot_sim.hand_replay import hand_from_demo, replay, save_replay

    check_int("--repeats", args.repeats, 1)
    check_int("--seed", args.seed, 0)
    variation = variation_from(HandVariation, variation_pairs(args.variation), "--variation")
    if args.nominal and args.variation:
        raise ConfigError("--variation", "a --nominal replay has no variation to change")
    demo = Demonstration.load(args.file)
    result = replay(
        demo,
        rope=args.rope,
        repeats=args.repeats,
        seed=args.seed,
        vary=not args.nominal,
        variation=variation,
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
        for i, (v, t) in enumerate(zip(result.verdicts, result.t_c, strict=True)):
            tc = "none" if t is None else f"{t:.3f} s"
            print(f"replay {i}: {'diverged' if v is None else v.describe()}, t_c {tc}")
        n = len(result.outcomes)
        print(f"knots in the hanging rope: {result.knots}/{n} (rope {result.rope})")
    return 0


def _demo_files(paths: Sequence[str]) -> list[Path]:
    """The demonstration files named: files as given, directories by their ``*.npz``."""
    from flyknot.errors import ConfigError

    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(p.glob("*.npz")))
        elif p.is_file():
            out.append(p)
        else:
            raise ConfigError("path", f"no file or directory {str(p)!r}")
    if not out:
        raise ConfigError("path", f"no .npz files in {', '.join(map(str, paths))}")
    return out


def _load_for_detection(path: Path):
    """A demonstration or replay file as a Demonstration, and the t_c it records (None for a
    replay without self-contact or a capture whose t_c is unknown: then the Demonstration
    carries its first sample time as a placeholder, which detection never reads)."""
    import numpy as np

    from flyknot.demo import Demonstration
    from flyknot.errors import RecordError

    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: np.array(z[k]) for k in ("t", "hand_pos", "hand_quat", "markers")}
    except (KeyError, ValueError, OSError) as e:
        raise RecordError(f"{str(path)!r} is not a demonstration file: {e}") from e
    recorded = meta.get("t_c")
    demo = Demonstration(
        **arrays,
        t_c=float(arrays["t"][0]) if recorded is None else recorded,
        rope=int(meta.get("rope", 1)),
        metadata=meta.get("metadata", {}),
    )
    return demo, recorded


def critical_rows(paths: Sequence[str], diameter: float | None = None) -> list[dict[str, Any]]:
    """t_c detected from each demonstration's markers (:func:`learner.critical_time.
    detect_critical_time`) beside the t_c the file records (for simulated demonstrations and
    replays: the simulator's first rope self-contact).

    Args:
        paths: Demonstration or replay files, or directories of them.
        diameter: Rope diameter [m] (default: that of the file's rope in ``assets/ropes.toml``).

    Returns:
        One row per file: ``file``, ``t_c`` (recorded, None if the rope never touched
        itself), ``detected`` (None if nothing fired), ``cue``, ``error_ms`` (detected -
        recorded, None unless both exist).
    """
    from flyknot_sim.rope_table import get_rope
    from learner.critical_time import detect_critical_time

    rows = []
    for f in _demo_files(paths):
        demo, recorded = _load_for_detection(f)
        d = diameter if diameter is not None else get_rope(demo.rope).diameter
        found = detect_critical_time(demo, d)
        err = None
        if found.t_c is not None and recorded is not None:
            err = round(1000.0 * (found.t_c - recorded), 1)
        rows.append(
            {
                "file": str(f),
                "t_c": recorded,
                "detected": found.t_c,
                "cue": found.cue,
                "error_ms": err,
            }
        )
    return rows


def write_detected(source: str, out: str, row: dict[str, Any]) -> None:
    """Save ``source`` again as ``out`` with t_c = the detected one (a capture without a
    known t_c becomes a demonstration the learner takes); the metadata keep the recorded t_c
    (``t_c_recorded``) and say where t_c came from (``t_c_source``: ``markers/<cue>``)."""
    from dataclasses import replace

    from flyknot.errors import ConfigError

    if row["detected"] is None:
        raise ConfigError("--write", f"no critical time found in {source!r}: nothing written")
    if Path(out).suffix != ".npz":
        raise ConfigError("--write", f"must be a .npz file, got {out!r}")
    demo, recorded = _load_for_detection(Path(source))
    meta = {**demo.metadata, "t_c_recorded": recorded, "t_c_source": f"markers/{row['cue']}"}
    replace(demo, t_c=row["detected"], metadata=meta).save(out)


def critical_summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Errors over the rows with both times: count, median, median |e|, 90th percentile of
    |e| and the worst (largest |e|, signed) [ms]; rows with only one of the two counted."""
    import numpy as np

    e = np.array([r["error_ms"] for r in rows if r["error_ms"] is not None], dtype=float)
    out: dict[str, Any] = {
        "n": len(e),
        "no_detection": sum(r["detected"] is None and r["t_c"] is not None for r in rows),
        "no_contact": sum(r["t_c"] is None for r in rows),
    }
    if len(e):
        out |= {
            "median_ms": float(np.median(e)),
            "median_abs_ms": float(np.median(np.abs(e))),
            "p90_abs_ms": float(np.percentile(np.abs(e), 90)),
            "worst_ms": float(e[np.argmax(np.abs(e))]),
        }
    return out


def _cmd_critical(args: argparse.Namespace) -> int:
    from flyknot.errors import check_positive

    if args.diameter is not None:
        check_positive("--diameter", args.diameter)
    rows = critical_rows(args.paths, args.diameter)
    if args.write is not None:
        from flyknot.errors import ConfigError

        if len(rows) != 1:
            raise ConfigError("--write", f"needs exactly one input file, got {len(rows)}")
        write_detected(rows[0]["file"], args.write, rows[0])
    summary = critical_summary(rows)
    if args.json:
        print(json.dumps({"rows": rows, "summary": summary}))
        return 0
    for r in rows:
        rec = "none" if r["t_c"] is None else f"{r['t_c']:.3f} s"
        det = "none" if r["detected"] is None else f"{r['detected']:.3f} s ({r['cue']})"
        err = "" if r["error_ms"] is None else f", error {r['error_ms']:+.0f} ms"
        print(f"{r['file']}: recorded {rec}, detected {det}{err}")
    if summary["n"]:
        print(
            f"{summary['n']} with both: median error {summary['median_ms']:+.1f} ms, median "
            f"|error| {summary['median_abs_ms']:.1f} ms, 90th percentile "
            f"{summary['p90_abs_ms']:.1f} ms, worst {summary['worst_ms']:+.0f} ms"
        )
    return 0


def add_demo_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``demo replay`` to a ``flyknot`` subparser set.

    Args:
        subparsers: The object returned by ``parser.add_subparsers()``.

    Returns:
        The ``demo`` parser.
    """
    d = subparsers.add_parser(
        "demo", help="replay a flying-knot demonstration; detect its critical time"
    )
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
    r.add_argument(
        "--variation",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="change a field of the hand lab's variation (servo_gain_rel, start_delay_max_s, "
        "tempo_rel, rest_start, rest_scale, sway_deg); repeatable",
    )
    r.add_argument("--settle", type=float, default=None, help="settling time [s]")
    r.add_argument("--out", default=None, help="directory for one file per replay")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_replay)

    c = dsub.add_parser(
        "critical",
        help="detect t_c from the markers alone and compare it with the recorded t_c",
    )
    c.add_argument("paths", nargs="+", help="demonstration/replay files or directories of them")
    c.add_argument(
        "--diameter", type=float, default=None, help="rope diameter [m] (default: the file's rope)"
    )
    c.add_argument(
        "--write",
        default=None,
        metavar="OUT.npz",
        help="with one input file: save it with t_c = the detected one (for a capture "
        "whose t_c is unknown)",
    )
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.set_defaults(func=_cmd_critical)
    return d


def build_parser() -> argparse.ArgumentParser:
    """A ``flyknot`` parser with only the ``demo`` command (for running this module alone)."""
    p = argparse.ArgumentParser(prog="flyknot")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    add_demo_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``flyknot demo replay ...`` (errors as ``flyknot`` prints them, exit status 2)."""
    from flyknot_app.dispatch import dispatch

    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())

"""Commands on trials and their verdicts: ``flyknot knot``, ``trial``, ``judge``, ``results``.

Each ``_cmd_*`` runs one command from its parsed arguments; :func:`add_trial_parsers` adds
their parsers to ``flyknot``'s (:mod:`flyknot_app.cli`).
"""

from __future__ import annotations

import argparse
import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

from flyknot.errors import CommandError, ConfigError
from flyknot.geometry import turning_angles
from flyknot.record import JointCommand
from flyknot_app.scenario import parse_rope_arg


def _cmd_knot(args: argparse.Namespace) -> int:
    from flyknot.knot import load_centreline
    from flyknot.verdict import judge_centreline

    verdict = judge_centreline(load_centreline(args.file))
    print(verdict.describe() if args.verdict else verdict.knot)
    return 0


COMMAND_FORMATS = (
    "accepted formats: .csv t,q1..q7 joint targets; .npy (n, 7) float radians; "
    ".npz Bezier knots and T"
)
"""The command files :func:`load_command` reads, as its error messages list them."""

_READ_ERRORS = (ValueError, TypeError, OSError, EOFError, zipfile.BadZipFile, zlib.error)
"""What NumPy and zipfile raise for a damaged file or an array of Python objects."""


def load_command(path: str | Path) -> JointCommand:
    """A command file (README, "Command files"): ``.csv``/``.npy`` joint targets
    (:meth:`JointCommand.load`); ``.npz`` Bezier knots (``knots`` (10, 8) and ``T`` [s], as
    the robot demonstration's seed ``assets/demos/seeds/robot_command.npz`` holds); or a run's
    ``final_knots.npy`` (10, 8), whose duration ``T`` is read from ``result.json`` beside it,
    or a learning trial's ``RUN/learning/knots_NNNN.npy`` (trial NNNN + 1's command), ``T``
    from the run's ``RUN/result.json``.

    Raises:
        CommandError: A missing file, or one whose content is no command: one line naming
            the file, what is wrong and :data:`COMMAND_FORMATS`.
    """
    path = Path(path)
    if not path.is_file():
        raise CommandError(f"command file {str(path)!r} does not exist")
    reader = {".csv": JointCommand.load, ".npy": _npy_command, ".npz": _npz_command}.get(
        path.suffix, _unknown_suffix
    )
    try:
        return reader(path)
    except CommandError as e:
        raise CommandError(f"{e} ({COMMAND_FORMATS})") from None


def _unknown_suffix(path: Path) -> JointCommand:
    raise CommandError(f"command file {str(path)!r}: unknown extension {path.suffix!r}")


def _npy_command(path: Path) -> JointCommand:
    """Joint targets (n, 7), or a run's knots (10, 8) with T from ``result.json`` beside."""
    q = read_npy(path)
    if q.shape == (10, 8):
        return _bezier_command(path, q, duration_beside(path))
    try:
        return JointCommand(q)
    except CommandError as e:
        raise CommandError(f"command file {str(path)!r}: {e}") from None


def _npz_command(path: Path) -> JointCommand:
    """Bezier knots and their duration T from an ``.npz`` file."""
    arrays = read_npz(path, ("knots", "T"))
    if arrays["T"].shape != ():
        raise CommandError(
            f"command file {str(path)!r}: T must be one number [s], got shape {arrays['T'].shape}"
        )
    return _bezier_command(path, arrays["knots"], float(arrays["T"]))


def _bezier_command(path: Path, knots: np.ndarray, T: float) -> JointCommand:
    from learner.bezier import BezierCommand

    try:
        return BezierCommand(knots, T).joint_command()
    except (ConfigError, CommandError) as e:
        raise CommandError(f"command file {str(path)!r}: {e}") from None


def duration_beside(path: Path) -> float:
    """T [s] of a run's knots: from the ``result.json`` beside ``RUN/final_knots.npy``, or
    from the run's ``RUN/result.json`` for a learning trial's ``RUN/learning/knots_NNNN.npy``
    (a run plays every trial over the same T)."""
    in_learning = path.parent.name == "learning"
    result = path.parent.parent / "result.json" if in_learning else path.with_name("result.json")
    if not result.is_file():
        where = f"the run's {str(result)!r}" if in_learning else "result.json beside it"
        raise CommandError(
            f"command file {str(path)!r} holds Bezier knots (10, 8): their duration T is "
            f"read from {where}, which is missing (or give an .npz with knots and T)"
        )
    try:
        return float(json.loads(result.read_text())["T"])
    except (ValueError, KeyError, TypeError) as e:
        raise CommandError(
            f"command file {str(path)!r} holds Bezier knots (10, 8), but {str(result)!r} "
            f"holds no duration T ({type(e).__name__}: {e})"
        ) from None


def read_npy(path: Path) -> np.ndarray:
    """The array of a ``.npy`` file of numbers, read without unpickling anything.

    Raises:
        CommandError: No NumPy header, Python objects (a pickled array) or other values than
            numbers, or data cut short.
    """
    dtype = _npy_dtype(path)
    if dtype.hasobject:
        raise CommandError(
            f"command file {str(path)!r} holds Python objects (a pickled array), not numbers"
        )
    if dtype.kind not in "iuf":
        raise CommandError(f"command file {str(path)!r} holds {dtype} values, not numbers")
    try:
        return np.load(path, allow_pickle=False)
    except _READ_ERRORS as e:
        raise CommandError(f"command file {str(path)!r} is damaged: {e}") from None


def _npy_dtype(path: Path) -> np.dtype:
    """The dtype a ``.npy`` file's header declares (nothing after the header is read)."""
    fmt = np.lib.format
    try:
        with path.open("rb") as f:
            major, _ = fmt.read_magic(f)
            read_header = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
            return read_header(f)[2]
    except ValueError:
        raise CommandError(f"command file {str(path)!r} is not a NumPy .npy file") from None


def read_npz(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Arrays ``names`` of an ``.npz`` file as floats, read without unpickling anything.

    Raises:
        CommandError: Not an ``.npz`` archive, an array missing, or one that is damaged or
            holds other values than numbers.
    """
    try:
        z = np.load(path, allow_pickle=False)
    except _READ_ERRORS:
        raise CommandError(f"command file {str(path)!r} is not a NumPy .npz archive") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise CommandError(f"command file {str(path)!r} holds one array, not an .npz archive")
    with z:
        missing = [n for n in names if n not in z.files]
        if missing:
            raise CommandError(f"command file {str(path)!r} lacks arrays: {', '.join(missing)}")
        try:
            return {n: np.asarray(z[n], dtype=float) for n in names}
        except _READ_ERRORS as e:
            raise CommandError(f"command file {str(path)!r}: unreadable arrays ({e})") from None


def rest_shape(record) -> dict[str, float]:
    """The rope's shape at the end of a trial (the simulator's centreline, its last frame):
    the median and largest turning angle between consecutive segments [deg], the joint at the
    held end left out (its first segment lies between the two held vertices); {} without it."""
    line = record.truth.get("centreline") if record.truth else None
    if line is None or len(line) == 0:
        return {}
    turn = np.degrees(turning_angles(line[-1]))[1:]
    return {"rest_median_turn_deg": float(np.median(turn)), "rest_max_turn_deg": float(turn.max())}


def _cmd_trial(args: argparse.Namespace) -> int:
    from flyknot_app.cells import lab_variation, variation_pairs
    from flyknot_sim.lab import LabParams, SimLab

    out = Path(args.out)
    if args.repeats < 1:
        raise ConfigError("--repeats", f"must be an integer >= 1, got {args.repeats}")
    stems = ["trial"] if args.repeats == 1 else [f"trial_{i:03d}" for i in range(args.repeats)]
    if (out / f"{stems[0]}.json").exists() and not args.force:
        raise ConfigError("--out", f"{str(out)!r} already holds a trial; use --force to replace it")
    variation = lab_variation(variation_pairs(args.variation), "--variation")
    command = load_command(args.command)
    lab = SimLab(
        LabParams(
            rope=args.rope,
            seed=args.seed,
            settle_s=args.settle,
            ropes=args.ropes,
            variation=variation,
        )
    )
    out.mkdir(parents=True, exist_ok=True)
    summaries = []
    for stem in stems:  # the lab's trials 0, 1, ... of its seed: each with its own variation
        record = lab.run(command)
        path = record.save(out / stem)
        summaries.append(
            {
                "rope": lab.rope_params.id,
                "fault": record.fault,
                "knot": record.knot,
                "verdict": None if record.verdict is None else record.verdict.to_json(),
                "first_contact_time": record.first_contact_time,
                **rest_shape(record),
                "record": str(path),
            }
        )
        if args.repeats > 1 and not args.json:
            v = record.verdict
            print(f"{stem}: {'fault: ' + record.fault if record.fault else v.describe()}")
    if args.repeats == 1:
        summary = summaries[0]
        text = "\n".join(f"{k}: {v}" for k, v in summary.items())
        print(json.dumps(summary) if args.json else text)
        return 0
    knots = sum(x["verdict"] is not None and x["verdict"]["klass"] == "knot" for x in summaries)
    if args.json:
        print(json.dumps({"trials": summaries, "knots": knots, "repeats": args.repeats}))
    else:
        print(f"knots in the hanging rope: {knots} of {args.repeats} (rope {lab.rope_params.id})")
    return 0


def _cmd_judge(args: argparse.Namespace) -> int:
    from flyknot_app.judging import judge_command

    print(judge_command(args.dir, pictures=args.pictures, out=args.out, as_json=args.json))
    return 0


def _cmd_results(args: argparse.Namespace) -> int:
    from flyknot_app.reports.results import results_table

    command = "flyknot results " + " ".join(args.dirs) + (f" --out {args.out}" if args.out else "")
    text = results_table(args.dirs, command)
    if args.out:
        Path(args.out).write_text(text)
        print(f"written: {args.out}")
    else:
        print(text, end="")
    return 0


def add_trial_parsers(sub) -> None:
    """Add ``knot``, ``trial``, ``judge`` and ``results`` to ``flyknot``'s subparsers."""
    k = sub.add_parser(
        "knot",
        help="the knot of a rope centreline (.npy or .csv, (n, 3), held end first; the tube "
        "continues the first segment)",
    )
    k.add_argument(
        "--verdict",
        action="store_true",
        help="print the verdict: class, closure vote and where the knot sits",
    )
    k.add_argument("file", help="centreline file; first point at the held end")
    k.set_defaults(func=_cmd_knot)

    t = sub.add_parser("trial", help="run one command on the simulated lab and save its record")
    t.add_argument(
        "--rope",
        type=parse_rope_arg,
        default=1,
        help="rope id 1..7 or a rope's name, e.g. of --ropes (default 1)",
    )
    t.add_argument(
        "--ropes", default=None, help="your own ropes file (.toml; see assets/ropes_example.toml)"
    )
    t.add_argument(
        "--command",
        required=True,
        help="command file (.csv or .npy joint targets; .npz Bezier knots with knots and T; "
        "a run's final_knots.npy, T from result.json beside it; a learning trial's "
        "RUN/learning/knots_NNNN.npy, T from RUN/result.json)",
    )
    t.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="play the command this many times (the lab's trials 0.. of --seed, each varied)",
    )
    t.add_argument("--out", required=True, help="directory for the trial record")
    t.add_argument("--seed", type=int, default=0, help="trial-to-trial variation seed")
    t.add_argument(
        "--variation",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="change a field of the lab's trial-to-trial variation (servo_gain_rel, "
        "start_delay_max_s, rest_start, rest_scale, sway_deg; docs/rope-model.md has each "
        "one's source and bracket); repeatable",
    )
    t.add_argument(
        "--settle",
        type=float,
        default=None,
        help="fixed settling time after the command [s] (default: until the rope is at rest)",
    )
    t.add_argument("--force", action="store_true", help="replace a trial already in --out")
    t.add_argument("--json", action="store_true", help="print a JSON summary")
    t.set_defaults(func=_cmd_trial)

    jg = sub.add_parser(
        "judge",
        help="judge every trial under a run or replay directory again: old and new verdict, "
        "closure vote, where the knot sits, totals",
    )
    jg.add_argument("dir", help="run directory (flyknot run) or replay directory (demo replay)")
    jg.add_argument(
        "--pictures",
        action="store_true",
        help="close-up renders of every knot and one trial per other class",
    )
    jg.add_argument("--out", default=None, help="folder of the pictures (default DIR/judge)")
    jg.add_argument("--json", action="store_true", help="print one JSON object")
    jg.set_defaults(func=_cmd_judge)

    rs = sub.add_parser(
        "results",
        help="one dated results table (markdown) from run, baseline, replay or trial dirs",
    )
    rs.add_argument("dirs", nargs="+", help="measured directories, in the table's order")
    rs.add_argument("--out", default=None, help="markdown file (default: print)")
    rs.set_defaults(func=_cmd_results)

"""``flyknot diagnose``: the learner's measuring sticks, for a run or a demonstration.

    flyknot diagnose floor RUN_DIR [--budget N] [--repeats K]     # a run of `flyknot run`
    flyknot diagnose floor --demo fast --rope 1 [--budget N]      # a demonstration alone
    flyknot diagnose decided DIR ... [--truth]                    # trials' records
    flyknot diagnose variation RUN_DIR [--trial K] [--plays N]    # a run's command

``floor``: the reachable floor (:mod:`flyknot_app.diagnose.floor`) from the run's initial command
(or the demonstration's initial guess), for the run's rope, lab, demonstration window and
critical weights (a demonstration alone: the scenarios' window and weights, ``--w-crit-vel``
to change the velocity weight); written to ``RUN_DIR/floor.json`` (or ``--out``).
``--repeats K`` plays the floor's command K times with the lab's trial-to-trial variation and
counts its knots. Only a simulated cell can be diagnosed this way; a run on a real cell is
refused in one line.

``decided``: when the rope states of the trials that tied and of those that did not part
(:mod:`flyknot_app.diagnose.decided`), from any records: a real lab's too (markers only).

``variation``: which component of the lab's trial-to-trial variation decides the knot of a
run's command (:mod:`flyknot_app.diagnose.variation_split`): by default the command of the run's
first knot, else of its lowest cost; written to ``RUN_DIR/variation.json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError
from flyknot.options import from_mapping
from flyknot.progress import bar_disable
from flyknot_app.diagnose.floor import FloorParams
from flyknot_app.learner_settings import SCENARIO_CRIT_VEL_WEIGHT, SCENARIO_WINDOW, scenario_weights
from flyknot_app.scenario import parse_rope_arg
from learner.inverse_qp import InverseModelWeights


def _run_inputs(run_dir: Path) -> dict[str, Any]:
    """A run directory's demonstration, window, cell and initial command."""
    result = run_dir / "result.json"
    knots0 = run_dir / "learning" / "knots_0000.npy"
    if not result.is_file() or not knots0.is_file():
        raise ConfigError(
            "RUN_DIR",
            f"{str(run_dir)!r} is not a finished run of `flyknot run` (needs result.json and "
            "learning/knots_0000.npy; give OUT/runs/NAME)",
        )
    opts = json.loads(result.read_text())
    return {
        "demo": opts["demo"],
        "window": (float(opts["follow_through_s"]), float(opts["path_frac"])),
        "cell": opts.get("cell", "sim"),
        "cell_values": {
            "rope": opts["rope"],
            "seed": opts["seed"],
            "settle_s": opts.get("settle_s"),
            "ropes": opts.get("ropes"),
            **opts.get("cell_options", {}),
        },
        "knots0": np.load(knots0),
        "out": run_dir / "floor.json",
        "weights": opts.get("weights"),  # read by the floor alone (_objective_weights)
    }


def _demo_inputs(args: argparse.Namespace) -> dict[str, Any]:
    """A demonstration's inputs: the simulated lab with ``--rope``, the initial guess."""
    if args.out is None:
        raise ConfigError("--out", "give the result's file when diagnosing a demonstration")
    return {
        "demo": args.demo,
        "window": (args.follow_through, args.path_frac),
        "cell": "sim",
        "cell_values": {"rope": args.rope, "seed": args.seed},
        "knots0": None,
        "out": Path(args.out),
        "weights": asdict(
            replace(
                scenario_weights(),
                w_crit_vel=SCENARIO_CRIT_VEL_WEIGHT if args.w_crit_vel is None else args.w_crit_vel,
            )
        ),
    }


def _objective_weights(inputs: dict[str, Any]) -> InverseModelWeights:
    """The floor's QP weights: the run's own (its ``result.json``) or the demonstration's."""
    if not isinstance(inputs["weights"], dict):
        raise ConfigError("RUN_DIR", "the run's result.json names no QP weights ('weights')")
    return from_mapping(InverseModelWeights, inputs["weights"])


def _cmd_floor(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from flyknot_app.cells import cell_spec, check_oracle, sim_lab_params
    from flyknot_app.diagnose.floor import reachable_floor
    from flyknot_app.runner import initial_knots, prepare_target
    from flyknot_sim.scene import robot_base_pose
    from learner.kinematics import RobotModel
    from learner.rope_model import RopeModelParams

    if (args.run is None) == (args.demo is None):
        raise ConfigError("RUN_DIR", "give a run directory or --demo, not both or neither")
    if args.run and args.w_crit_vel is not None:
        raise ConfigError("--w-crit-vel", "a run's floor uses the run's own weights; give --demo")
    inputs = _run_inputs(Path(args.run)) if args.run else _demo_inputs(args)
    weights = _objective_weights(inputs)  # validated before any work
    spec = cell_spec(inputs["cell"], inputs["cell_values"])
    check_oracle(inputs["cell"], dry_run=bool(getattr(spec, "dry_run", False)))
    params = FloorParams(budget=args.budget)  # validated before any work
    lab_params = sim_lab_params(spec)
    robot, dt = RobotModel.from_mjcf(), RopeModelParams().dt
    _, target = prepare_target(inputs["demo"], dt, inputs["window"])
    knots0 = inputs["knots0"]
    if knots0 is None:  # the demonstration's initial guess, for the lab's base height
        base_height = float(robot_base_pose(lab_params.scene)[2])
        out_dir = inputs["out"].parent
        knots0, _ = initial_knots(inputs["demo"], out_dir, robot, dt, base_height, inputs["window"])
    bar = tqdm(total=params.budget, desc="floor", unit="play", disable=bar_disable(not args.json))

    def on_iteration(plays: int, cost: float) -> None:
        bar.n = plays
        bar.set_postfix_str(f"cost {cost:.3g}")
        bar.refresh()

    try:
        res = reachable_floor(
            lab_params,
            target,
            knots0,
            robot,
            RopeModelParams(),
            params,
            weights=weights,
            on_iteration=on_iteration,
        )
    finally:
        bar.close()
    out = res.to_json() | {
        "demo": inputs["demo"], "rope": spec.rope, "t_c": target.t_c, "T": target.T
    }  # fmt: skip
    if args.repeats:
        out["repeats"] = _repeat_classes(lab_params, res.knots, target.T, args.repeats)
    inputs["out"].parent.mkdir(parents=True, exist_ok=True)
    inputs["out"].write_text(json.dumps(out, indent=2))
    print(json.dumps(out) if args.json else format_floor(out, inputs["out"]))
    return 0


def _repeat_classes(lab_params, knots: np.ndarray, T: float, n: int) -> list[str]:
    """The verdict class of each of ``n`` varied plays of ``knots`` (trials 0..n-1)."""
    from flyknot_sim.lab import SimLab
    from learner.bezier import BezierCommand

    lab = SimLab(lab_params)
    command = BezierCommand(knots, T).joint_command()
    classes = []
    for _ in range(n):
        record = lab.run(command)
        classes.append("fault" if record.fault else record.verdict.klass)
    return classes


def format_floor(out: dict, path: Path) -> str:
    """The floor's result as a few lines of text."""
    lines = [
        f"demo {out['demo']}, rope {out['rope']}: floor {out['cost']:.3f} after {out['plays']} "
        f"plays ({out['stopped_because']}); position part {out['position_part']:.3f}, "
        f"velocity part {out['velocity_part']:.3f}",
        "cost per Jacobian: " + ", ".join(f"{c:.3g}" for c in out["costs"]),
        "marker position error [cm]: "
        + " ".join(f"{100 * e:.1f}" for e in out["marker_position_error"]),
        "marker velocity error [m/s]: "
        + " ".join(f"{e:.1f}" for e in out["marker_velocity_error"]),
        "demo marker speed [m/s]:     " + " ".join(f"{e:.1f}" for e in out["demo_marker_speed"]),
    ]
    if "repeats" in out:
        knots = sum(c == "knot" for c in out["repeats"])
        lines.append(f"the floor's command tied {knots} of {len(out['repeats'])} varied plays")
    lines.append(f"written to {path}")
    return "\n".join(lines)


def _cmd_decided(args: argparse.Namespace) -> int:
    from flyknot_app.diagnose.decided import (
        lead_after_contact,
        record_stems,
        separation,
        trial_states,
    )
    from learner.inverse_qp import InverseModelWeights

    if args.step <= 0 or args.end <= 0:
        raise ConfigError("--step", "--step and --end must be > 0 [s]")
    stems = record_stems(args.dirs)
    t = np.arange(0.0, args.end + 1e-9, args.step)
    states, tied, contacts = trial_states(stems, t, truth=args.truth)
    if tied.sum() < 2 or (~tied).sum() < 2:
        raise ConfigError(
            "DIR", f"needs at least two trials that tied and two that did not, got "
            f"{int(tied.sum())} and {int((~tied).sum())}"
        )  # fmt: skip
    sep = separation(t, states, tied, args.threshold)
    out = sep.to_json() | {"source": "truth" if args.truth else "markers"}
    out |= lead_after_contact(sep.t_decided, contacts, InverseModelWeights().w_crit_pos)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=2))
    print(json.dumps(out) if args.json else format_decided(sep, out))
    return 0


def format_decided(sep, out: dict) -> str:
    """The separation's result (and ``out``'s lead after the first contact) as text lines."""
    finite = np.isfinite(sep.ratio)
    peak = int(np.nanargmax(sep.ratio)) if finite.any() else None
    lines = [
        f"{sep.n_knot} trials tied, {sep.n_other} did not ({out['source']})",
        "decided at "
        + (f"{sep.t_decided:.3f} s" if sep.t_decided is not None else "no time in the range")
        + f" (separation >= {sep.threshold:g} from then on)",
    ]
    if peak is not None:
        lines.append(
            f"largest separation {sep.ratio[peak]:.2f} at {sep.t[peak]:.3f} s "
            f"(class distance {100 * sep.distance[peak]:.1f} cm, spread "
            f"{100 * sep.spread[peak]:.1f} cm)"
        )
    if "lead_s" in out:
        lines.append(
            f"{1000 * out['lead_s']:.0f} ms after the median first self-contact "
            f"({out['t_contact']:.3f} s): velocities weighed as that much position, "
            f"--set weights.w_crit_vel={out['w_crit_vel']:.3g} (the paper's 0.00375 is 12 ms)"
        )
    return "\n".join(lines)


def _run_command(run_dir: Path, trial: int | None) -> tuple[int, np.ndarray, float]:
    """The run's trial ``trial`` (1-based; default its first knot, else its lowest cost) and
    that trial's command (knots (10, 8), T [s])."""
    opts = json.loads((run_dir / "result.json").read_text())
    costs = opts["costs"]
    if trial is None:
        tts = opts.get("trials_to_success")
        trial = int(tts) if tts else int(np.nanargmin(np.asarray(costs, dtype=float))) + 1
    if not 1 <= trial <= len(costs):
        raise ConfigError("--trial", f"must be 1..{len(costs)} (the run's trials), got {trial}")
    return trial, np.load(run_dir / "learning" / f"knots_{trial - 1:04d}.npy"), float(opts["T"])


def _variation_source(
    args: argparse.Namespace,
) -> tuple[str, dict, np.ndarray, float, dict, Path | None]:
    """What ``diagnose variation`` plays: (its name, the lab's cell values, knots, T [s], the
    source's fields of the result, the result's default file or None)."""
    if (args.run is None) == (args.floor is None):
        raise ConfigError("RUN_DIR", "give a run directory or --floor, not both or neither")
    if args.floor:
        doc = json.loads(Path(args.floor).read_text())
        if "knots" not in doc or "T" not in doc:
            raise ConfigError(
                "--floor", f"{args.floor!r} is not a result of `flyknot diagnose floor`"
            )
        values = {"rope": doc["rope"], "seed": 0}
        knots, T = np.asarray(doc["knots"]), doc["T"]
        return "the floor's command", values, knots, T, {"floor": str(args.floor)}, None
    run_dir = Path(args.run)
    inputs = _run_inputs(run_dir)
    if inputs["cell"] != "sim":
        raise ConfigError(
            "RUN_DIR",
            f"only a simulated lab can switch its variation off; this run's cell is "
            f"{inputs['cell']!r}",
            ["sim"],
        )
    trial, knots, T = _run_command(run_dir, args.trial)
    fields = {"run": str(run_dir), "trial": trial}
    return (
        f"trial {trial}'s command",
        inputs["cell_values"],
        knots,
        T,
        fields,
        run_dir / "variation.json",
    )


def _cmd_variation(args: argparse.Namespace) -> int:
    from flyknot_app.cells import cell_spec, lab_variation, sim_lab_params, variation_pairs
    from flyknot_app.diagnose.variation_split import format_split, lab_play, split_variation

    what, values, knots, T, fields, default = _variation_source(args)
    changed = variation_pairs(args.variation)
    lab_variation(changed, "--variation")
    values = {**values, "variation": {**values.get("variation", {}), **changed}}
    lab_params = sim_lab_params(cell_spec("sim", values))
    split = split_variation(lab_params, lab_play(knots, T), args.plays)
    out = split.to_json() | fields | {"variation": values["variation"]}
    path = Path(args.out) if args.out else default
    if path is not None:
        path.write_text(json.dumps(out, indent=2))
    text = f"{what}, {args.plays} plays per setting:\n" + format_split(split)
    if path is not None and default is not None:
        text += f"\nwritten to {path}"
    print(json.dumps(out) if args.json else text)
    return 0


def add_window_arguments(parser: argparse.ArgumentParser, when: str = "") -> None:
    """``--follow-through`` and ``--path-frac``: the demonstration window, by default the
    scenarios' (``when`` says when they apply, e.g. ``", with --demo"``)."""
    parser.add_argument(
        "--follow-through",
        type=float,
        default=SCENARIO_WINDOW[0],
        help=f"window t_f - t_c [s]{when} (default {SCENARIO_WINDOW[0]:g})",
    )
    parser.add_argument(
        "--path-frac",
        type=float,
        default=SCENARIO_WINDOW[1],
        help=f"window start path fraction{when} (default {SCENARIO_WINDOW[1]:g})",
    )


def add_diagnose_parser(sub: argparse._SubParsersAction) -> None:
    """``flyknot diagnose floor``, ``decided`` and ``variation``."""
    d = sub.add_parser("diagnose", help="the learner's measuring sticks (simulated lab)")
    dsub = d.add_subparsers(dest="action", required=True, metavar="ACTION")
    f = dsub.add_parser(
        "floor",
        help="the lowest critical cost a command within the limits reaches (lab's Jacobian)",
    )
    f.add_argument("run", nargs="?", metavar="RUN_DIR", help="a run directory (OUT/runs/NAME)")
    f.add_argument("--demo", help="a demonstration (name or file) instead of a run")
    f.add_argument(
        "--rope", type=parse_rope_arg, default=1, help="rope id 1..7 or a rope's name (--demo)"
    )
    f.add_argument("--seed", type=int, default=0, help="the lab's seed, with --demo")
    add_window_arguments(f, ", with --demo")
    f.add_argument(
        "--w-crit-vel",
        type=float,
        default=None,
        help="the cost's marker velocity weight [s^2/m^2], with --demo (default "
        f"{SCENARIO_CRIT_VEL_WEIGHT:g}, the scenarios'; the paper's 0.00375)",
    )
    f.add_argument("--budget", type=int, default=FloorParams().budget, help="plays at most")
    f.add_argument("--repeats", type=int, default=0, help="varied plays of the floor's command")
    f.add_argument("--out", help="the result's JSON file (default RUN_DIR/floor.json)")
    f.add_argument("--json", action="store_true", help="print JSON, no progress")
    f.set_defaults(func=_cmd_floor)
    k = dsub.add_parser(
        "decided", help="when the rope states of tying and untying trials part (records)"
    )
    k.add_argument("dirs", nargs="+", metavar="DIR", help="directories of trial records")
    k.add_argument("--truth", action="store_true", help="the simulator's ground truth")
    k.add_argument("--step", type=float, default=0.01, help="time step [s] (default 0.01)")
    k.add_argument("--end", type=float, default=2.0, help="last time [s] (default 2)")
    k.add_argument("--threshold", type=float, default=1.0, help="separation that decides")
    k.add_argument("--out", help="write the result as JSON")
    k.add_argument("--json", action="store_true", help="print JSON")
    k.set_defaults(func=_cmd_decided)
    v = dsub.add_parser(
        "variation", help="which part of the lab's variation decides a command's knot"
    )
    v.add_argument("run", nargs="?", metavar="RUN_DIR", help="a run directory (OUT/runs/NAME)")
    v.add_argument("--floor", help="a result of `flyknot diagnose floor` instead of a run")
    v.add_argument(
        "--trial", type=int, help="its trial (default: the first knot, else lowest cost)"
    )
    v.add_argument("--plays", type=int, default=12, help="varied plays per setting (default 12)")
    v.add_argument(
        "--variation",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="split a changed variation (over the run's own): e.g. servo_gain_rel=0.003; "
        "repeatable",
    )
    v.add_argument("--out", help="the result's JSON file (default RUN_DIR/variation.json)")
    v.add_argument("--json", action="store_true", help="print JSON")
    v.set_defaults(func=_cmd_variation)

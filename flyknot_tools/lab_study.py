"""The rope model's sensitivity: the demonstrations over the brackets of its unmeasured values.

``flyknot-tools lab-study`` plays, for every candidate lab (a row: the lab's defaults with
one or more physics switches changed) and every start (the settled start, or an extra
initial sway of ``sway_deg``):

* the robot demonstration's command (``assets/demos/robot.npz``'s ``command_knots``) on the
  arm in :class:`flyknot_sim.lab.SimLab`, trials ``0 .. n - 1`` of lab seed ``seed``;
* the Swipe hand demonstration (``assets/demos/swipe.npz``) in the hand lab
  (:func:`flyknot_sim.hand_replay.replay`), replays ``0 .. n - 1`` of seed ``seed``;

and reports per row the knots tied, the failure anatomy of the rest
(:func:`flyknot_app.anatomy.diagnosis.diagnose`, against each demonstration's t_c), how the
verdict was
reached (at rest, contact-free, at the cap), the mean simulated seconds per trial and the wall
seconds per simulated second. The switches are the lab's own (``LabParams`` / ``HandParams``
fields) and the rope table's (:class:`flyknot_sim.rope_table.RopeParams` fields); no value
here is new physics: each comes with its source in ``assets/ropes.toml`` or
``docs/rope-model.md``. The results of ``docs/rope-model.md``, "Sensitivity over the
brackets" (prose, robot / Swipe ties per row), are this tool's output.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, check_int, check_nonnegative

DEMOS = Path(__file__).resolve().parents[1] / "assets" / "demos"
ROBOT_DEMO = DEMOS / "robot.npz"
DEMO_KINDS = ("robot", "hand")  # the arm's command in the arm's lab; Swipe in the hand lab


@dataclass(frozen=True)
class Candidate:
    """One row: a name and the switches it sets.

    Attributes:
        name: Row label (what differs from the lab's defaults).
        rope: Rope-table fields replaced (``bend_modulus``, ``bend_hysteresis``,
            ``friction``, ...), values for rope 1 (the demonstrations' rope).
        lab: Lab fields replaced in both labs (``twist``, ``bend_friction`` moment [N m]).
        sim: ``[simulation]`` settings replaced in both labs (``cone``, ``impratio``).
        variation: Trial-to-trial variation fields replaced, in each lab that has them
            (``servo_gain_rel``, ``start_delay_max_s``, ``rest_start``; ``tempo_rel`` is the
            hand's alone).
        table: ``lab`` (``assets/ropes.toml``) or ``elastic`` (:data:`ELASTIC`): the rope
            table the row starts from.
    """

    name: str
    rope: tuple[tuple[str, Any], ...] = ()
    lab: tuple[tuple[str, Any], ...] = ()
    sim: tuple[tuple[str, Any], ...] = ()
    variation: tuple[tuple[str, Any], ...] = ()
    table: str = "lab"


ELASTIC = "assets/ropes_elastic.toml"
"""The purely elastic rope table the lab used before the validation suite; the ``elastic
table`` row starts from it, every other row from the lab's table."""

_VARIATION_OFF = (
    ("servo_gain_rel", 0.0),
    ("start_delay_max_s", 0.0),
    ("rest_start", False),
    ("tempo_rel", 0.0),
)


def _variation_alone(keep: str | None) -> tuple[tuple[str, Any], ...]:
    """Every part of the trial-to-trial variation off except ``keep`` (None: all off)."""
    return tuple((k, v) for k, v in _VARIATION_OFF if k != keep)


CANDIDATES: dict[str, Candidate] = {
    c.name: c
    for c in (
        Candidate("lab"),
        # the cotton's unmeasured values across their brackets (assets/ropes.toml)
        Candidate("E 2.25e4 Pa (yarn, per tex)", rope=(("bend_modulus", 2.25e4),)),
        Candidate("E 1e6 Pa (feasibility study)", rope=(("bend_modulus", 1.0e6),)),
        Candidate("HB/B 0 (elastic)", rope=(("bend_hysteresis", 0.0),)),
        Candidate("HB/B 23 1/m", rope=(("bend_hysteresis", 23.0),)),
        Candidate("friction 0.3", rope=(("friction", 0.3),)),
        Candidate("friction 0.6", rope=(("friction", 0.6),)),
        # MuJoCo's friction settings
        Candidate("impratio 1", sim=(("impratio", 1.0),)),
        Candidate("pyramidal cone", sim=(("cone", "pyramidal"),)),
        # switches of the lab
        Candidate("condim 4", rope=(("condim", 4),)),
        Candidate("C_D 1.2", rope=(("cd", 1.2),)),
        # the purely elastic table the lab used before (elastic cotton, impratio 1)
        Candidate("elastic table", table="elastic"),
        # the lab's trial-to-trial variation, one part at a time
        Candidate("no variation", variation=_variation_alone(None)),
        Candidate("servo gains alone", variation=_variation_alone("servo_gain_rel")),
        Candidate("start delay alone", variation=_variation_alone("start_delay_max_s")),
        Candidate("rest start alone", variation=_variation_alone("rest_start")),
    )
}
"""The rows, by name: the lab's model, each unmeasured value at an end of its bracket, a
MuJoCo setting, two switches, the elastic table the lab used before, and the lab's
trial-to-trial variation without any part, then with each part alone (at its default)."""


def _labs(candidate: Candidate, rope_id: int, sway_deg: float):
    """The arm's :class:`LabParams` and the hand's :class:`HandParams` of one row."""
    from flyknot.constants import ROPE_TABLE
    from flyknot.demo import Demonstration
    from flyknot_sim.bend_friction import BendFrictionParams
    from flyknot_sim.hand_replay import hand_from_demo
    from flyknot_sim.lab import LabParams, VariationParams
    from flyknot_sim.rope_table import load_rope_table, load_sim_settings

    path = ROPE_TABLE if candidate.table == "lab" else DEMOS.parents[1] / ELASTIC
    rope = replace(load_rope_table(path)[rope_id], **dict(candidate.rope))
    lab_kw: dict[str, Any] = {}
    for key, value in candidate.lab:
        lab_kw[key] = BendFrictionParams(moment=value) if key == "bend_friction" else value
    lab_kw["settings"] = replace(load_sim_settings(path), **dict(candidate.sim))
    variation = {"sway_deg": sway_deg, **dict(candidate.variation)}
    arm_fields = {f.name for f in fields(VariationParams)}
    arm_variation = VariationParams(**{k: v for k, v in variation.items() if k in arm_fields})
    arm = LabParams(rope=rope, variation=arm_variation, **lab_kw)
    swipe = Demonstration.load(DEMOS / "swipe.npz")
    hand = hand_from_demo(swipe, rope_id, vary=True)
    hand = replace(hand, rope=rope, variation=replace(hand.variation, **variation), **lab_kw)
    return arm, hand


SETTLE_KINDS = ("rest", "contact_free", "knot_set", "cap")
"""How a trial's settle ended (:class:`flyknot.rest.SettleOutcome`)."""


def _settle_kind(settle: dict | None) -> str:
    """``rest``, ``contact_free``, ``knot_set`` or ``cap``: how the verdict was reached."""
    if settle and settle.get("settled"):
        return "rest"
    if settle and settle.get("contact_free"):
        return "contact_free"
    if settle and settle.get("knot_set"):
        return "knot_set"
    return "cap"


def _robot_trials(arm, n: int, demo_path: Path = ROBOT_DEMO) -> list[dict[str, Any]]:
    """The robot command's trials ``0 .. n - 1`` in the arm's lab, diagnosed (the command
    stored in the robot demonstration ``demo_path``)."""
    from flyknot.demo import Demonstration
    from flyknot_app.anatomy.diagnosis import diagnose
    from flyknot_sim.lab import SimLab
    from learner.bezier import BezierCommand

    demo = Demonstration.load(demo_path)
    meta = demo.metadata
    command = BezierCommand(
        np.asarray(meta["command_knots"], dtype=float), float(meta["command_T"])
    ).joint_command()
    lab = SimLab(arm)
    rows = []
    for _ in range(n):
        t0 = time.perf_counter()
        rec = lab.run(command)
        wall = time.perf_counter() - t0
        d = diagnose(rec, t_c=demo.t_c)
        rows.append(
            {
                "label": d.label,
                "settle": _settle_kind(rec.metadata.get("settle")),
                "sim_s": float(rec.metadata["sim_duration_s"]),
                "wall_s": wall,
            }
        )
    return rows


def _hand_trials(hand, n: int, seed: int) -> list[dict[str, Any]]:
    """Swipe's replays ``0 .. n - 1`` in the hand lab, diagnosed."""
    from flyknot.demo import Demonstration
    from flyknot_app.anatomy.diagnosis import diagnose
    from flyknot_app.anatomy.trials import load_replay
    from flyknot_sim.hand import HandLab
    from flyknot_sim.hand_replay import motion_from_demo, save_replay

    swipe = Demonstration.load(DEMOS / "swipe.npz")
    motion = motion_from_demo(swipe)
    lab = HandLab(hand)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(n):
            t0 = time.perf_counter()
            trial = lab.run(motion, np.random.default_rng([seed, i]))
            wall = time.perf_counter() - t0
            path = save_replay(
                Path(tmp) / f"replay_{i:03d}.npz",
                trial,
                lab.rope,
                rope=swipe.rope,
                seed=seed,
                index=i,
                source="swipe",
            )
            d = diagnose(load_replay(path), t_c=swipe.t_c)
            rows.append(
                {
                    "label": d.label,
                    "settle": _settle_kind(dict(trial.settle) if trial.settle else None),
                    "sim_s": float(trial.t[-1]),
                    "wall_s": wall,
                }
            )
    return rows


def _measure(job: tuple[str, float, str, int, int, int, Path]) -> dict[str, Any]:
    """One (row, sway, demonstration) cell of the table, in a worker process."""
    name, sway, which, n, seed, rope_id, robot_demo = job
    arm, hand = _labs(CANDIDATES[name], rope_id, sway)
    trials = _robot_trials(arm, n, robot_demo) if which == "robot" else _hand_trials(hand, n, seed)
    return {"candidate": name, "sway_deg": sway, "demo": which, "trials": trials}


def _summary(trials: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Counts and means of one cell."""
    labels = Counter(t["label"] for t in trials)
    settle = Counter(t["settle"] for t in trials)
    sim = sum(t["sim_s"] for t in trials)
    return {
        "n": len(trials),
        "ties": labels.get("success", 0),
        "failures": {k: v for k, v in sorted(labels.items()) if k != "success"},
        "settle": {k: settle.get(k, 0) for k in SETTLE_KINDS},
        "sim_s_per_trial": sim / len(trials),
        "wall_per_sim_s": sum(t["wall_s"] for t in trials) / sim,
    }


def run_study(
    candidates: Sequence[str],
    sways: Sequence[float],
    *,
    n: int = 40,
    seed: int = 0,
    rope: int = 1,
    workers: int = 1,
    robot_demo: str | Path = ROBOT_DEMO,
    demos: Sequence[str] = DEMO_KINDS,
    on_cell: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Measure every (candidate, sway) row with the chosen demonstrations.

    Args:
        candidates: Names in :data:`CANDIDATES`.
        sways: Extra initial sways [deg] (0: the settled start alone).
        n: Trials per demonstration and row, >= 1.
        seed: Lab seed.
        rope: Rope id.
        workers: Worker processes, >= 1.
        robot_demo: The robot demonstration whose stored command the arm plays.
        demos: Which of :data:`DEMO_KINDS` to play (the other's summary is None): a new robot
            command is compared without playing Swipe again.
        on_cell: Called with each finished cell (for progress).

    Returns:
        One dict per row: ``candidate``, ``sway_deg``, ``robot`` and ``hand`` summaries.

    Raises:
        ConfigError: An unknown candidate or demonstration kind (valid ones listed), or a bad
            count or sway.
    """
    for c in candidates:
        if c not in CANDIDATES:
            raise ConfigError("candidate", f"unknown candidate {c!r}", sorted(CANDIDATES))
    for s in sways:
        check_nonnegative("sway_deg", s)
    check_int("n", n, 1)
    check_int("workers", workers, 1)
    for d in demos:
        if d not in DEMO_KINDS:
            raise ConfigError("demos", f"unknown demonstration kind {d!r}", DEMO_KINDS)
    if not demos:
        raise ConfigError("demos", "empty", DEMO_KINDS)
    if "robot" in demos and not Path(robot_demo).is_file():
        raise ConfigError("robot_demo", f"no file {str(robot_demo)!r}")
    jobs = [
        (c, float(s), w, n, seed, rope, Path(robot_demo))
        for c in candidates
        for s in sways
        for w in DEMO_KINDS
        if w in demos
    ]
    cells: dict[tuple[str, float, str], dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for cell in pool.map(_measure, jobs):
            cells[(cell["candidate"], cell["sway_deg"], cell["demo"])] = cell
            if on_cell is not None:
                on_cell(cell)
    return [
        {
            "candidate": c,
            "sway_deg": float(s),
            **{
                w: _summary(cells[(c, float(s), w)]["trials"]) if w in demos else None
                for w in DEMO_KINDS
            },
        }
        for c in candidates
        for s in sways
    ]


def _failures_text(f: dict[str, int]) -> str:
    """``3 not_through, 12 shaken_loose``; ``-`` when none."""
    return ", ".join(f"{v} {k}" for k, v in f.items()) or "-"


def _columns(summary: dict[str, Any] | None) -> dict[str, str]:
    """One demonstration's cells of a table line (``-`` for a demonstration not played)."""
    if summary is None:
        return dict.fromkeys(("ties", "failures", "settle", "sim", "wall"), "-")
    return {
        "ties": f"{summary['ties']}/{summary['n']}",
        "failures": _failures_text(summary["failures"]),
        "settle": "/".join(str(summary["settle"].get(k, 0)) for k in SETTLE_KINDS),
        "sim": f"{summary['sim_s_per_trial']:.1f}",
        "wall": f"{summary['wall_per_sim_s']:.2f}",
    }


def table_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The study as a markdown table (one line per row)."""
    head = (
        "| lab | start | robot ties | robot failures | hand ties | hand failures | "
        "at rest / contact-free / knot set / cap (robot; hand) | sim s per trial (robot; hand) | "
        "wall s per sim s (robot; hand) |\n|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        a, h = _columns(r["robot"]), _columns(r["hand"])
        start = "settled" if r["sway_deg"] == 0 else f"+{r['sway_deg']:g} deg sway"
        lines.append(
            f"| {r['candidate']} | {start} | {a['ties']} | {a['failures']} | {h['ties']} | "
            f"{h['failures']} | {a['settle']}; {h['settle']} | {a['sim']}; {h['sim']} | "
            f"{a['wall']}; {h['wall']} |"
        )
    return head + "\n".join(lines) + "\n"


def write_outputs(rows: Sequence[dict[str, Any]], out: str | Path) -> Path:
    """Write ``lab_study.json`` and ``lab_study.md`` into ``out``; returns the directory."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "lab_study.json").write_text(json.dumps(list(rows), indent=1))
    (out / "lab_study.md").write_text(table_markdown(rows))
    return out

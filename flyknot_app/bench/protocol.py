"""``flyknot bench protocol``: the paper's protocol at one seed, timed.

Every paper scenario (``scenarios/0*.toml``) runs as ``flyknot paper`` runs it: all their runs
on one pool of the given workers (:func:`flyknot_app.runner.run_scenarios`), into a temporary
directory; the initial guesses (one trajectory optimisation per demonstration and window,
cached by the runner) are made once before and timed apart. Per scenario: its runs' wall
seconds in the workers, when its report was written, trials played (learning trials and
repeats, read back from the records) and simulated seconds per trial; in total the wall time
and the peak resident memory of the largest worker process.

``--quick`` runs a fixed small subset (:data:`QUICK`) four times in the same process: in the
lab as it is; without the knot-set end of the settle
(:attr:`flyknot.rest.SettleParams.knot_set_s` off: a knotted rope runs to rest or the cap);
without the held-unknot end (:attr:`flyknot.rest.SettleParams.unknot_held_s` off: an
unknotted rope that touches itself runs to rest or the cap); and scenario by scenario, each
on its own pool (as ``flyknot run`` runs one). So the before/after ratios come from one run
on one machine state.
"""

from __future__ import annotations

import contextlib
import io
import json
import resource
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flyknot.errors import ConfigError
from flyknot_app.reports.paper import PAPER_SCENARIOS

BEFORE_LABS = ("no_knot_set", "no_unknot_held", "by_scenario")
"""The labs ``--quick`` compares with the lab as it is (module docstring)."""


@dataclass(frozen=True)
class QuickCase:
    """One scenario of the quick subset, cut down with ``--set`` overrides."""

    scenario: str
    overrides: dict

    @property
    def label(self) -> str:
        """The scenario's name, and its rope when the overrides pick one
        (``04-success-rate-rope5``): the case's directory and row."""
        rope = self.overrides.get("rope")
        return self.scenario if rope is None else f"{self.scenario}-rope{rope}"


QUICK = (
    QuickCase("01-tracking", {"max_runs": 1, "repeats": 7}),
    QuickCase("04-success-rate", {"max_runs": 1, "rope": 4, "repeats": 6}),
    QuickCase("04-success-rate", {"max_runs": 1, "rope": 5, "repeats": 8}),
)
"""Rope 1's initial command 8 times (ropes that end unknotted), rope 4 learned from the
robot demonstration (a knot at trial 2 at lab seed 0) with 6 repeats of its command (knots:
what the knot-set end of the settle shortens), and rope 5 learned and repeated 8 times (ropes
wrapped round the grip or hanging in a loop: what the held-unknot end shortens)."""


def _peak_rss_mb() -> dict[str, float]:
    """Peak resident set size [MB] of this process and of its largest finished child."""
    scale = 1.0 / 1024.0 if sys.platform != "darwin" else 1.0 / 1024.0**2  # KiB on Linux
    return {
        "main_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale,
        "largest_worker_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * scale,
    }


def _trial_stats(run_dir: Path) -> tuple[int, float]:
    """Trials recorded under a scenario's run directory and their simulated seconds."""
    n, sim = 0, 0.0
    for path in (run_dir / "runs").glob("*/*/*.json"):
        meta = json.loads(path.read_text()).get("metadata", {})
        if "sim_duration_s" in meta:
            n += 1
            sim += float(meta["sim_duration_s"])
    return n, sim


def _stats_row(name: str, runs: int, out: Path, run_s: float, done_s: float) -> dict[str, Any]:
    n, sim = _trial_stats(out)
    return {
        "scenario": name,
        "runs": runs,
        "trials": n,
        "run_s": run_s,
        "done_s": done_s,
        "sim_s_per_trial": sim / n if n else 0.0,
    }


def _run_lab(
    cases, root: Path, guesses: Path, workers: int, cell: dict | None, together: bool
) -> tuple[list[dict[str, Any]], float]:
    """Every case into ``root/<scenario>`` with the shared guess cache: on one pool
    (``together``) or each scenario on its own pool, one after the other. Per scenario: its
    runs' wall seconds in the workers and when it was done; and the whole wall time."""
    from flyknot_app.runner import run_scenario, run_scenarios
    from flyknot_app.scenario import load_scenario

    items = []
    for label, name, overrides in cases:
        where = root / label
        where.mkdir(parents=True)
        (where / "initial_guess").symlink_to(guesses, target_is_directory=True)
        items.append((load_scenario(name, dict(overrides), cell=cell), where))
    t0 = time.perf_counter()
    rows = []
    with contextlib.redirect_stdout(io.StringIO()):  # the runner's line per run
        if together:
            done = run_scenarios(items, workers=workers, progress=False)
            for (scen, where), d in zip(items, done, strict=True):
                rows.append(_stats_row(where.name, len(scen.runs), where, d.run_s, d.done_s))
        else:
            for scen, where in items:
                t1 = time.perf_counter()
                run_scenario(scen, where, workers=workers, progress=False)
                wall = time.perf_counter() - t1
                done_s = time.perf_counter() - t0
                rows.append(_stats_row(where.name, len(scen.runs), where, wall, done_s))
    return rows, time.perf_counter() - t0


def _make_guesses(cases, guesses: Path) -> float:
    """Every initial guess the cases need, into ``guesses``; wall seconds."""
    from flyknot_app.runner import make_initial_guesses
    from flyknot_app.scenario import load_scenario

    t0 = time.perf_counter()
    for _, name, overrides in cases:
        make_initial_guesses(load_scenario(name, dict(overrides)), guesses.parent)
    return time.perf_counter() - t0


def bench_protocol(
    workers: int = 2,
    quick: bool = False,
    progress: bool = True,
    cases: tuple[QuickCase, ...] | None = None,
    keep: str | Path | None = None,
) -> dict[str, Any]:
    """Time the paper's protocol (or the quick subset, before and after) at seed 0.

    ``cases``: the scenarios with their overrides (default: every paper scenario as it is, or
    :data:`QUICK` with ``quick``); ``keep``: a new directory that keeps every scenario's run
    directory (``LAB/SCENARIO``; default: a temporary one).
    """
    from tqdm import tqdm

    from flyknot.progress import bar_disable

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError("--workers", f"must be an integer >= 1, got {workers!r}")
    if cases is None:
        cases = QUICK if quick else tuple(QuickCase(name, {}) for name in PAPER_SCENARIOS)
    cases = [(c.label, c.scenario, c.overrides) for c in cases]
    # (cell, on one pool?): the cell as the scenario says, all scenarios on one pool
    labs: dict[str, tuple[dict | None, bool]] = {"now": (None, True)}
    if quick:
        labs["no_knot_set"] = ({"kind": "sim", "knot_set": False}, True)
        labs["no_unknot_held"] = ({"kind": "sim", "unknot_held": False}, True)
        labs["by_scenario"] = (None, False)
    out: dict[str, Any] = {"workers": workers, "quick": quick, "labs": {}}
    with tempfile.TemporaryDirectory() as scratch:
        tmp = scratch if keep is None else str(keep)
        if keep is not None and Path(keep).exists():
            raise ConfigError("--out", f"{str(keep)!r} exists already; give a new directory")
        guesses = Path(tmp) / "cache" / "initial_guess"
        guesses.mkdir(parents=True)
        out["initial_guess_s"] = _make_guesses(cases, guesses)
        for lab in tqdm(labs, desc="bench protocol", disable=bar_disable(progress)):
            cell, together = labs[lab]
            rows, wall = _run_lab(cases, Path(tmp) / lab, guesses, workers, cell, together)
            out["labs"][lab] = [*rows, _total(rows, wall)]
    out["memory"] = _peak_rss_mb()
    if quick:
        now = out["labs"]["now"][-1]["wall_s"]
        for lab in BEFORE_LABS:
            before = out["labs"][lab][-1]["wall_s"]
            out[f"{lab}_over_now"] = before / now if now else float("nan")
    return out


def _total(rows: list[dict[str, Any]], wall: float) -> dict[str, Any]:
    n = sum(r["trials"] for r in rows)
    sim = sum(r["sim_s_per_trial"] * r["trials"] for r in rows)
    return {
        "scenario": "total",
        "runs": sum(r["runs"] for r in rows),
        "trials": n,
        "run_s": sum(r["run_s"] for r in rows),
        "done_s": wall,
        "wall_s": wall,
        "sim_s_per_trial": sim / n if n else 0.0,
    }


def format_protocol(res: dict[str, Any]) -> str:
    """The benchmark as a text table."""
    lines = [
        f"workers {res['workers']}; initial guesses {res['initial_guess_s']:.1f} s (once, "
        "before the scenarios)",
        "run s: the scenario's runs' wall seconds in the workers (summed); done at: seconds "
        "from the lab's start until its report was written",
    ]
    head = f"{'lab':>14} {'scenario':>21} {'runs':>5} {'trials':>7} {'run s':>8} "
    head += f"{'done at s':>10} {'sim s/trial':>12}"
    lines.append(head)
    for lab, rows in res["labs"].items():
        for r in rows:
            lines.append(
                f"{lab:>14} {r['scenario']:>21} {r['runs']:>5} {r['trials']:>7} "
                f"{r['run_s']:>8.1f} {r['done_s']:>10.1f} {r['sim_s_per_trial']:>12.2f}"
            )
    mem = res["memory"]
    lines.append(
        f"peak RSS: main process {mem['main_mb']:.0f} MB, largest worker "
        f"{mem['largest_worker_mb']:.0f} MB"
    )
    for lab in BEFORE_LABS:
        if f"{lab}_over_now" in res:
            lines.append(f"{lab} / now, total wall time: {res[f'{lab}_over_now']:.2f}x")
    return "\n".join(lines)

"""``flyknot bench protocol``: the paper's protocol at one seed, timed scenario by scenario.

Every paper scenario (``scenarios/0*.toml``) runs as ``flyknot run`` runs it, on the given
workers, into a temporary directory; the initial guesses (one trajectory optimisation per
demonstration and window, cached by the runner) are made once before and timed apart. Per
scenario: wall time, trials played (learning trials and repeats, read back from the records),
simulated seconds per trial, and the peak resident memory of the largest worker process.

``--quick`` runs a fixed small subset (:data:`QUICK`) twice in the same process, once in the
lab as it is and once without the knot-set end of the settle
(:attr:`flyknot.rest.SettleParams.knot_set_s` off: a knotted rope runs to rest or the cap),
so a before/after ratio comes from one run on one machine state.
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
from flyknot_app.paper import PAPER_SCENARIOS


@dataclass(frozen=True)
class QuickCase:
    """One scenario of the quick subset, cut down with ``--set`` overrides."""

    scenario: str
    overrides: dict


QUICK = (
    QuickCase("01-tracking", {"max_runs": 1, "repeats": 7}),
    QuickCase("04-success-rate", {"max_runs": 1, "rope": 4, "repeats": 6}),
)
"""Rope 1's initial command 8 times (ropes that end unknotted), and rope 4 learned from the
robot demonstration (a knot at trial 2 at lab seed 0) with 6 repeats of its command (knots:
what the knot-set end of the settle shortens)."""


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


def _run_one(
    name: str, overrides: dict, out: Path, guesses: Path, workers: int, cell: dict | None
) -> dict[str, Any]:
    """Run one scenario into ``out`` with the shared guess cache; time it."""
    from flyknot_app.runner import run_scenario
    from flyknot_app.scenario import load_scenario

    scen = load_scenario(name, dict(overrides), cell=cell)
    out.mkdir(parents=True)
    (out / "initial_guess").symlink_to(guesses, target_is_directory=True)
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # the runner's line per run
        run_scenario(scen, out, workers=workers, overrides=overrides, progress=False)
    wall = time.perf_counter() - t0
    n, sim = _trial_stats(out)
    return {
        "scenario": name,
        "runs": len(scen.runs),
        "wall_s": wall,
        "trials": n,
        "sim_s_per_trial": sim / n if n else 0.0,
        "wall_s_per_trial": wall / n if n else 0.0,
    }


def _make_guesses(cases, guesses: Path) -> float:
    """Every initial guess the cases need, into ``guesses``; wall seconds."""
    from flyknot_app.runner import make_initial_guesses
    from flyknot_app.scenario import load_scenario

    t0 = time.perf_counter()
    for name, overrides in cases:
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
    cases = [(c.scenario, c.overrides) for c in cases]
    labs: dict[str, dict | None] = {"now": None}  # the cell as the scenario says
    if quick:
        labs["no_knot_set"] = {"kind": "sim", "knot_set": False}
    out: dict[str, Any] = {"workers": workers, "quick": quick, "labs": {}}
    with tempfile.TemporaryDirectory() as scratch:
        tmp = scratch if keep is None else str(keep)
        if keep is not None and Path(keep).exists():
            raise ConfigError("--out", f"{str(keep)!r} exists already; give a new directory")
        guesses = Path(tmp) / "cache" / "initial_guess"
        guesses.mkdir(parents=True)
        out["initial_guess_s"] = _make_guesses(cases, guesses)
        jobs = [(lab, name, ov) for lab in labs for name, ov in cases]
        for lab, name, ov in tqdm(jobs, desc="bench protocol", disable=bar_disable(progress)):
            row = _run_one(name, ov, Path(tmp) / lab / name, guesses, workers, labs[lab])
            out["labs"].setdefault(lab, []).append(row)
    for rows in out["labs"].values():
        rows.append(_total(rows))
    out["memory"] = _peak_rss_mb()
    if quick:
        now, before = out["labs"]["now"][-1], out["labs"]["no_knot_set"][-1]
        out["speedup"] = before["wall_s"] / now["wall_s"] if now["wall_s"] else float("nan")
    return out


def _total(rows: list[dict[str, Any]]) -> dict[str, Any]:
    n = sum(r["trials"] for r in rows)
    wall = sum(r["wall_s"] for r in rows)
    sim = sum(r["sim_s_per_trial"] * r["trials"] for r in rows)
    return {
        "scenario": "total",
        "runs": sum(r["runs"] for r in rows),
        "wall_s": wall,
        "trials": n,
        "sim_s_per_trial": sim / n if n else 0.0,
        "wall_s_per_trial": wall / n if n else 0.0,
    }


def format_protocol(res: dict[str, Any]) -> str:
    """The benchmark as a text table."""
    lines = [
        f"workers {res['workers']}; initial guesses {res['initial_guess_s']:.1f} s (once, "
        "before the scenarios)"
    ]
    head = f"{'lab':>12} {'scenario':>16} {'runs':>5} {'trials':>7} {'wall s':>8} "
    head += f"{'wall s/trial':>13} {'sim s/trial':>12}"
    lines.append(head)
    for lab, rows in res["labs"].items():
        for r in rows:
            lines.append(
                f"{lab:>12} {r['scenario']:>16} {r['runs']:>5} {r['trials']:>7} "
                f"{r['wall_s']:>8.1f} {r['wall_s_per_trial']:>13.2f} {r['sim_s_per_trial']:>12.2f}"
            )
    mem = res["memory"]
    lines.append(
        f"peak RSS: main process {mem['main_mb']:.0f} MB, largest worker "
        f"{mem['largest_worker_mb']:.0f} MB"
    )
    if "speedup" in res:
        lines.append(f"no_knot_set / now, total wall time: {res['speedup']:.2f}x")
    return "\n".join(lines)

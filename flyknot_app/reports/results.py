"""One dated results table from measured directories: ``flyknot results DIR ... [--out F]``.

Each directory is read for what it holds:

* a scenario run (``summary.json`` of ``flyknot run``): per run, the trials until the first
  knot in the hanging rope and, with repeats, the knots among them with a 95 % Wilson
  interval and the verdict classes of the rest;
* a baseline (``baseline.json`` of ``flyknot baseline``): the same per seed;
* anything else with trials (``flyknot demo replay --out``, ``flyknot trial --repeats``):
  the knots among its trials, with the interval and the classes.

Every count is a verdict of :mod:`flyknot.verdict` (stored with the trial, else judged from
its rope). The table carries the date, the commit and the command that wrote it, so it is
regenerated, never edited.
"""

from __future__ import annotations

import datetime as dt
import json
import subprocess
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from flyknot.constants import REPO_ROOT
from flyknot.errors import ConfigError
from flyknot.verdict import JUDGE_NAME, KNOT
from flyknot_app.judging import FAULT, rejudge_directory
from flyknot_app.reports.report import wilson_interval
from flyknot_app.reports.run_summary import ScenarioSummary


def _rate(classes: Sequence[str | None]) -> str:
    """``k/n (lo-hi %)`` knots among ``classes`` and the other classes counted."""
    n = len(classes)
    if n == 0:
        return "-"
    k = sum(c == KNOT for c in classes)
    lo, hi = wilson_interval(k, n)
    rest = Counter("not judged" if c is None else c for c in classes if c != KNOT)
    others = ", ".join(f"{name} {v}" for name, v in sorted(rest.items()))
    return f"{k}/{n} ({100 * lo:.0f}-{100 * hi:.0f} %)" + (f"; {others}" if others else "")


def _trials(trials_to_success: int | None, n_trials: int) -> str:
    return str(trials_to_success) if trials_to_success is not None else f"none in {n_trials}"


def _settings(directory: Path) -> str:
    """How a directory was made, as far as it says: ``--set`` overrides of a scenario run,
    a baseline's budget and repeats."""
    manifest = directory / "manifest.json"
    if manifest.is_file():
        over = json.loads(manifest.read_text()).get("overrides") or {}
        return " ".join(f"`{k}={v}`" for k, v in over.items()) or "-"
    base = directory / "baseline.json"
    if base.is_file():
        params = json.loads(base.read_text()).get("params") or {}
        return ", ".join(f"{k} {params[k]}" for k in ("budget", "repeats") if k in params)
    return "-"


def _row(what: str, label: str, rope: Any, seed: Any, settings: str, trials: str, reps) -> str:
    return f"| {what} | {label} | {rope} | {seed} | {settings} | {trials} | {_rate(reps)} |"


def _not_judged(directory: Path) -> ConfigError:
    return ConfigError(
        "DIR",
        f"{str(directory)!r} was run before trials carried verdicts; its counts are "
        "not verdicts (flyknot judge re-judges its trials)",
    )


def _scenario_rows(directory: Path, doc: dict[str, Any]) -> list[str]:
    """One row per run of a scenario's ``summary.json``."""
    what, settings = f"`{doc.get('scenario', directory.name)}`", _settings(directory)
    rows = []
    for r in ScenarioSummary.from_json(doc).runs:
        if r.judge != JUDGE_NAME:
            raise _not_judged(directory)
        trials = _trials(r.trials_to_success, len(r.costs))
        seed = "-" if r.seed is None else r.seed
        rows.append(_row(what, r.label, r.rope, seed, settings, trials, r.repeat_classes))
    return rows


def _baseline_rows(directory: Path, doc: dict[str, Any]) -> list[str]:
    """One row per search of a ``baseline.json``."""
    name = doc["runs"][0].get("name", "baseline") if doc["runs"] else "baseline"
    what, settings = f"baseline `{name}`", _settings(directory)
    rows = []
    for r in doc["runs"]:
        if r.get("judge") != JUDGE_NAME:
            raise _not_judged(directory)
        label = r.get("name") or f"seed {r.get('seed')}"
        trials = _trials(r.get("trials_to_success"), len(r.get("costs") or []))
        rope, seed = r.get("rope", doc.get("rope")), r.get("seed", "-")
        rows.append(_row(what, label, rope, seed, settings, trials, r.get("repeats") or []))
    return rows


def rows_of(directory: str | Path) -> list[str]:
    """The table rows of one measured directory (module docstring).

    Raises:
        ConfigError: The directory is missing or holds nothing measured.
    """
    d = Path(directory)
    if (d / "summary.json").is_file():
        return _scenario_rows(d, json.loads((d / "summary.json").read_text()))
    if (d / "baseline.json").is_file():
        return _baseline_rows(d, json.loads((d / "baseline.json").read_text()))
    trials = rejudge_directory(d, keep_stored=True)
    classes = [FAULT if t.fault else (t.new.klass if t.new else None) for t in trials]
    kind = "replays" if trials[0].kind == "replay" else "trials"
    return [f"| {kind} | `{d.name}` | - | - | - | - | {_rate(classes)} |"]


def git_commit() -> str:
    """The repository's short commit id, with ``-dirty`` when tracked files differ from it,
    or ``"unknown"`` outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "describe", "--always", "--dirty", "--abbrev=7"],
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out.stdout.strip()


def results_table(directories: Sequence[str | Path], command: str) -> str:
    """The markdown document: header (date, commit, command) and one table of every row."""
    if not directories:
        raise ConfigError("DIR", "give at least one measured directory")
    lines = [
        "# Results",
        "",
        f"Measured in the simulated lab; written {dt.date.today().isoformat()} at commit "
        f"{git_commit()} by `{command}`. A knot is a verdict `knot` of `flyknot.verdict` (an "
        "overhand knot in the hanging rope); intervals are 95 % Wilson.",
        "",
        "| what | run | rope | seed | settings | trials until the first knot | knots in the "
        "repeats or trials; other verdicts |",
        "|---|---|---|---|---|---|---|",
    ]
    for d in directories:
        lines += rows_of(d)
    return "\n".join(lines) + "\n"

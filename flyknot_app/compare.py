"""``flyknot compare RUN_DIR ...``: several runs side by side, in a table and figures.

Each RUN_DIR is what ``flyknot run`` wrote (its ``summary.json``) or what ``flyknot
baseline`` wrote (its ``baseline.json``). Per directory: how many of its runs tied the knot,
the trials until the knot (median and range, over the runs that tied), the knots in the
repeats pooled over its runs with a 95 % Wilson interval, and the learning curves (the cost
per trial of every run, and their median). Written into ``--out``: ``compare.md``,
``compare_costs.png``, ``compare_trials.png`` and (when any directory has repeats)
``compare_success.png``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

from flyknot.errors import ConfigError
from flyknot_app.report import wilson_interval


@dataclass(frozen=True)
class RunSet:
    """The runs of one directory, reduced to what a comparison needs.

    Attributes:
        label: Name in tables and legends (the directory's name).
        costs: Per run, the cost of each trial (NaN: unmeasured).
        trials_to_success: Per run, trials until the first knot, or None.
        repeats_tied: Trefoils in the repeats, pooled over the runs.
        repeats: Repeats, pooled over the runs.
    """

    label: str
    costs: tuple[tuple[float, ...], ...]
    trials_to_success: tuple[int | None, ...]
    repeats_tied: int
    repeats: int


def _tts(run: dict[str, Any]) -> int | None:
    if "trials_to_success" in run:
        return run["trials_to_success"]
    first = run.get("first_success_trial")  # run directories written before session 4
    return None if first is None else first + 1


def load_runset(directory: str | Path) -> RunSet:
    """Read a run directory (``summary.json``) or a baseline directory (``baseline.json``)."""
    d = Path(directory)
    if (d / "summary.json").is_file():
        runs = json.loads((d / "summary.json").read_text())["runs"]
    elif (d / "baseline.json").is_file():
        runs = json.loads((d / "baseline.json").read_text())["runs"]
    else:
        raise ConfigError("RUN_DIR", f"{str(d)!r} holds neither summary.json nor baseline.json")
    costs = tuple(tuple(np.nan if c is None else float(c) for c in r["costs"]) for r in runs)
    reps = [x for r in runs for x in (r.get("repeats") or [])]
    return RunSet(
        label=d.name,
        costs=costs,
        trials_to_success=tuple(_tts(r) for r in runs),
        repeats_tied=sum(x == "trefoil" for x in reps),
        repeats=len(reps),
    )


def table(sets: list[RunSet]) -> str:
    """The comparison as a markdown table."""
    lines = [
        "| runs | knot learned | trials until knot (median, range) | repeats tied (95 % CI) |",
        "|---|---|---|---|",
    ]
    for s in sets:
        tied = [n for n in s.trials_to_success if n is not None]
        tt = f"{np.median(tied):g} ({min(tied)}-{max(tied)})" if tied else "-"
        rep = "-"
        if s.repeats:
            lo, hi = wilson_interval(s.repeats_tied, s.repeats)
            rep = f"{s.repeats_tied}/{s.repeats} ({lo:.0%}-{hi:.0%})"
        n = len(s.trials_to_success)
        lines.append(f"| {s.label} | {len(tied)} of {n} | {tt} | {rep} |")
    return "\n".join(lines) + "\n"


def _plot_costs(sets: list[RunSet], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    for i, s in enumerate(sets):
        colour = f"C{i}"
        n = max(len(c) for c in s.costs)
        padded = np.full((len(s.costs), n), np.nan)
        for k, c in enumerate(s.costs):
            padded[k, : len(c)] = c
            ax.plot(np.arange(1, len(c) + 1), c, color=colour, alpha=0.25, lw=0.8)
        with np.errstate(all="ignore"):
            med = np.nanmedian(padded, axis=0) if np.isfinite(padded).any() else padded[0]
        ax.plot(np.arange(1, n + 1), med, color=colour, lw=2, marker=".", label=s.label)
    ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set(xlabel="trial", ylabel="critical-point cost (thin: runs, thick: median)")
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _plot_trials(sets: list[RunSet], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6, 3.8), constrained_layout=True)
    for i, s in enumerate(sets):
        for n in s.trials_to_success:
            y = n if n is not None else max(len(c) for c in s.costs) + 1
            ax.plot(
                i + np.random.default_rng(len(ax.lines)).uniform(-0.12, 0.12),
                y,
                "o",
                color=f"C{i}",
                mfc="none" if n is None else f"C{i}",
            )
    ax.set_xticks(range(len(sets)), [s.label for s in sets], rotation=30, ha="right")
    ax.set(ylabel="trials until the first knot (open: none)")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _plot_success(sets: list[RunSet], path: Path) -> Path | None:
    rows = [s for s in sets if s.repeats]
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(6, 3.8), constrained_layout=True)
    for i, s in enumerate(rows):
        p = s.repeats_tied / s.repeats
        lo, hi = wilson_interval(s.repeats_tied, s.repeats)
        ax.bar(i, p, color=f"C{sets.index(s)}")
        ax.errorbar(i, p, yerr=[[p - lo], [hi - p]], color="k", capsize=4)
    ax.set_xticks(range(len(rows)), [s.label for s in rows], rotation=30, ha="right")
    ax.set(ylabel="knots in the repeats (95 % Wilson)", ylim=(0, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def compare(directories: list[str | Path], out: str | Path) -> Path:
    """Write ``compare.md`` and the figures for ``directories`` into ``out``; its path."""
    if not directories:
        raise ConfigError("RUN_DIR", "give at least one run directory")
    sets = [load_runset(d) for d in directories]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = [
        _plot_costs(sets, out / "compare_costs.png"),
        _plot_trials(sets, out / "compare_trials.png"),
    ]
    success = _plot_success(sets, out / "compare_success.png")
    if success is not None:
        figs.append(success)
    text = (
        "# Comparison\n\n" + table(sets) + "\n" + "".join(f"![{f.stem}]({f.name})\n" for f in figs)
    )
    path = out / "compare.md"
    path.write_text(text)
    return path

"""``flyknot compare RUN_DIR ...``: several runs side by side, in tables and figures.

Each RUN_DIR is what ``flyknot run`` wrote (its ``summary.json``: ILC) or what ``flyknot
baseline`` wrote (its ``baseline.json``: random search, CMA-ES or PPO). Per directory: how
many of its runs tied the knot, the trials until the knot (median and range, over the runs
that tied), the knots in the repeats pooled over its runs with a 95 % Wilson interval (the
success rate after the budget), and the learning curves (the cost per trial of every run,
and their median).

ILC beside each baseline, run by run: a table of the trials until the first knot per (rope,
seed) with each directory in a column (a run without a knot shows ``>n``, its n trials), the
mean trials until the first knot, and the ratio of each baseline's mean to ILC's over the
(rope, seed) pairs both have (a run without a knot counts as n + 1 trials, so a mean with
one is a lower bound, marked >=; a ratio is then a bound too, or undetermined when both
are). The seed of an ILC run is its ``seed`` field or its name's ``-seedS`` suffix
(``flyknot run --seeds``). Written into ``--out``: ``compare.md``, ``compare_costs.png``,
``compare_trials.png``, ``compare_seeds.png`` and (when any directory has repeats)
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
from flyknot.verdict import KNOT
from flyknot_app.reports.report import wilson_interval
from flyknot_app.reports.run_summary import ScenarioSummary


@dataclass(frozen=True)
class RunSet:
    """The runs of one directory, reduced to what a comparison needs.

    Attributes:
        label: Name in tables and legends (the directory's name).
        costs: Per run, the cost of each trial (NaN: unmeasured).
        trials_to_success: Per run, trials until the first knot, or None.
        repeats_tied: Trefoils in the repeats, pooled over the runs.
        repeats: Repeats, pooled over the runs.
        kind: ``"ilc"`` (a run directory) or the baseline's name.
        keys: Per run, its (rope, seed); the seed None when unknown.
    """

    label: str
    costs: tuple[tuple[float, ...], ...]
    trials_to_success: tuple[int | None, ...]
    repeats_tied: int
    repeats: int
    kind: str = "ilc"
    keys: tuple[tuple[Any, int | None], ...] = ()

    @property
    def trials(self) -> tuple[int, ...]:
        """Per run, the trials until the first knot, or its trials + 1 when it has none."""
        return tuple(
            len(c) + 1 if n is None else n
            for n, c in zip(self.trials_to_success, self.costs, strict=True)
        )


def _ilc_rows(doc: dict[str, Any]) -> list[tuple[Any, ...]]:
    """(costs, trials to the first knot, repeats, (rope, seed)) of a scenario's runs."""
    runs = ScenarioSummary.from_json(doc).runs
    return [(r.costs, r.trials_to_success, r.repeat_classes, (r.rope, r.seed)) for r in runs]


def _baseline_rows(doc: dict[str, Any]) -> list[tuple[Any, ...]]:
    """(costs, trials to the first knot, repeats, (rope, seed)) of a baseline's searches."""
    return [
        (
            r["costs"],
            r.get("trials_to_success"),
            r.get("repeats") or [],
            (r.get("rope", doc.get("rope")), r.get("seed")),
        )
        for r in doc["runs"]
    ]


def load_runset(directory: str | Path) -> RunSet:
    """Read a run directory (``summary.json``) or a baseline directory (``baseline.json``)."""
    d = Path(directory)
    if (d / "summary.json").is_file():
        rows, kind = _ilc_rows(json.loads((d / "summary.json").read_text())), "ilc"
    elif (d / "baseline.json").is_file():
        doc = json.loads((d / "baseline.json").read_text())
        rows = _baseline_rows(doc)
        kind = doc["runs"][0].get("name", "baseline") if doc["runs"] else "baseline"
    else:
        raise ConfigError("RUN_DIR", f"{str(d)!r} holds neither summary.json nor baseline.json")
    reps = [x for row in rows for x in row[2]]
    return RunSet(
        label=d.name,
        costs=tuple(tuple(np.nan if c is None else float(c) for c in row[0]) for row in rows),
        trials_to_success=tuple(row[1] for row in rows),
        repeats_tied=sum(x == KNOT for x in reps),
        repeats=len(reps),
        kind=kind,
        keys=tuple(row[3] for row in rows),
    )


def mean_trials(runs: RunSet, keys=None) -> tuple[float, bool]:
    """Mean trials until the first knot over the runs (of ``keys`` only, if given), and whether
    it is a lower bound (a run without a knot counted as its trials + 1)."""
    rows = [
        (t, n is None)
        for k, t, n in zip(runs.keys, runs.trials, runs.trials_to_success, strict=True)
        if keys is None or k in keys
    ]
    if not rows:
        return float("nan"), False
    return float(np.mean([t for t, _ in rows])), any(c for _, c in rows)


def _mean_text(mean: float, bound: bool) -> str:
    return "-" if not np.isfinite(mean) else f"{'>=' if bound else ''}{mean:.3g}"


def ratios(sets: list[RunSet]) -> list[tuple[RunSet, RunSet, float, str, int]]:
    """Each baseline against the first ILC directory: (baseline, ilc, mean trials of the
    baseline / mean trials of ILC over the (rope, seed) pairs both have, its kind: ``"="``,
    ``">="`` (a lower bound), ``"<="`` or ``"?"`` (undetermined), pairs compared)."""
    ilc = next((s for s in sets if s.kind == "ilc"), None)
    out = []
    if ilc is None:
        return out
    for s in sets:
        if s.kind == "ilc":
            continue
        common = set(s.keys) & set(ilc.keys)
        keys = common or None
        m_b, b_bound = mean_trials(s, keys)
        m_i, i_bound = mean_trials(ilc, keys)
        kind = {(False, False): "=", (True, False): ">=", (False, True): "<="}.get(
            (b_bound, i_bound), "?"
        )
        n = len(common) if common else len(s.keys)
        out.append((s, ilc, m_b / m_i, kind, n))
    return out


def _key_text(key: tuple[Any, int | None]) -> str:
    rope, seed = key
    return f"rope {rope}, seed {'?' if seed is None else seed}"


def seed_table(sets: list[RunSet]) -> str:
    """Trials until the first knot per (rope, seed), a column per directory, the means and
    each baseline's ratio to ILC (module docstring), as markdown."""
    keys = sorted({k for s in sets for k in s.keys}, key=lambda k: (str(k[0]), k[1] or -1))
    lines = [
        "| rope, seed | " + " | ".join(s.label for s in sets) + " |",
        "|---|" + "---|" * len(sets),
    ]
    for key in keys:
        cells = []
        for s in sets:
            hits = [
                str(n) if n is not None else f">{len(c)}"
                for k, n, c in zip(s.keys, s.trials_to_success, s.costs, strict=True)
                if k == key
            ]
            cells.append(", ".join(hits) or "-")
        lines.append(f"| {_key_text(key)} | " + " | ".join(cells) + " |")
    means = [_mean_text(*mean_trials(s)) for s in sets]
    lines.append("| mean trials until knot | " + " | ".join(means) + " |")
    text = "\n".join(lines) + "\n"
    for b, ilc, r, kind, n in ratios(sets):
        rel = "" if kind == "=" else {">=": ">= ", "<=": "<= ", "?": "~ (undetermined) "}[kind]
        text += (
            f"\nMean trials until the first knot, {b.label} / {ilc.label}: {rel}{r:.3g}x "
            f"(over {n} (rope, seed) pairs)\n"
        )
    return text


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


def _plot_seeds(sets: list[RunSet], path: Path) -> Path:
    """Trials until the first knot per (rope, seed), a marker per directory (open: no knot,
    drawn at its trials + 1), the ratios to ILC in the title."""
    keys = sorted({k for s in sets for k in s.keys}, key=lambda k: (str(k[0]), k[1] or -1))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.5 * len(keys) + 3), 4.0), constrained_layout=True)
    width = 0.6 / max(1, len(sets))
    markers = "os^DvP*X"
    for i, s in enumerate(sets):
        x = (
            np.array([keys.index(k) for k in s.keys], dtype=float)
            + (i - (len(sets) - 1) / 2) * width
        )
        tied = np.array([n is not None for n in s.trials_to_success], dtype=bool)
        y = np.array(s.trials, dtype=float)
        style = {"color": f"C{i}", "marker": markers[i % len(markers)], "ls": "none"}
        ax.plot(x[tied], y[tied], label=s.label, **style)
        ax.plot(x[~tied], y[~tied], mfc="none", **style)
    ax.set_xticks(range(len(keys)), [_key_text(k) for k in keys], rotation=30, ha="right")
    ax.set(ylabel="trials until the first knot (open: none, at n + 1)")
    ax.set_ylim(bottom=0)
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    title = "; ".join(
        f"{b.label}/{ilc.label} {'' if kind == '=' else kind}{r:.2g}x"
        for b, ilc, r, kind, _ in ratios(sets)
    )
    if title:
        ax.set_title("mean trials, " + title, fontsize=9)
    ax.legend(fontsize=7)
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
        _plot_seeds(sets, out / "compare_seeds.png"),
    ]
    success = _plot_success(sets, out / "compare_success.png")
    if success is not None:
        figs.append(success)
    text = (
        "# Comparison\n\n"
        + table(sets)
        + "\n## Trials until the first knot, run by run\n\n"
        + seed_table(sets)
        + "\n"
        + "".join(f"![{f.stem}]({f.name})\n" for f in figs)
    )
    path = out / "compare.md"
    path.write_text(text)
    return path

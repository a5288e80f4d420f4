"""The failure anatomy of a set of trials (:mod:`flyknot_app.anatomy.diagnosis`): tables, figures,
reports.

:func:`explain` diagnoses trials in memory, :func:`explain_directory` every trial under a run or
replay directory (:func:`flyknot_app.anatomy.trials.find_trials`); :func:`format_table`,
:func:`plot_anatomy`, :func:`markdown_section` and :func:`report_section` show the result.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, FlyknotError, check_choice, check_int, check_nonnegative
from flyknot.record import TrialRecord, atomic_write_text
from flyknot_app.anatomy.diagnosis import (
    COLOURS,
    DESCRIPTIONS,
    LABELS,
    MARKERS_LOST,
    PERSIST_S,
    AnatomyParams,
    Diagnosis,
    diagnose,
)
from flyknot_app.anatomy.trials import (
    TrialEvidence,
    TrialFile,
    find_trials,
    load_evidence,
    require_trials,
)


@dataclass(frozen=True)
class Anatomy:
    """The diagnoses of every trial of a directory (or any set of trials).

    Attributes:
        source: What was explained (a directory path, or free text).
        diagnoses: One per trial, in file order.
        t_c_sources: How t_c was found, one line per distinct source (for the table).
    """

    source: str
    diagnoses: tuple[Diagnosis, ...]
    t_c_sources: tuple[str, ...] = ()

    def groups(self) -> tuple[str, ...]:
        """Distinct groups, in order of first appearance."""
        return tuple(dict.fromkeys(d.group for d in self.diagnoses))

    def counts(self, group: str | None = None) -> dict[str, int]:
        """Trials per label (every label, in :data:`LABELS` order), of one group or all.

        Raises:
            ConfigError: ``group`` is not one of :meth:`groups`.
        """
        if group is not None:
            check_choice("group", group, self.groups())
        out = dict.fromkeys(LABELS, 0)
        for d in self.diagnoses:
            if group is None or d.group == group:
                out[d.label] += 1
        return out

    def as_dict(self) -> dict[str, Any]:
        """Plain data (JSON-ready): counts overall and per group, and every diagnosis."""
        return {
            "source": self.source,
            "t_c_sources": list(self.t_c_sources),
            "counts": self.counts(),
            "groups": {g: self.counts(g) for g in self.groups()},
            "trials": [d.as_dict() for d in self.diagnoses],
        }


def explain(
    trials: Iterable[TrialRecord | TrialEvidence],
    *,
    t_c: float | None = None,
    params: AnatomyParams | None = None,
    source: str = "trials",
) -> Anatomy:
    """Diagnose a set of trials in memory (all checked against one ``t_c``).

    Args:
        trials: Records (with truth for the full anatomy) or evidence.
        t_c: Critical time [s], or None (no ``markers_lost`` check).
        params: Thresholds.
        source: Name of the set in tables.

    Returns:
        The :class:`Anatomy`; trial names are ``trial_000``, ... unless evidence names them.
    """
    out = []
    for i, trial in enumerate(trials):
        name = trial.name if isinstance(trial, TrialEvidence) else f"trial_{i:03d}"
        out.append(diagnose(trial, t_c=t_c, params=params, name=name))
    return Anatomy(source, tuple(out))


def explain_directory(
    directory: str | Path,
    *,
    t_c: float | None = None,
    params: AnatomyParams | None = None,
    progress: Callable[[Iterable[TrialFile]], Iterable[TrialFile]] | None = None,
    workers: int = 1,
) -> Anatomy:
    """Diagnose every trial under a run or replay directory (:func:`find_trials`).

    Groups: the run of each record (``rope1``, ``rope1/repeats``, ...); trials directly in
    ``directory`` are grouped by rope (``rope 1``).

    Args:
        directory: The directory.
        t_c: Critical time [s] for every trial; None: each run's ``t_c`` (``result.json`` or
            ``summary.json``) or each replay's demonstration t_c, where found.
        params: Thresholds.
        progress: Optional wrapper of the file iteration (e.g. ``tqdm``).
        workers: Worker processes diagnosing the trials (>= 1); the result does not depend
            on it (each trial is diagnosed alone, in the files' order).

    Returns:
        The :class:`Anatomy`.

    Raises:
        ConfigError: ``directory`` does not exist, is not a directory, or holds no trials;
            ``t_c`` is not a finite number >= 0.
        RecordError: A trial file under it is malformed (the message names the file).
    """
    if t_c is not None:
        check_nonnegative("t_c", t_c)
    check_int("workers", workers, 1)
    files = require_trials(directory)
    jobs = [(f, t_c, params, Path(directory).name) for f in files]
    if workers > 1 and len(files) > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=min(workers, len(files))) as pool:
            done = pool.map(_diagnose_file, jobs, chunksize=max(1, len(jobs) // (8 * workers)))
            diagnoses = [
                d for _, d in zip(progress(files) if progress else files, done, strict=True)
            ]
    else:
        diagnoses = [
            _diagnose_file(job)
            for job, _ in zip(jobs, progress(files) if progress else files, strict=True)
        ]
    if t_c is not None:
        sources = (f"t_c {t_c:.3f} s (given)",)
    else:
        per_group: dict[str, set[float | None]] = {}
        for f, d in zip(files, diagnoses, strict=True):
            per_group.setdefault(d.group, set()).add(f.t_c)
        sources = tuple(
            f"{g}: "
            + ", ".join("none found" if v is None else f"{v:.3f} s" for v in _sorted_t_c(vals))
            for g, vals in per_group.items()
        )
    return Anatomy(str(directory), tuple(diagnoses), sources)


def _diagnose_file(job: tuple[TrialFile, float | None, AnatomyParams | None, str]) -> Diagnosis:
    """Diagnose one found trial (a module-level function: worker processes run it); a
    diagnosis stored beside the record for the same t_c and thresholds is read instead
    (:func:`store_diagnoses`)."""
    f, t_c, params, dir_name = job
    t_c = f.t_c if t_c is None else t_c
    cached = _cached(f, t_c, params)
    if cached is not None and (f.group or cached.group):
        return replace(cached, name=f.name, group=f.group or cached.group)
    ev = load_evidence(f)
    group = f.group
    if not group:
        rope = ev.metadata.get("rope")
        group = f"rope {rope}" if rope is not None else dir_name
    return diagnose(ev, t_c=t_c, params=params, group=group)


def _cache_path(f: TrialFile) -> Path:
    return f.path.with_name(f.path.name.rsplit(".", 1)[0] + ".diagnosis")


def _cache_key(t_c: float | None, params: AnatomyParams | None) -> dict[str, Any]:
    return {"t_c": t_c, "params": asdict(params or AnatomyParams())}


def _cached(f: TrialFile, t_c: float | None, params: AnatomyParams | None) -> Diagnosis | None:
    """The stored diagnosis of ``f`` if it was made for this t_c and these thresholds after
    the record was last written, else None."""
    path = _cache_path(f)
    try:
        if f.kind != "record" or path.stat().st_mtime < f.path.stat().st_mtime:
            return None
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if data.get("key") != json.loads(json.dumps(_cache_key(t_c, params))):
        return None
    d = dict(data["diagnosis"])
    d["trefoil_runs"] = tuple(tuple(r) for r in d.get("trefoil_runs", ()))
    try:
        return Diagnosis(**d)
    except (TypeError, FlyknotError):
        return None


def store_diagnoses(directory: str | Path, t_c: float | None = None) -> int:
    """Diagnose every trial record under ``directory`` and store each diagnosis beside its
    record (``<stem>.diagnosis``: JSON, without a ``.json`` suffix so that no record glob
    sees it), so that a report diagnosing the same trials later reads them: a run's worker
    calls this when the run ends, in parallel with the other runs.

    Returns:
        The number of diagnoses stored.
    """
    n = 0
    for f in find_trials(directory):
        if f.kind != "record":
            continue
        t = f.t_c if t_c is None else t_c
        d = _diagnose_file((f, t_c, None, Path(directory).name))
        payload = {"key": _cache_key(t, None), "diagnosis": d.as_dict()}
        atomic_write_text(_cache_path(f), json.dumps(payload))
        n += 1
    return n


def _sorted_t_c(values: Iterable[float | None]) -> list[float | None]:
    """Values sorted with None last (for listing the t_c of a group)."""
    vals = list(values)
    return sorted(v for v in vals if v is not None) + [None] * sum(v is None for v in vals)


# --- output ----------------------------------------------------------------------------------


def _share(k: int, n: int) -> str:
    return f"{100.0 * k / n:.0f} %" if n else "-"


def _used_labels(anatomy: Anatomy) -> list[str]:
    total = anatomy.counts()
    return [lab for lab in LABELS if total[lab]]


def format_table(anatomy: Anatomy, *, trials: bool = False) -> str:
    """Plain-text table: label -> count and share, per group when there are several.

    Args:
        anatomy: What to print.
        trials: Also list every trial with its label and reason.

    Returns:
        The text (no trailing newline).
    """
    total = anatomy.counts()
    n = len(anatomy.diagnoses)
    lines = [f"failure anatomy of {anatomy.source}: {n} trial{'s' if n != 1 else ''}"]
    lines += [f"  t_c: {s}" for s in anatomy.t_c_sources]
    lines.append("")
    width = max(len(lab) for lab in LABELS)
    lines.append(f"{'class':<{width}}  {'meaning':<42}  {'count':>5}  {'share':>5}")
    for lab in LABELS:
        if total[lab]:
            lines.append(
                f"{lab:<{width}}  {DESCRIPTIONS[lab]:<42}  {total[lab]:>5}  "
                f"{_share(total[lab], n):>5}"
            )
    lines.append(f"{'total':<{width}}  {'':<42}  {n:>5}  {_share(n, n):>5}")
    lost = [d for d in anatomy.diagnoses if d.label == MARKERS_LOST]
    if lost:
        then = {}
        for d in lost:
            then[d.outcome] = then.get(d.outcome, 0) + 1
        lines.append(
            f"  {MARKERS_LOST}, by outcome: "
            + ", ".join(f"{lab} {then[lab]}" for lab in LABELS if lab in then)
        )
    groups = anatomy.groups()
    if len(groups) > 1:
        used = _used_labels(anatomy)
        gw = max(len("group"), *(len(g) for g in groups))
        cw = [max(len(lab), 8) for lab in used]
        lines += ["", "per group (count, share):"]
        lines.append(
            f"{'group':<{gw}}  {'n':>4}  "
            + "  ".join(f"{lab:>{w}}" for lab, w in zip(used, cw, strict=True))
        )
        for g in groups:
            c = anatomy.counts(g)
            m = sum(c.values())
            cells = [f"{c[lab]} {_share(c[lab], m)}" if c[lab] else "-" for lab in used]
            lines.append(
                f"{g:<{gw}}  {m:>4}  "
                + "  ".join(f"{x:>{w}}" for x, w in zip(cells, cw, strict=True))
            )
    if trials:
        nw = max(len(d.name) for d in anatomy.diagnoses)
        lines += ["", "trials:"]
        lines += [f"{d.name:<{nw}}  {d.label:<{width}}  {d.reason}" for d in anatomy.diagnoses]
    return "\n".join(lines)


def plot_anatomy(anatomy: Anatomy, path: str | Path, title: str | None = None) -> Path:
    """Stacked bar chart of the labels' shares: one bar per group (and "all" if several).

    Args:
        anatomy: What to draw.
        path: PNG to write (its directory is created).
        title: Figure title (default: the anatomy's source).

    Returns:
        ``path``.

    Raises:
        ConfigError: The anatomy holds no trials.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not anatomy.diagnoses:
        raise ConfigError("anatomy", "holds no trials to plot")
    groups = list(anatomy.groups())
    bars = [(g, anatomy.counts(g)) for g in groups]
    if len(groups) > 1:
        bars.append(("all", anatomy.counts()))
    used = _used_labels(anatomy)
    fig, ax = plt.subplots(figsize=(0.9 * len(bars) + 5.0, 4.2), constrained_layout=True)
    x = np.arange(len(bars))
    bottom = np.zeros(len(bars))
    for lab in used:
        k = np.array([c[lab] for _, c in bars], dtype=float)
        n = np.array([sum(c.values()) for _, c in bars], dtype=float)
        share = k / n
        ax.bar(
            x,
            share,
            0.7,
            bottom=bottom,
            color=COLOURS[lab],
            edgecolor="k",
            linewidth=0.5,
            label=f"{lab}: {DESCRIPTIONS[lab]}",
        )
        r, g, b_ = matplotlib.colors.to_rgb(COLOURS[lab])
        ink = "w" if 0.299 * r + 0.587 * g + 0.114 * b_ < 0.45 else "k"
        for xi, b, s, ki in zip(x, bottom, share, k, strict=True):
            if s >= 0.06:
                ax.text(
                    xi, b + s / 2, f"{int(ki)}", ha="center", va="center", fontsize=7, color=ink
                )
        bottom += share
    for xi, (_, c) in zip(x, bars, strict=True):
        ax.text(xi, 1.01, f"n={sum(c.values())}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [g for g, _ in bars], rotation=30 if len(bars) > 4 else 0, ha="right")
    ax.set(
        xlim=(-0.75, len(bars) - 0.25),
        ylim=(0, 1.08),
        ylabel="share of trials",
        title=title or f"failure anatomy: {anatomy.source}",
    )
    handles, labels = ax.get_legend_handles_labels()  # top of the stack first
    ax.legend(
        handles[::-1],
        labels[::-1],
        fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        frameon=False,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def markdown_section(anatomy: Anatomy, figure: str | None = None) -> list[str]:
    """Lines of a report section: label table, per-group table if several, the figure.

    Args:
        anatomy: What to report.
        figure: File name of the figure to link (relative to the report), or None.

    Returns:
        Markdown lines, starting with the section heading.
    """
    total = anatomy.counts()
    n = len(anatomy.diagnoses)
    lines = ["## Failure anatomy", ""]
    lines.append(
        f"Why each of the {n} trials ended as it did "
        f"(`flyknot_app.anatomy.diagnosis`; a trefoil lasting "
        f"{PERSIST_S:g} s or more was tied, a shorter one slipped out)."
    )
    lines += ["", "| class | meaning | count | share |", "|---|---|---|---|"]
    for lab in LABELS:
        if total[lab]:
            lines.append(
                f"| {lab} | {DESCRIPTIONS[lab]} | {total[lab]} | {_share(total[lab], n)} |"
            )
    groups = anatomy.groups()
    if len(groups) > 1:
        used = _used_labels(anatomy)
        lines += [
            "",
            "| run | n | " + " | ".join(used) + " |",
            "|---|---" + "|---" * len(used) + "|",
        ]
        for g in groups:
            c = anatomy.counts(g)
            lines.append(
                f"| {g} | {sum(c.values())} | " + " | ".join(str(c[lab]) for lab in used) + " |"
            )
    if anatomy.t_c_sources:
        lines += ["", "t_c: " + "; ".join(anatomy.t_c_sources) + "."]
    if figure is not None:
        lines += ["", f"![anatomy]({figure})"]
    return [*lines, ""]


def report_section(
    run_dir: str | Path, figure_name: str = "anatomy.png", *, workers: int = 1
) -> list[str]:
    """The anatomy section of a run directory's ``report.md`` (writes its figure there).

    Never raises for a directory without trials or with a malformed record: the section then
    says so.

    Args:
        run_dir: The run directory.
        figure_name: File name of the figure inside ``run_dir``.
        workers: Worker processes for the diagnoses (:func:`explain_directory`).

    Returns:
        Markdown lines.
    """
    run_dir = Path(run_dir)
    try:
        anatomy = explain_directory(run_dir, workers=workers)
    except FlyknotError as exc:
        return ["## Failure anatomy", "", f"Not available: {exc}", ""]
    plot_anatomy(anatomy, run_dir / figure_name, title=f"failure anatomy: {run_dir.name}")
    return markdown_section(anatomy, figure_name)

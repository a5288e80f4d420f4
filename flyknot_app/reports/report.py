"""Figures and ``report.md`` of a scenario run, with the paper's numbers beside ours."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

from flyknot.verdict import KNOT
from flyknot_app.anatomy.report import report_section
from flyknot_app.judging import report_section as verdict_section
from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary
from flyknot_app.scenario import UNDER_RUNS

# The paper's results (Suresh & Atkeson), quoted per scenario kind.
PAPER = {
    "smoke": "(A check of the pipeline; the paper has no such experiment.)",
    "track": "Tracking the demonstration hand alone never tied the knot on rope 1; "
    "ropes 4 and 7 nearly succeeded.",
    "objectives": "Critical-point objective: knot learned; equally weighted objective: "
    "no knot (after 8 iterations shown).",
    "learn": "All 7 ropes learned within 10 trials (fewest for ropes 3, 6, 7; most for 2, 5); "
    "each learned command succeeded in 40/40 repeats.",
    "demos": "All 4 demonstration variants (Fast, Slow, Swipe, Inverse) learned on rope 1; "
    "Demo type 2 took the most trials.",
    "transfer": "Most transfers needed 2-5 trials; commands transferred to rope 7 needed none; "
    "5->2, 5->3 (and 6->2 or 6->3) failed within 10 trials.",
    "sensitivity": "Trials until success on rope 1: k=1e5,m_e=5: 4; k=1e4: 4; k=1e3: 4; "
    "k=1e2: >10; m_e=0.05: 8; m_e=0.005: 6.",
}
PAPER_SENSITIVITY = {
    (1e5, 5.0): "4",
    (1e4, 5.0): "4",
    (1e3, 5.0): "4",
    (1e2, 5.0): ">10",
    (1e5, 0.05): "8",
    (1e5, 0.005): "6",
}


def _trials_text(run: RunSummary) -> str:
    n = run.trials_to_success
    return str(n) if n is not None else f">{len(run.costs)}"


def smoke_line(runs: Sequence[RunSummary]) -> str:
    """Whether the pipeline worked: trials played and judged, errors measured and updates
    made (a ``smoke`` scenario checks the pipeline, not the knot)."""
    trials = sum(len(r.costs) for r in runs)
    measured = sum(c is not None for r in runs for c in r.costs)
    faults = sum(f is not None for r in runs for f in r.faults)
    classes = Counter(v["klass"] for r in runs for v in r.verdicts if v)
    judged = ", ".join(f"{k} {n}" for k, n in sorted(classes.items())) or "none"
    works = measured > 0 and trials > 0
    head = "Smoke run: the pipeline works" if works else "Smoke run: the pipeline FAILED"
    text = (
        f"{head}: {trials} trials played ({faults} faulted), judged ({judged}), the "
        f"critical-point error measured in {measured}"
    )
    if not works:
        text += " (no trial gave the learner a measurement: see the failure anatomy)"
    return text + "."


def outcome_line(kind: str, runs: Sequence[RunSummary]) -> str:
    """One sentence on a scenario's outcome: knots learned, (``track``) how often tracking
    alone tied, in the first trial and in the repeats, or (``smoke``) whether the pipeline
    worked."""
    if kind == "smoke":
        return smoke_line(runs)
    n_ok = sum(r.trials_to_success is not None for r in runs)
    if kind != "track":
        text = f"Knot learned in {n_ok} of {len(runs)} runs"
        confirming = [r for r in runs if r.learner.confirm]
        if confirming:
            k, n = confirming[0].learner.confirm
            n_conf = sum(r.confirmed for r in confirming)
            text += f"; confirmed ({k} of {n} repeats tied) in {n_conf} of {len(confirming)}"
        return text + "."
    reps = [x for r in runs for x in r.repeat_classes]
    text = f"Tracking alone (no learning): the first trial tied in {n_ok} of {len(runs)} runs"
    if reps:
        text += f"; the repeats tied in {sum(x == KNOT for x in reps)} of {len(reps)}"
    return text + "."


def plot_costs(runs: Sequence[RunSummary], path: Path, title: str) -> Path:
    """Critical-point cost over trials; squares: first knot, dots: later knots."""
    fig, ax = plt.subplots(figsize=(7, 4.2), constrained_layout=True)
    for r in runs:
        costs = [np.nan if c is None else c for c in r.costs]
        x = np.arange(1, len(costs) + 1)
        (line,) = ax.plot(x, costs, marker=".", lw=1.2, label=r.label)
        knots = np.array(r.knots, dtype=bool)
        if knots.any():
            first = int(np.argmax(knots))
            ax.plot(x[first], costs[first], "s", ms=9, color=line.get_color())
            later = np.flatnonzero(knots)[1:]
            ax.plot(x[later], np.array(costs)[later], "o", ms=8, color=line.get_color())
    ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set(xlabel="trial", ylabel="critical-point cost ||x(t_c) - x_demo(t_c)||²_Q", title=title)
    if any(any(r.knots) for r in runs):  # the markers' meaning, once, in grey
        ax.plot([], [], "s", ms=8, color="0.4", label="first knot")
        ax.plot([], [], "o", ms=7, color="0.4", label="later knot")
    ax.legend(fontsize=7, ncol=2)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval (95 % for z = 1.96) of a success rate k / n, n >= 1."""
    if n < 1 or not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n and n >= 1, got k={k}, n={n}")
    p = k / n
    den = 1.0 + z**2 / n
    mid = (p + z**2 / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / den
    return float(max(0.0, mid - half)), float(min(1.0, mid + half))


def plot_success_rates(runs: Sequence[RunSummary], path: Path, title: str) -> Path | None:
    """Knots in each run's repeats (bars) with 95 % Wilson intervals; None without repeats."""
    rows = [r for r in runs if r.repeat_classes]
    if not rows:
        return None
    k = np.array([r.n_knots_repeated for r in rows])
    n = np.array([len(r.repeat_classes) for r in rows])
    lo_hi = np.array([wilson_interval(int(a), int(b)) for a, b in zip(k, n, strict=True)])
    rate = k / n
    fig, ax = plt.subplots(figsize=(max(4.0, 0.6 * len(rows) + 2), 3.6), constrained_layout=True)
    x = np.arange(len(rows))
    ax.bar(x, rate, color="tab:blue", alpha=0.7)
    ax.errorbar(x, rate, yerr=[rate - lo_hi[:, 0], lo_hi[:, 1] - rate], fmt="none", ecolor="k")
    for xi, a, b in zip(x, k, n, strict=True):
        ax.text(xi, 1.02, f"{a}/{b}", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [r.label for r in rows], rotation=45, ha="right")
    ax.set(ylim=(0, 1.12), ylabel="knots in repeats (95 % interval)", title=title)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_transfer_grid(runs: Sequence[RunSummary], path: Path) -> Path:
    """7x7 grid of trials needed to transfer rope A's command to rope B (red: failed)."""
    grid = np.full((7, 7), np.nan)
    failed = np.zeros((7, 7), dtype=bool)
    src = {r.name: r for r in runs}
    for r in runs:
        if not r.start_from:
            continue
        a = src[r.start_from].rope
        b = r.rope
        n = r.trials_to_success
        if n is None:
            failed[a - 1, b - 1] = True
        else:
            grid[a - 1, b - 1] = n - 1  # updates before the knot (0: none needed)
    fig, ax = plt.subplots(figsize=(5.2, 4.6), constrained_layout=True)
    ax.imshow(np.where(failed, np.nan, grid), cmap="Greens_r", vmin=0, vmax=10)
    for a in range(7):
        for b in range(7):
            if failed[a, b]:
                ax.add_patch(plt.Rectangle((b - 0.5, a - 0.5), 1, 1, color="#d9534f"))
                ax.text(b, a, ">10", ha="center", va="center", fontsize=8, color="w")
            elif np.isfinite(grid[a, b]):
                ax.text(b, a, f"{int(grid[a, b])}", ha="center", va="center", fontsize=9)
    ax.set_xticks(range(7), [str(i) for i in range(1, 8)])
    ax.set_yticks(range(7), [str(i) for i in range(1, 8)])
    ax.set(
        xlabel="rope B (learning on)",
        ylabel="rope A (command from)",
        title="trials to transfer A -> B",
    )
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


CRITICAL_FIGURES = 8
"""The report shows the critical-point figure of a scenario's first this many runs."""


def critical_figure_path(out_dir: Path, run_name: str) -> Path:
    """Where a run's critical-point figure goes (beside the scenario's ``report.md``)."""
    return Path(out_dir) / f"critical_point_{run_name}.png"


def plot_critical_overlays(run_dir: Path, run: RunSummary, path: Path) -> Path | None:
    """Rope at the critical point in each trial (measured, demo frame) against the demo's.

    Each trial is drawn at the critical point its update used (t_c, or the last tracked
    instant when the rope touched itself earlier); the demonstration's rope at that time is
    x_meas - err from the update file.
    """
    from flyknot.record import TrialRecord
    from learner.critical_state import critical_state_from_record
    from learner.run_directory import RunDirectory

    rd = RunDirectory(run_dir / "learning")
    ups = sorted((run_dir / "learning").glob("update_*.json"))
    if not ups:
        return None
    fig = plt.figure(figsize=(10, 4.2), constrained_layout=True)
    axes = [fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)]
    n = len(ups)
    drawn = 0
    for u in ups:
        up = json.loads(u.read_text())
        k = int(up["trial"])
        t_eff = float(up.get("t_eff", run.t_c))
        stems = sorted((run_dir / "learning").glob(f"trial_{k:04d}_a*.json"))
        try:
            rec = TrialRecord.load(stems[-1])
            x = critical_state_from_record(rec, t_eff, rd.load_knots(k)[7:, 0])
        except Exception:
            continue
        p = x[:33].reshape(11, 3)
        pd = (x - np.asarray(up["err"]))[:33].reshape(11, 3)
        c = plt.cm.Greens(0.35 + 0.6 * (k + 1) / max(1, n))
        for ax, (i, j) in zip(axes, [(0, 2), (1, 2)], strict=True):
            ax.plot(
                pd[:, i],
                pd[:, j],
                "-",
                color="#c0392b",
                lw=1.0,
                alpha=0.5,
                label="demonstration" if drawn == 0 else None,
            )
            ax.plot(
                p[:, i], p[:, j], ".-", color=c, lw=1.2, label=f"trial {k + 1} (t = {t_eff:.3f} s)"
            )
        drawn += 1
    if not drawn:
        plt.close(fig)
        return None
    for ax, lab in zip(axes, ["x [m]", "y [m]"], strict=True):
        ax.set(xlabel=lab, ylabel="z [m]", aspect="equal")
    axes[0].set_title(f"rope at the critical point, {run.name} (t_c = {run.t_c:.3f} s)")
    axes[1].legend(fontsize=6, loc="best")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def settings_lines(out_dir: Path) -> list[str]:
    """What the report's runs were run with: ``--set`` overrides and the cell (manifest)."""
    path = out_dir / "manifest.json"
    if not path.is_file():
        return []
    manifest = json.loads(path.read_text())
    over = dict(manifest.get("overrides") or {})
    under = over.pop(UNDER_RUNS, {})
    text = ", ".join(f"`{k}={json.dumps(v)}`" for k, v in sorted(over.items())) or "none"
    if under:
        pairs = ", ".join(f"`{k}={json.dumps(v)}`" for k, v in sorted(under.items()))
        text += f"; under each run's own fields: {pairs}"
    runs = manifest.get("runs") or []
    runs = list(runs.values()) if isinstance(runs, dict) else runs
    cells = sorted({str(r.get("cell", "sim")) for r in runs if isinstance(r, dict)}) or ["sim"]
    return [f"Overrides (`--set`): {text}. Cell: {', '.join(cells)}.", ""]


def write_report(out_dir: str | Path, summary: ScenarioSummary, *, workers: int = 1) -> Path:
    """Write figures and ``report.md`` for a scenario's summary (the failure anatomy's
    diagnoses on ``workers`` processes)."""
    out_dir = Path(out_dir)
    runs = summary.runs
    kind = summary.kind
    figs = [plot_costs(runs, out_dir / "costs.png", summary.scenario)]
    rates = plot_success_rates(runs, out_dir / "success_rates.png", summary.scenario)
    if rates is not None:
        figs.append(rates)
    if kind == "transfer":
        figs.append(plot_transfer_grid(runs, out_dir / "transfer_grid.png"))
    for r in runs[:CRITICAL_FIGURES]:
        run_dir, path = out_dir / "runs" / r.name, critical_figure_path(out_dir, r.name)
        result = run_dir / "result.json"
        if path.is_file() and result.is_file() and path.stat().st_mtime >= result.stat().st_mtime:
            figs.append(path)  # drawn by the run's worker when the run ended
            continue
        p = plot_critical_overlays(run_dir, r, path)
        if p is not None:
            figs.append(p)
    lines = [f"# {summary.scenario}", ""]
    lines += ["## The paper", "", summary.paper or PAPER.get(kind, ""), "", "## Ours", ""]
    if kind == "sensitivity":
        lines += [
            "| stiffness | end mass | trials until success (ours) | paper |",
            "|---|---|---|---|",
        ]
        for r in runs:
            k = r.learner.rope_model.stiffness
            me = r.learner.rope_model.end_mass
            lines.append(
                f"| {k:g} | {me:g} | {_trials_text(r)} | {PAPER_SENSITIVITY.get((k, me), '-')} |"
            )
    else:
        lines += [
            "| run | rope | demo | objective | from | trials until knot | costs per trial "
            "| repeats |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in runs:
            costs = ", ".join("-" if c is None else f"{c:.3g}" for c in r.costs)
            rep = f"{r.n_knots_repeated}/{len(r.repeat_classes)}" if r.repeat_classes else "-"
            lines.append(
                f"| {r.name} | {r.rope} | {r.demo} | {r.learner.update.objective} | "
                f"{r.start_from or '-'} | {_trials_text(r)} | {costs} | {rep} |"
            )
    lines += ["", outcome_line(kind, runs), ""]
    lines += settings_lines(out_dir)
    lines += report_section(
        out_dir, workers=workers
    )  # failure anatomy of every trial; writes anatomy.png
    lines += verdict_section(out_dir)  # every knot and one trial per class, as pictures
    lines += ["## Figures", ""]
    lines += [f"![{p.stem}]({p.name})" for p in figs]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path

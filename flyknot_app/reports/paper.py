"""``flyknot paper``: every experiment of the paper over lab seeds, and one results table.

Each paper scenario (``scenarios/0*.toml``) runs once per lab seed (``flyknot run SCENARIO
--seeds ...``: run ``r`` becomes ``r-seedS``) into ``OUT/<scenario>``, sharing one cache of
initial guesses (``OUT/initial_guess``) and one pool of workers (a scenario's last long run
leaves no worker idle); ``--resume`` continues where a run stopped. :func:`paper_table` reads
every ``summary.json`` back and writes ``OUT/results.md``: per experiment, each run over the
seeds (trials until the first knot: median, range and how many seeds tied within the budget;
knots in the repeats pooled over the seeds, 95 % Wilson interval) beside the paper's result,
the transfer grid, the sensitivity table, the anatomy by rope (``paper_anatomy``)."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from flyknot.constants import SCENARIOS_DIR
from flyknot.errors import ConfigError
from flyknot_app.reports.paper_anatomy import anatomy_figures, anatomy_section
from flyknot_app.reports.paper_variants import VARIANTS, variant_kind

if TYPE_CHECKING:
    from flyknot_app.reports.run_summary import RunSummary, ScenarioSummary

PAPER_SCENARIOS = tuple(sorted(p.stem for p in SCENARIOS_DIR.glob("0*.toml")))
"""The paper's experiments, one scenario file each."""


_SEED_SUFFIX = re.compile(r"-seed\d+$")


def run_paper(
    out: str | Path,
    seeds: Sequence[int],
    *,
    workers: int = 1,
    resume: bool = False,
    overrides: dict | None = None,
    scenarios: Sequence[str] = PAPER_SCENARIOS,
    progress: bool = True,
) -> dict[str, float]:
    """Run ``scenarios`` over ``seeds`` into ``out`` (module docstring), every run of them on
    one pool of ``workers`` (:func:`flyknot_app.runner.run_scenarios`); per scenario, the
    seconds from the start until its report was written."""
    from flyknot_app.runner import run_scenarios
    from flyknot_app.scenario import expand_seeds, load_scenario

    out = Path(out)
    for name in scenarios:
        if name not in PAPER_SCENARIOS:
            raise ConfigError("--scenarios", f"unknown paper scenario {name!r}", PAPER_SCENARIOS)
    scens = [expand_seeds(load_scenario(n, dict(overrides or {})), list(seeds)) for n in scenarios]
    guesses = out / "initial_guess"  # made once every scenario and its demonstrations are read
    guesses.mkdir(parents=True, exist_ok=True)
    items, again = [], []
    for name, scen in zip(scenarios, scens, strict=True):
        where = out / name
        again.append(resume and (where / "manifest.json").is_file())
        where.mkdir(parents=True, exist_ok=True)
        if not (where / "initial_guess").exists():
            (where / "initial_guess").symlink_to(guesses.resolve(), target_is_directory=True)
        if progress:
            print(f"{name}: {len(scen.runs)} runs -> {where}", flush=True)
        items.append((scen, where))
    done = run_scenarios(
        items, workers=workers, resume=again, overrides=overrides, progress=progress
    )
    walls = {name: d.done_s for name, d in zip(scenarios, done, strict=True)}
    if progress:
        for name, d in zip(scenarios, done, strict=True):
            print(f"{name}: its runs {d.run_s:.0f} s in the workers, done at {d.done_s:.0f} s")
    return walls


def _base(run: RunSummary) -> str:
    """A run's name without its seed suffix."""
    return _SEED_SUFFIX.sub("", run.name)


def _grouped(summary: ScenarioSummary) -> dict[str, list[RunSummary]]:
    """The runs of a scenario by their name without the seed, in first-seen order."""
    groups: dict[str, list[RunSummary]] = {}
    for r in summary.runs:
        groups.setdefault(_base(r), []).append(r)
    return groups


def trials_text(runs: Sequence[RunSummary]) -> str:
    """Trials until the first knot over seeds: ``median (min-max), k of n seeds tied``; a
    seed without a knot counts as its budget + 1 (``>``)."""
    tied = [r.trials_to_success for r in runs if r.trials_to_success is not None]
    seeds = f"{len(runs)} seed" + ("s" if len(runs) != 1 else "")
    if not tied:
        budget = max((len(r.costs) for r in runs), default=0)
        return f"none in {budget} ({seeds})"
    med = statistics.median(tied)
    span = f"{min(tied)}-{max(tied)}" if len(tied) > 1 else f"{tied[0]}"
    return f"{med:g} ({span}), {len(tied)} of {seeds} tied"


def repeats_text(runs: Sequence[RunSummary]) -> str:
    """Knots in the repeats pooled over seeds, with a 95 % Wilson interval, or ``-``."""
    from flyknot_app.reports.report import wilson_interval

    k = sum(r.n_knots_repeated for r in runs)
    n = sum(len(r.repeat_classes) for r in runs)
    if not n:
        return "-"
    lo, hi = wilson_interval(k, n)
    return f"{k}/{n} ({100 * lo:.0f}-{100 * hi:.0f} %)"


def _runs_section(
    name: str, summary: ScenarioSummary, beside: dict[str, ScenarioSummary] | None = None
) -> list[str]:
    """Each run over the seeds; with ``beside`` (the same scenario run as a variant, by the
    variant's label) their results beside."""
    from flyknot_app.reports.report import PAPER

    beside = beside or {}
    paper = summary.paper or PAPER.get(summary.kind, "-")
    lines = [f"## `{name}` ({summary.kind})", "", f"Paper: {paper}", ""]
    head = "| run | rope | demo | objective | trials until the first knot | knots in repeats |"
    rule = "|---|---|---|---|---|---|"
    for label in beside:
        head += f" {label}: trials | knots in repeats |"
        rule += "---|---|"
    lines += [head, rule]
    others = {label: _grouped(s) for label, s in beside.items()}
    for base, runs in _grouped(summary).items():
        r = runs[0]
        if r.start_from:
            continue  # a transfer: in the grid below
        objective = r.learner.update.objective
        row = (
            f"| {base} | {r.rope} | {r.demo} | {objective} | {trials_text(runs)} | "
            f"{repeats_text(runs)} |"
        )
        for other in others.values():
            theirs = other.get(base, [])
            row += f" {trials_text(theirs) if theirs else '-'} | {repeats_text(theirs)} |"
        lines.append(row)
    return [*lines, ""]


def _sensitivity_section(
    summary: ScenarioSummary, beside: dict[str, ScenarioSummary] | None = None
) -> list[str]:
    """Trials until the first knot by the learner's rope model; with ``beside`` (variants, by
    label) theirs in a column each."""
    from flyknot_app.reports.report import PAPER_SENSITIVITY

    beside = beside or {}
    others = [_grouped(b) for b in beside.values()]
    lines = ["Trials until the first knot on rope 1, by the learner's rope model.", ""]
    lines += [
        "| stiffness | end mass | trials until the first knot (ours) | paper |"
        + "".join(f" {label} |" for label in beside)
    ]
    lines += ["|---|---|---|---|" + "---|" * len(beside)]
    for base, runs in _grouped(summary).items():
        rm = runs[0].learner.rope_model
        paper = PAPER_SENSITIVITY.get((rm.stiffness, rm.end_mass), "-")
        row = f"| {rm.stiffness:g} | {rm.end_mass:g} | {trials_text(runs)} | {paper} |"
        for other in others:
            row += f" {trials_text(other[base]) if base in other else '-'} |"
        lines.append(row)
    return [*lines, ""]


def transfer_cell(runs: Sequence[RunSummary]) -> str:
    """One transfer over seeds: the median trials until the first knot over the seeds that
    tied, ``(k/n)`` after it when k of the n seeds tied and k < n; ``-`` when none tied."""
    tied = [r.trials_to_success for r in runs if r.trials_to_success is not None]
    if not tied:
        return "-"
    share = "" if len(tied) == len(runs) else f" ({len(tied)}/{len(runs)})"
    return f"{statistics.median(tied):g}{share}"


def _transfer_section(summary: ScenarioSummary) -> list[str]:
    """The transfer grid: :func:`transfer_cell` of rope A's command on rope B."""
    runs = {r.name: r for r in summary.runs}
    cells: dict[tuple, list[RunSummary]] = {}
    for r in summary.runs:
        if r.start_from:
            cells.setdefault((runs[r.start_from].rope, r.rope), []).append(r)
    ropes = sorted({b for _, b in cells} | {a for a, _ in cells}, key=str)
    lines = ["### Transfer: median trials until the first knot, command of rope A on rope B", ""]
    lines += ["Over the seeds that tied; (k/n): k of the n seeds tied; -: none tied.", ""]
    if not cells:
        return [*lines, "No transfer run in this directory.", ""]
    lines += ["| A \\ B | " + " | ".join(str(b) for b in ropes) + " |"]
    lines += ["|---" * (len(ropes) + 1) + "|"]
    for a in ropes:
        row = []
        for b in ropes:
            row.append(transfer_cell(cells[a, b]) if (a, b) in cells else "")  # empty: not run
        lines.append(f"| {a} | " + " | ".join(row) + " |")
    return [*lines, ""]


BASELINES_DIR = "baselines"
"""Where the table looks for black-box searches from the same start: ``OUT/baselines/<name>``,
each a ``flyknot baseline NAME --demo ... --seeds ... --out`` directory."""


RESULT_BASELINES = ("cma", "random")
"""The black-box searches ``flyknot paper --all`` runs beside ILC on rope 1."""
RESULT_BASELINE_BUDGET = 10
"""Their trial budget: ILC's ``max_trials`` on rope 1."""


def check_fresh(where: Path, scenarios: Sequence[str], resume: bool) -> None:
    """Refuse to start runs over a scenario of ``where`` that holds some, unless ``resume``."""
    if not resume and any((where / n / "manifest.json").is_file() for n in scenarios):
        raise ConfigError("--out", f"{str(where)!r} already holds paper runs; use --resume")


def run_all(
    out: str | Path,
    seeds: Sequence[int],
    *,
    workers: int = 1,
    resume: bool = False,
    sets: Sequence[str] = (),
    progress: bool = True,
) -> None:
    """Everything ``docs/results.md`` shows, into ``out``: every paper scenario
    (:func:`run_paper`), each variant's :attr:`Variant.results` into ``OUT/<variant>``, and
    :data:`RESULT_BASELINES` from the rope-1 demonstration of ``03-ropes`` into
    ``OUT/baselines/<name>`` (with ``resume``, those already written are kept). ``sets``, the
    user's ``--set`` pairs, lie over every run and win over a part's own."""
    from flyknot_app.baselines import BaselineParams, search_seeds, write_results
    from flyknot_app.scenario import load_scenario, parse_overrides

    out = Path(out)
    jobs = [(out, list(PAPER_SCENARIOS), parse_overrides(list(sets)))]
    for v in VARIANTS.values():
        for part in v.results:
            scenarios = [n for n in part.scenarios if n not in v.skips]
            overrides = parse_overrides([*part.sets, *sets], defaults=v.overrides)
            jobs.append((out / v.name, scenarios, overrides))
    for where, scenarios, _ in jobs:
        check_fresh(where, scenarios, resume)
    for where, scenarios, overrides in jobs:
        run_paper(
            where, seeds, workers=workers, resume=resume, overrides=overrides,
            scenarios=scenarios, progress=progress,
        )  # fmt: skip
    demo = load_scenario("03-ropes", parse_overrides(list(sets))).runs[0].demo
    params = BaselineParams(budget=RESULT_BASELINE_BUDGET)
    for name in RESULT_BASELINES:
        where = out / BASELINES_DIR / name
        if resume and (where / "baseline.json").is_file():
            continue
        results, settings = search_seeds(name, seeds, params, demo=demo, progress=progress)
        write_results(where, results, params, 1, settings)


def _rope1(runs) -> tuple[list[int], int]:
    """A :class:`flyknot_app.reports.compare.RunSet`'s rope-1 runs: their trials until the first
    knot (a run that did not tie: its trials + 1) and how many tied."""
    pick = [i for i, (rope, _) in enumerate(runs.keys) if rope in (1, "1", None)]
    return [runs.trials[i] for i in pick], sum(runs.trials_to_success[i] is not None for i in pick)


def _baselines_section(out: Path) -> list[str]:
    """ILC's rope-1 runs (``03-ropes``) beside each black-box search in ``OUT/baselines``:
    the trials until the first knot, median with a run that did not tie counted as its
    budget + 1, and that median's ratio to ILC's."""
    from flyknot_app.reports.compare import load_runset

    found = sorted(d for d in (out / BASELINES_DIR).glob("*") if (d / "baseline.json").is_file())
    if not found or not (out / "03-ropes" / "summary.json").is_file():
        return []
    ilc, ilc_tied = _rope1(load_runset(out / "03-ropes"))
    rows = [("ILC (`03-ropes`)", ilc, ilc_tied)]
    for d in found:
        rs = load_runset(d)
        rows.append((f"{rs.kind} (`{d.name}`)", *_rope1(rs)))
    lines = [
        "## Baselines from the same start (rope 1)",
        "",
        "Black-box searches over the same command from the same initial command, lab seeds and "
        "budget (`flyknot baseline NAME --demo DEMO --budget 10 --seeds ... --out "
        f"OUT/{BASELINES_DIR}/NAME`), beside ILC's rope-1 runs of `03-ropes`. A seed without a "
        "knot counts as its budget + 1.",
        "",
        "| learner | seeds tied | median trials until the first knot | median / ILC's |",
        "|---|---|---|---|",
    ]
    for label, trials, tied in rows:
        if not trials:
            continue
        med = statistics.median(trials)
        ratio = f"{med / statistics.median(ilc):.2g}" if ilc else "-"
        lines.append(f"| {label} | {tied} of {len(trials)} | {med:g} | {ratio} |")
    return [*lines, ""]


def knot_pictures(out: str | Path) -> dict[str, Path]:
    """Per paper scenario in ``out``, the picture of its first knot (by run and trial name)
    that its report drew (``OUT/<scenario>/verdicts/*.knot.png``)."""
    out = Path(out)
    found = {}
    for name in PAPER_SCENARIOS:
        knots = sorted((out / name / "verdicts").glob("*.knot.png"))
        if knots:
            found[name] = knots[0]
    return found


def run_commits(out: str | Path) -> list[str]:
    """The commits the runs under ``out`` were made at (each scenario's and variant's
    ``manifest.json``: its ``commit`` and each resume's, ``"unrecorded"`` for one that names
    none), each once, sorted."""
    found = set()
    for path in Path(out).rglob("manifest.json"):
        try:
            doc = json.loads(path.read_text())
            commits = [doc.get("commit"), *(r.get("commit") for r in doc.get("resumed", []))]
        except (OSError, ValueError, AttributeError):
            commits = [None]
        found.update(str(c or "unrecorded") for c in commits)
    return sorted(found)


def paper_table(out: str | Path, command: str, pictures: dict[str, str] | None = None) -> str:
    """The results document of a ``flyknot paper`` directory (module docstring); under each
    scenario in ``pictures`` its picture (a path relative to the document).

    Raises:
        ConfigError: ``out`` holds no scenario's ``summary.json``.
    """
    from flyknot_app.reports.results import git_commit
    from flyknot_app.reports.run_summary import ScenarioSummary

    out = Path(out)
    found = [n for n in PAPER_SCENARIOS if (out / n / "summary.json").is_file()]
    if not found:
        raise ConfigError("--out", f"{str(out)!r} holds no paper scenario's summary.json")

    def read(path: Path) -> ScenarioSummary | None:
        doc = path / "summary.json"
        return ScenarioSummary.from_json(json.loads(doc.read_text())) if doc.is_file() else None

    seeds = set()
    sections: list[str] = []
    for name in found:
        summary = read(out / name)
        beside = {v.label: read(out / v.name / name) for v in VARIANTS.values()}
        beside = {label: b for label, b in beside.items() if b is not None}
        seeds |= {r.seed for r in summary.runs}
        if summary.kind == "sensitivity":
            sections += [f"## `{name}` ({summary.kind})", ""]
            sections += _sensitivity_section(summary, beside)
        else:
            sections += _runs_section(name, summary, beside)
        if summary.kind == "transfer":
            sections += _transfer_section(summary)
        sections += anatomy_section(out, name, pictures)
        if name in (pictures or {}):
            picture = pictures[name]
            sections += [f"The first knot of `{name}`: ![a knot of `{name}`]({picture})", ""]
    sections += _baselines_section(out)
    head = [
        "# Results",
        "",
        f"The paper's experiments in the simulated lab, lab seeds "
        f"{', '.join(str(s) for s in sorted(seeds, key=str))}; written "
        f"{dt.date.today().isoformat()} at commit {git_commit()} by `{command}` from runs made "
        f"at {', '.join(run_commits(out)) or 'unrecorded'} (each run directory's "
        "`manifest.json`). A knot is a verdict `knot` of `flyknot.verdict` (an overhand knot in "
        "the hanging rope). Trials until the first knot: median (range) over the seeds that "
        "tied; knots in the repeats (with the lab's trial-to-trial variation, whose bracket and "
        "what it does to them `docs/rope-model.md` gives): pooled over the seeds, 95 % Wilson "
        "interval. Each run's report, with a picture of every counted knot: `OUT/<scenario>/"
        "report.md`. Where the same experiments ran as a variant (`flyknot paper --variant NAME`: "
        + ", ".join(f"`{v.name}`, {v.label}" for v in VARIANTS.values())
        + "), their results stand beside.",
        "",
    ]
    return "\n".join(head + sections)


def _write_results(path: Path, out: Path, command: str, found: dict[str, Path]) -> None:
    """The table at ``path`` (``docs/results.md``), its knot pictures copied beside it into
    ``img/results/`` (the pictures already in that folder removed)."""
    import shutil

    folder = path.parent / "img" / "results"
    if folder.is_dir():
        for old in folder.glob("*.png"):
            old.unlink()
    folder.mkdir(parents=True, exist_ok=True)
    pictures = anatomy_figures(out, folder, "img/results")  # and each scenario's first knot
    for name, src in found.items():
        shutil.copyfile(src, folder / f"{name}.png")
        pictures[name] = f"img/results/{name}.png"
    path.write_text(paper_table(out, command, pictures))


def add_paper_parser(sub) -> None:
    """Add ``paper`` to ``flyknot``'s subparsers."""
    p = sub.add_parser(
        "paper",
        help="every experiment of the paper over lab seeds, then one results table",
    )
    p.add_argument("--seeds", default="0-4", help="lab seeds: A-B or A,B,... (default 0-4)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--out", default="runs/paper", help="directory (default runs/paper)")
    p.add_argument("--resume", action="store_true", help="continue the runs found in --out")
    p.add_argument(
        "--scenarios",
        nargs="+",
        default=list(PAPER_SCENARIOS),
        metavar="NAME",
        help="only these paper scenarios (default: all)",
    )
    p.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a run option (repeatable)"
    )
    p.add_argument(
        "--results", default=None, help="also write the table to this file (docs/results.md)"
    )
    p.add_argument(
        "--variant",
        default=None,
        metavar="NAME",
        help="run the experiments as a variant, into OUT/NAME (the table puts it beside the "
        "scenarios' own): " + "; ".join(f"{v.name}: {v.label}" for v in VARIANTS.values()),
    )
    p.add_argument(
        "--paper-settings",
        action="store_true",
        help="the same as --variant paper-settings",
    )
    p.add_argument("--table-only", action="store_true", help="run nothing; write the table")
    p.add_argument(
        "--all",
        action="store_true",
        help="everything docs/results.md shows: every experiment, each variant's columns and "
        "the baselines beside ILC (" + ", ".join(RESULT_BASELINES) + ")",
    )
    p.set_defaults(func=_cmd_paper)


def _cmd_paper(args: argparse.Namespace) -> int:
    from flyknot_app.scenario import parse_overrides, parse_seeds

    seeds = parse_seeds(args.seeds)
    if args.all:
        return _cmd_all(args, seeds)
    name = "paper-settings" if args.paper_settings else args.variant
    variant = None if name is None else variant_kind(name)
    overrides = parse_overrides(args.set, defaults=variant.overrides if variant else ())
    out = Path(args.out)
    where = out / variant.name if variant else out
    scenarios = [n for n in args.scenarios if variant is None or n not in variant.skips]
    if not args.table_only:
        check_fresh(where, scenarios, args.resume)
        run_paper(
            where,
            seeds,
            workers=args.workers,
            resume=args.resume,
            overrides=overrides,
            scenarios=scenarios,
        )
    return _write_tables(args, out)


def _cmd_all(args: argparse.Namespace, seeds: list[int]) -> int:
    """``flyknot paper --all``: :func:`run_all`, then the tables."""
    for flag, given in (
        ("--variant", args.variant is not None),
        ("--paper-settings", args.paper_settings),
        ("--table-only", args.table_only),
        ("--scenarios", list(args.scenarios) != list(PAPER_SCENARIOS)),
    ):
        if given:
            raise ConfigError("--all", f"runs every scenario and variant; not with {flag}")
    out = Path(args.out)
    run_all(out, seeds, workers=args.workers, resume=args.resume, sets=args.set or ())
    return _write_tables(args, out)


def _write_tables(args: argparse.Namespace, out: Path) -> int:
    """``OUT/results.md`` and, with ``--results``, that file with its pictures; the header
    names the command line that ran the experiments."""
    command = "flyknot paper" + (" --all" if args.all else "")
    command += f" --seeds {args.seeds} --out {args.out}"
    command += "".join(f" --set {p}" for p in args.set or [])
    found = knot_pictures(out)
    pictures = {n: str(p.relative_to(out)) for n, p in found.items()}
    pictures |= anatomy_figures(out, out / "img", "img")
    (out / "results.md").write_text(paper_table(out, command, pictures))
    if args.results:
        _write_results(Path(args.results), out, command, found)
    print(f"results: {out / 'results.md'}" + (f" and {args.results}" if args.results else ""))
    return 0

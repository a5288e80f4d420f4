"""Scenario files: one TOML file per experiment, parsed into frozen dataclasses.

Format (every field is validated; unknown keys are errors that list the valid ones)::

    name = "ropes"                      # defaults to the file's stem
    description = "Learning on each rope from the rope-1 demonstration"
    kind = "learn"          # learn | track | transfer | sensitivity | objectives | demos | smoke
    paper = "all 7 ropes within 10 trials"   # the paper's result, quoted in report.md

    [defaults]                          # fields shared by every run (RunSpec below)
    demo = "fast"
    max_trials = 10

    [defaults.rope_model]               # the learner's rope model (learner.rope_model)
    stiffness = 1e5

    [[run]]                             # one entry per run; overrides the defaults
    name = "rope1"
    rope = 1

    [grid]                              # or: the product of lists makes the runs
    rope = [1, 2, 3, 4, 5, 6, 7]

Your own ropes: a top-level ``ropes = "my_ropes.toml"`` (a ropes file, see
``assets/ropes_example.toml``; a relative path is looked up beside the scenario file, then in
the working directory; ``flyknot run --ropes FILE`` replaces it) lets ``rope`` (in runs,
defaults and grids) name its ropes: ``rope = "my cord"``.

A run may start from another run's learned command: ``start_from = "rope3"`` (the name of a
run in the same scenario); it then runs after that one.
"""

from __future__ import annotations

import itertools
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from flyknot.constants import DEMOS_DIR, FOLLOW_THROUGH_S, PATH_FRAC, SCENARIOS_DIR
from flyknot.errors import ConfigError, RecordError, check_choice, check_nonnegative
from flyknot.options import (
    INLINE,
    NOT_AN_OPTION,
    coerce_override,
    from_mapping,
    nested_options,
    option_names,
    to_mapping,
)
from flyknot_app.cells import cell_kind, cell_spec
from flyknot_app.learner_settings import PAPER_SETTINGS
from learner.ilc import ILCParams

KINDS = ("learn", "track", "transfer", "sensitivity", "objectives", "demos", "smoke")


@dataclass(frozen=True)
class RunSpec:
    """One learning run of a scenario.

    A run's options are its own fields below and the learning loop's (``learner``), which sit
    beside them: ``max_trials``, ``gain``, ``objective``, ``weights.w_control``... (every
    option of :class:`learner.ilc.ILCParams` and :class:`learner.update.UpdateSettings`).

    Attributes:
        name: Unique within the scenario (a directory name).
        rope: Rope id in the simulated lab (1..7), or a rope's name: the paper's (it becomes
            its id) or one of ``ropes``.
        demo: Demonstration: a name under ``assets/demos`` (without ``.npz``) or a path.
        seed: Seed of the lab's trial-to-trial variation.
        repeats: After learning, play the final command this many more times (success rate).
        settle_s: A fixed settling time before the knot is judged [s]; None (default): the
            lab waits until the rope is at rest (``flyknot.rest.SettleParams``).
        start_from: Name of the run whose final command starts this one (transfer), or None.
        follow_through_s: Demonstration window end t_f - t_c [s] (the paper: 0.035).
        path_frac: Demonstration window start: the fraction of the hand path travelled at
            t_0, in [0, 1) (the paper: 0.05).
        label: Free text for figures (e.g. "k=1e3, m_e=5").
        learner: The learning loop's options (:class:`learner.ilc.ILCParams`; ``max_trials``
            0 plays the initial command once: tracking alone). On the command line the
            confirmed-success rule is ``--set confirm=k/n``.
        ropes: A user's ropes file (absolute path; set from the scenario's top-level
            ``ropes``), or None.
        cell: Kind of cell the run plays on (:data:`flyknot_app.cells.CELLS`; set by the
            scenario's ``[cell] kind`` or ``flyknot run --cell``): ``rope``, ``seed``,
            ``settle_s`` and ``ropes`` are given to that cell.
        cell_options: The cell's other fields (e.g. the real lab's ``lab`` file), from the
            ``[cell]`` table or the command line.
    """

    name: str
    rope: int | str = 1
    demo: str = "fast"
    seed: int = 0
    repeats: int = 0
    settle_s: float | None = None
    start_from: str | None = None
    follow_through_s: float = FOLLOW_THROUGH_S
    path_frac: float = PATH_FRAC
    label: str = ""
    learner: ILCParams = field(default_factory=ILCParams, metadata=INLINE)
    ropes: str | None = field(default=None, metadata=NOT_AN_OPTION)
    cell: str = field(default="sim", metadata=NOT_AN_OPTION)
    cell_options: Mapping[str, Any] = field(default_factory=dict, metadata=NOT_AN_OPTION)

    def __post_init__(self) -> None:
        cell_kind(self.cell)
        if not isinstance(self.name, str) or not self.name or "/" in self.name:
            raise ConfigError(
                "run.name", f"must be a non-empty name without '/', got {self.name!r}"
            )
        rope = parse_rope_arg(self.rope) if isinstance(self.rope, str) else self.rope
        if isinstance(rope, str) or self.ropes is not None:
            from flyknot_sim.rope_custom import resolve_rope

            params = resolve_rope(rope, self.ropes)
            rope = params.name if params.custom else params.id
        else:
            check_choice("rope", rope, range(1, 8))
        object.__setattr__(self, "rope", rope)
        for f in ("seed", "repeats"):
            v = getattr(self, f)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ConfigError(f, f"must be an integer >= 0, got {v!r}")
        if self.settle_s is not None:
            check_nonnegative("settle_s", self.settle_s)
        if not isinstance(self.learner, ILCParams):
            raise ConfigError("learner", f"must be an ILCParams, got {self.learner!r}")
        check_nonnegative("follow_through_s", self.follow_through_s)
        if not (isinstance(self.path_frac, (int, float)) and 0.0 <= self.path_frac < 1.0):
            raise ConfigError("path_frac", f"must lie in [0, 1), got {self.path_frac!r}")
        object.__setattr__(self, "cell_options", dict(self.cell_options))

    def cell_spec(self) -> Any:
        """The validated spec of the run's cell (:func:`flyknot_app.cells.cell_spec`)."""
        values = {"rope": self.rope, "seed": self.seed, "settle_s": self.settle_s}
        return cell_spec(self.cell, {**values, "ropes": self.ropes, **self.cell_options})

    @property
    def window(self) -> tuple[float, float]:
        """(follow_through_s, path_frac): what selects the demonstration window."""
        return (float(self.follow_through_s), float(self.path_frac))

    def to_json(self) -> dict[str, Any]:
        """Every option of the run (:func:`flyknot.options.to_mapping`) and its cell."""
        cell = {"ropes": self.ropes, "cell": self.cell, "cell_options": dict(self.cell_options)}
        return {**to_mapping(self), **cell}


RUN_KEYS = option_names(RunSpec)
"""Options a scenario's runs, defaults, grid and ``--set`` may give (``ropes`` and the cell
are top-level)."""


def parse_rope_arg(text: str) -> int | str:
    """A rope on the command line or in a scenario: digits are a paper rope id (an int),
    anything else a rope's name (``argparse`` ``type=`` for ``--rope``)."""
    t = text.strip()
    return int(t) if t.isdigit() else text


def find_ropes_file(path: str | Path, base: Path | None = None) -> str:
    """A ropes file as an absolute path: ``path`` itself if absolute, else beside ``base``
    (a scenario's folder) if there, else in the working directory.

    Raises:
        ConfigError: No such file.
    """
    p = Path(path).expanduser()
    for cand in [p] if p.is_absolute() else [*([base / p] if base else []), p]:
        if cand.is_file():
            return str(cand.resolve())
    raise ConfigError("ropes", f"no ropes file {str(path)!r}")


@dataclass(frozen=True)
class Scenario:
    """An experiment: a list of runs plus what to report."""

    name: str
    kind: str
    runs: tuple[RunSpec, ...]
    description: str = ""
    paper: str = ""
    source: str | None = None

    def __post_init__(self) -> None:
        check_choice("kind", self.kind, KINDS)
        if not self.runs:
            raise ConfigError("run", "the scenario defines no runs")
        names = [r.name for r in self.runs]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError("run.name", f"duplicate run names: {', '.join(dup)}")
        for r in self.runs:
            if r.start_from is not None:
                check_choice(
                    f"run {r.name!r} start_from", r.start_from, [n for n in names if n != r.name]
                )

    def order(self) -> list[list[RunSpec]]:
        """Runs in waves: each wave depends only on earlier waves (for parallel workers)."""
        done: set[str] = set()
        left = list(self.runs)
        waves = []
        while left:
            wave = [r for r in left if r.start_from is None or r.start_from in done]
            if not wave:
                raise ConfigError("start_from", "runs depend on each other in a cycle")
            waves.append(wave)
            done |= {r.name for r in wave}
            left = [r for r in left if r.name not in done]
        return waves


def option_path(key: str) -> list[str]:
    """A ``--set`` key as its path of option names (``weights.w_control`` -> two names), each
    checked against the options of the run or of the table it names.

    Raises:
        ConfigError: A name that is not an option there (the message lists the valid ones).
    """
    parts = key.split(".")
    cls: type | None = RunSpec
    for i, part in enumerate(parts):
        names = option_names(cls) if cls is not None else ()
        if cls is None or part not in names:
            where = "--set key" if i == 0 else f"{'.'.join(parts[:i])} key"
            valid = [n for n in names if n != "name"] + (["max_runs"] if i == 0 else [])
            raise ConfigError(where, f"unknown value {part!r}", valid)
        cls = nested_options(cls, part)
    return parts


CELL_KEY = "cell"
"""The first name of a ``--set`` key that sets a field of the run's cell
(``cell.variation.servo_gain_rel=0.003``), laid over the scenario's ``[cell]`` table."""


def cell_path(key: str) -> list[str]:
    """A ``--set cell....`` key as its path (the cell's fields are checked with its kind, in
    :func:`parse_scenario`).

    Raises:
        ConfigError: An empty name, or a field a run sets itself (``rope``, ``seed``,
            ``settle_s``: ``--set rope=3``).
    """
    parts = key.split(".")
    if not all(parts):
        raise ConfigError("--set key", f"expected cell.FIELD[.NAME]=value, got {key!r}")
    if parts[1] in RUN_KEYS:
        raise ConfigError("--set key", f"set {parts[1]!r} as --set {parts[1]}=VALUE, not {key!r}")
    return parts


UNDER_RUNS = "defaults"
"""The key of an overrides dict whose options lie over a scenario's defaults and under each
run's own fields (:func:`parse_overrides`)."""


def parse_overrides(
    pairs: list[str] | None, *, paper_settings: bool = False, defaults: Sequence[str] = ()
) -> dict[str, Any]:
    """``["max_trials=2", "rope_model.stiffness=1e3"]`` -> a nested dict of run options (a
    later pair wins) that lies over every run.

    ``defaults`` (and with ``paper_settings``, :data:`PAPER_SETTINGS` before them) go under
    the key :data:`UNDER_RUNS`: they replace the scenario's defaults but not what a run sets
    itself (the equal run's objective, a sensitivity run's rope model)."""
    out = _parse_pairs(pairs or [])
    under = [*(PAPER_SETTINGS if paper_settings else ()), *defaults]
    if under:
        out[UNDER_RUNS] = _parse_pairs(under)
    return out


def _parse_pairs(pairs: Sequence[str]) -> dict[str, Any]:
    """``key=value`` pairs -> a nested dict of run options (and ``max_runs``)."""
    out: dict[str, Any] = {}
    for p in pairs:
        if "=" not in p:
            raise ConfigError("--set", f"expected key=value, got {p!r}")
        key, value = (part.strip() for part in p.split("=", 1))
        if key == "max_runs":
            out["max_runs"] = int(value)
            continue
        *tables, leaf = cell_path(key) if key.startswith(CELL_KEY + ".") else option_path(key)
        node = out
        for t in tables:
            node = node.setdefault(t, {})
        node[leaf] = coerce_override(value)
    return out


def _name_part(value: Any) -> str:
    """A grid value in a run name: a rope name's spaces and slashes become '_'."""
    return "_".join(value.replace("/", " ").split()) if isinstance(value, str) else str(value)


def merge_options(*layers: Mapping[str, Any]) -> dict[str, Any]:
    """Option tables laid over each other: a later layer's value wins, nested tables merge."""
    out: dict[str, Any] = {}
    for layer in layers:
        for k, v in layer.items():
            if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
                out[k] = merge_options(out[k], v)
            else:
                out[k] = dict(v) if isinstance(v, Mapping) else v
    return out


def _make_run(
    raw: Mapping[str, Any],
    where: str,
    ropes: str | None = None,
    cell: str = "sim",
    cell_options: Mapping[str, Any] | None = None,
) -> RunSpec:
    given = {"ropes": ropes, "cell": cell, "cell_options": dict(cell_options or {})}
    return from_mapping(RunSpec, raw, where=where, given=given)


def _leaves(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested option table as ``{"a.b": value}``: its leaf values by dotted key."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        out |= _leaves(v, key + ".") if isinstance(v, Mapping) else {key: v}
    return out


def _refuse_collapsing(
    scenario: str,
    overrides: Mapping[str, Any],
    entries: Sequence[Mapping[str, Any]],
) -> None:
    """Refuse a ``--set`` of a field every run of the scenario sets itself, not all alike.

    Such a field is what the scenario compares (02-objectives' objective, 03-ropes' rope,
    05-demos' demo): overriding it gives every run the same value under its own name.

    Raises:
        ConfigError: ``--set KEY`` names one (its values listed).
    """
    sets = [_leaves(e) for e in entries]
    for key in _leaves(overrides):
        if not sets or not all(key in s for s in sets):
            continue
        values = sorted({repr(s[key]) for s in sets})
        if len(values) > 1:
            raise ConfigError(
                f"--set {key}",
                f"{scenario!r} compares its runs by {key} ({', '.join(values)}); a --set "
                "would give every run the same value under its own name: set it on a "
                "scenario that does not vary it (learn-rope1)",
            )


def parse_scenario(
    doc: Mapping[str, Any],
    *,
    name: str,
    overrides: Mapping[str, Any] | None = None,
    source: str | None = None,
    ropes: str | Path | None = None,
    cell: Mapping[str, Any] | None = None,
) -> Scenario:
    """Build a :class:`Scenario` from a parsed TOML document (plus ``--set`` overrides).

    ``cell`` (``flyknot run --cell FILE``) replaces the document's ``[cell]`` table.

    ``ropes`` (``flyknot run --ropes FILE``) replaces the document's top-level ``ropes``; a
    relative path in the document is looked up beside ``source`` first.
    """
    allowed = ("name", "description", "kind", "paper", "ropes", "cell", "defaults", "run", "grid")
    for k in doc:
        if k not in allowed:
            raise ConfigError(k, "unknown top-level field", allowed)
    if ropes is not None:
        ropes = find_ropes_file(ropes)
    elif "ropes" in doc:
        if not isinstance(doc["ropes"], str) or not doc["ropes"]:
            raise ConfigError("ropes", f"must be a file path, got {doc['ropes']!r}")
        ropes = find_ropes_file(doc["ropes"], Path(source).parent if source else None)
    overrides = dict(overrides or {})
    cell = merge_options(cell if cell is not None else doc.get("cell", {}))
    cell = merge_options(cell, overrides.pop(CELL_KEY, {}))
    kind = cell.pop("kind", "sim")
    cell_kind(kind)
    settable = tuple(f for f in cell_kind(kind).fields if f != "ropes")
    for k in cell:
        if k not in settable:
            raise ConfigError(f"cell.{k}", f"not a field of a {kind!r} cell", settable)
    options = {k: v for k, v in cell.items() if k not in RUN_KEYS}
    cell_defaults = {k: v for k, v in cell.items() if k in RUN_KEYS}
    defaults = {**cell_defaults, **dict(doc.get("defaults", {}))}
    max_runs = overrides.pop("max_runs", None)
    under = overrides.pop(UNDER_RUNS, {})
    raw_runs: list[dict[str, Any]] = []
    if "grid" in doc:
        grid = dict(doc["grid"])
        keys = list(grid)
        for k in keys:
            if not isinstance(grid[k], list) or not grid[k]:
                raise ConfigError(f"grid.{k}", "must be a non-empty list")
        for combo in itertools.product(*(grid[k] for k in keys)):
            entry = dict(zip(keys, combo, strict=True))
            entry.setdefault("name", "-".join(f"{k}{_name_part(v)}" for k, v in entry.items()))
            raw_runs.append(entry)
    for entry in doc.get("run", []):
        raw_runs.append(dict(entry))
    _refuse_collapsing(str(doc.get("name", name)), overrides, raw_runs)
    runs = []
    for i, entry in enumerate(raw_runs):
        merged = merge_options({"name": f"run{i}"}, defaults, under, entry, overrides)
        runs.append(_make_run(merged, f"run[{i}]", ropes, kind, options))
    scen = Scenario(
        name=str(doc.get("name", name)),
        kind=str(doc.get("kind", "learn")),
        runs=tuple(runs),
        description=str(doc.get("description", "")),
        paper=str(doc.get("paper", "")),
        source=source,
    )
    if max_runs is not None:
        scen = limit_runs(scen, max_runs)
    return scen


def parse_seeds(text: str) -> list[int]:
    """``"0-4"`` or ``"0,2,5"`` as a list of seeds."""
    try:
        if "-" in text:
            lo, hi = (int(v) for v in text.split("-", 1))
            seeds = list(range(lo, hi + 1))
        else:
            seeds = [int(v) for v in text.split(",")]
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0:
        raise ConfigError("--seeds", f"must be A-B or A,B,... with seeds >= 0, got {text!r}")
    return seeds


def expand_seeds(scen: Scenario, seeds: list[int]) -> Scenario:
    """Every run once per lab seed: run ``r`` becomes ``r-seedS`` with ``seed = S`` (a
    transfer run starts from the same seed's source run)."""
    if not seeds:
        raise ConfigError("--seeds", "give at least one seed")
    runs = []
    for s in seeds:
        for r in scen.runs:
            start = None if r.start_from is None else f"{r.start_from}-seed{s}"
            runs.append(replace(r, name=f"{r.name}-seed{s}", seed=s, start_from=start))
    return replace(scen, runs=tuple(runs))


def limit_runs(scen: Scenario, n: int) -> Scenario:
    """Keep the first ``n`` runs plus the runs they start from (smoke tests)."""
    if n < 1:
        raise ConfigError("max_runs", f"must be >= 1, got {n}")
    by_name = {r.name: r for r in scen.runs}
    keep: list[str] = []
    for r in scen.runs[:n]:
        chain = []
        cur: RunSpec | None = r
        while cur is not None and cur.name not in keep and cur.name not in chain:
            chain.append(cur.name)
            cur = by_name.get(cur.start_from) if cur.start_from else None
        keep.extend(reversed(chain))
    runs = tuple(r for r in scen.runs if r.name in keep)
    return replace(scen, runs=runs)


def find_named_file(field_name: str, name_or_path: str, folder: Path, suffix: str) -> Path:
    """A file by path, or by name (stem) in ``folder``; the error lists the names there."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    cand = folder / f"{name_or_path}{suffix}"
    if cand.is_file():
        return cand
    names = sorted(q.stem for q in folder.glob(f"*{suffix}")) if folder.is_dir() else []
    raise ConfigError(field_name, f"no {field_name} file or name {name_or_path!r}", names)


def find_scenario(name_or_path: str) -> Path:
    """A scenario by path, or by name under ``scenarios/`` (error lists the names)."""
    return find_named_file("scenario", name_or_path, SCENARIOS_DIR, ".toml")


def load_scenario(
    name_or_path: str,
    overrides: Mapping[str, Any] | None = None,
    ropes: str | Path | None = None,
    cell: Mapping[str, Any] | None = None,
) -> Scenario:
    """Read and validate a scenario file (``ropes``, ``cell``: see :func:`parse_scenario`),
    and read every demonstration its runs name (:func:`check_demos`)."""
    path = find_scenario(name_or_path)
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(path), f"not valid TOML: {e}") from None
    scen = parse_scenario(
        doc, name=path.stem, overrides=overrides, source=str(path), ropes=ropes, cell=cell
    )
    check_demos(scen)
    return scen


def demo_names() -> list[str]:
    """The demonstrations under ``assets/demos``, by the names a run's ``demo`` may give."""
    return sorted(p.stem for p in DEMOS_DIR.glob("*.npz"))


def check_demo(demo: str) -> Path:
    """The file of a run's ``demo`` (a name under ``assets/demos`` or a path to a ``.npz``,
    ``.csv`` or ``.c3d`` demonstration: :func:`flyknot.demo_formats.read_demonstration`),
    read whole.

    Raises:
        ConfigError: No such demonstration, or a file that is no readable demonstration; the
            message names the problem and lists :func:`demo_names`.
    """
    from flyknot.demo_formats import read_demonstration

    if not isinstance(demo, str) or not demo:
        raise ConfigError("demo", f"must be a name or a file path, got {demo!r}", demo_names())
    path = find_named_file("demo", demo, DEMOS_DIR, ".npz")
    try:
        read_demonstration(path)
    except RecordError as e:
        raise ConfigError("demo", str(e), demo_names()) from None
    return path


def check_demos(scen: Scenario) -> None:
    """Read every demonstration the scenario's runs name (:func:`check_demo`): a missing or
    unreadable one stops the scenario before anything is written."""
    for demo in sorted({r.demo for r in scen.runs}, key=str):
        check_demo(demo)

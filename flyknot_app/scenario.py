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
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from flyknot.constants import FOLLOW_THROUGH_S, PATH_FRAC, SCENARIOS_DIR
from flyknot.errors import ConfigError, check_choice, check_nonnegative
from flyknot_app.cells import cell_kind, cell_spec
from learner.ilc import ILCParams
from learner.inverse_qp import InverseModelWeights
from learner.rope_model import RopeModelParams

KINDS = ("learn", "track", "transfer", "sensitivity", "objectives", "demos", "smoke")
ROPE_MODEL_KEYS = tuple(f.name for f in fields(RopeModelParams))
"""The learner's rope model fields a run may set (``rope_model.<key>``)."""
WEIGHT_KEYS = tuple(f.name for f in fields(InverseModelWeights))
"""The inverse-model weights a run may set (``weights.<key>``)."""


@dataclass(frozen=True)
class RunSpec:
    """One learning run of a scenario.

    Attributes:
        name: Unique within the scenario (a directory name).
        rope: Rope id in the simulated lab (1..7), or a rope's name: the paper's (it becomes
            its id) or one of ``ropes``.
        demo: Demonstration: a name under ``assets/demos`` (without ``.npz``) or a path.
        seed: Seed of the lab's trial-to-trial variation.
        max_trials: Learning trials at most (0: only play the initial command once).
        objective: ``"critical"`` or ``"equal"``.
        stop_at_success: Stop at the first knot.
        repeats: After learning, play the final command this many more times (success rate).
        settle_s: A fixed settling time before the knot is judged [s]; None (default): the
            lab waits until the rope is at rest (``flyknot.rest.SettleParams``).
        backend: QP solver (``"clarabel"`` or ``"osqp"``).
        start_from: Name of the run whose final command starts this one (transfer), or None.
        rope_model: Overrides of the learner's rope model parameters.
        gain: ILC learning gain in (0, 1] (the paper: 1).
        weights: Overrides of the inverse-model weights (learner.inverse_qp).
        trust_region: Largest change of any arm knot per update [rad], or None (the paper
            has none).
        confirm: Confirmed-success stop rule ``[k, n]`` (a tying command is repeated until
            n of its trials ran; stop when k tied; repeats count as trials), or None: the
            paper's stop at the first knot. On the command line: ``--set confirm=k/n``.
        safeguard: Reject an update whose trial's cost rose above the best trial's and step
            from the best command instead, shrunk by 1/2 per rejection (the paper: none).
        average: Plays of each command before an update, on their mean critical-point error
            (each play a trial; the paper: 1).
        follow_through_s: Demonstration window end t_f - t_c [s] (the paper: 0.035).
        path_frac: Demonstration window start: the fraction of the hand path travelled at
            t_0, in [0, 1) (the paper: 0.05).
        label: Free text for figures (e.g. "k=1e3, m_e=5").
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
    max_trials: int = 10
    objective: str = "critical"
    stop_at_success: bool = True
    repeats: int = 0
    settle_s: float | None = None
    backend: str = "clarabel"
    start_from: str | None = None
    rope_model: Mapping[str, float] = field(default_factory=dict)
    gain: float = 1.0
    weights: Mapping[str, float] = field(default_factory=dict)
    trust_region: float | None = None
    confirm: tuple[int, int] | None = None
    safeguard: bool = False
    average: int = 1
    follow_through_s: float = FOLLOW_THROUGH_S
    path_frac: float = PATH_FRAC
    label: str = ""
    ropes: str | None = None
    cell: str = "sim"
    cell_options: Mapping[str, Any] = field(default_factory=dict)

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
        for f in ("seed", "max_trials", "repeats"):
            v = getattr(self, f)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ConfigError(f, f"must be an integer >= 0, got {v!r}")
        if self.settle_s is not None:
            check_nonnegative("settle_s", self.settle_s)
        for key, choices in (("rope_model", ROPE_MODEL_KEYS), ("weights", WEIGHT_KEYS)):
            values = dict(getattr(self, key))
            for k in values:
                check_choice(f"{key} key", k, choices)
            object.__setattr__(self, key, values)
        # The learner's options are validated where they live (ILCParams).
        object.__setattr__(self, "confirm", self.ilc_params().confirm)
        check_nonnegative("follow_through_s", self.follow_through_s)
        if not (isinstance(self.path_frac, (int, float)) and 0.0 <= self.path_frac < 1.0):
            raise ConfigError("path_frac", f"must lie in [0, 1), got {self.path_frac!r}")

    def ilc_params(self) -> ILCParams:
        """The learning loop's options of this run (:class:`learner.ilc.ILCParams`), which
        validates them; ``max_trials`` 0 (the initial command alone) plays one trial."""
        return ILCParams(
            max_trials=max(1, self.max_trials),
            stop_at_success=self.stop_at_success,
            objective=self.objective,
            backend=self.backend,
            rope_model=RopeModelParams(**self.rope_model),
            gain=self.gain,
            weights=InverseModelWeights(**self.weights),
            trust_region=self.trust_region,
            confirm=self.confirm,
            safeguard=self.safeguard,
            average=self.average,
        )

    def cell_spec(self) -> Any:
        """The validated spec of the run's cell (:func:`flyknot_app.cells.cell_spec`)."""
        values = {"rope": self.rope, "seed": self.seed, "settle_s": self.settle_s}
        return cell_spec(self.cell, {**values, "ropes": self.ropes, **self.cell_options})

    @property
    def window(self) -> tuple[float, float]:
        """(follow_through_s, path_frac): what selects the demonstration window."""
        return (float(self.follow_through_s), float(self.path_frac))


RUN_KEYS = tuple(f.name for f in fields(RunSpec) if f.name not in ("ropes", "cell", "cell_options"))
"""Fields a scenario's runs, defaults, grid and ``--set`` may give (``ropes`` and the cell's
kind are top-level)."""


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


def _coerce_override(value: str) -> Any:
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    low = value.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    return value


PAPER_SETTINGS = (
    "gain=1",
    "weights.w_control=0.5",
    "rope_model.stiffness=1e5",
    "rope_model.damping=50",
    "path_frac=0.05",
    "follow_through_s=0.035",
)
"""The paper's learner settings as ``--set`` overrides (``flyknot run --paper-settings``):
ILC gain 1, control weight 0.5, rope model bending stiffness 1e5 and damping 50, the
demonstration window from 5 % of the hand path to t_c + 35 ms (Suresh & Atkeson; the
scenario files' own values and why they differ: README "Learner settings")."""


def parse_overrides(pairs: list[str] | None) -> dict[str, Any]:
    """``["max_trials=2", "rope_model.stiffness=1e3"]`` -> a nested dict of run fields."""
    out: dict[str, Any] = {}
    for p in pairs or []:
        if "=" not in p:
            raise ConfigError("--set", f"expected key=value, got {p!r}")
        key, value = p.split("=", 1)
        key = key.strip()
        if key.startswith("rope_model."):
            sub = key.split(".", 1)[1]
            check_choice("rope_model key", sub, ROPE_MODEL_KEYS)
            out.setdefault("rope_model", {})[sub] = _coerce_override(value)
        elif key.startswith("weights."):
            sub = key.split(".", 1)[1]
            check_choice("weights key", sub, WEIGHT_KEYS)
            out.setdefault("weights", {})[sub] = _coerce_override(value)
        elif key == "max_runs":
            out["max_runs"] = int(value)
        else:
            check_choice("--set key", key, [k for k in RUN_KEYS if k != "name"] + ["max_runs"])
            out[key] = _coerce_override(value)
    return out


def _name_part(value: Any) -> str:
    """A grid value in a run name: a rope name's spaces and slashes become '_'."""
    return "_".join(value.replace("/", " ").split()) if isinstance(value, str) else str(value)


def _make_run(
    raw: Mapping[str, Any],
    where: str,
    ropes: str | None = None,
    cell: str = "sim",
    cell_options: Mapping[str, Any] | None = None,
) -> RunSpec:
    for k in raw:
        if k not in RUN_KEYS:
            raise ConfigError(f"{where}.{k}", "unknown field", RUN_KEYS)
    try:
        return RunSpec(**raw, ropes=ropes, cell=cell, cell_options=dict(cell_options or {}))
    except TypeError as e:
        raise ConfigError(where, str(e)) from None


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
    cell = dict(cell if cell is not None else doc.get("cell", {}))
    kind = cell.pop("kind", "sim")
    cell_kind(kind)
    settable = tuple(f for f in cell_kind(kind).fields if f != "ropes")
    for k in cell:
        if k not in settable:
            raise ConfigError(f"cell.{k}", f"not a field of a {kind!r} cell", settable)
    options = {k: v for k, v in cell.items() if k not in RUN_KEYS}
    cell_defaults = {k: v for k, v in cell.items() if k in RUN_KEYS}
    defaults = {**cell_defaults, **dict(doc.get("defaults", {}))}
    overrides = dict(overrides or {})
    max_runs = overrides.pop("max_runs", None)
    rope_model = {**dict(defaults.pop("rope_model", {})), **dict(overrides.pop("rope_model", {}))}
    weights = {**dict(defaults.pop("weights", {})), **dict(overrides.pop("weights", {}))}
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
    runs = []
    for i, entry in enumerate(raw_runs):
        merged = {**defaults, **entry, **overrides}
        merged["rope_model"] = {
            **rope_model,
            **dict(entry.get("rope_model", {})),
            **dict(overrides.get("rope_model", {})),
        }
        merged["weights"] = {**weights, **dict(entry.get("weights", {}))}
        merged.setdefault("name", f"run{i}")
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
    """Read and validate a scenario file (``ropes``, ``cell``: see :func:`parse_scenario`)."""
    path = find_scenario(name_or_path)
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(str(path), f"not valid TOML: {e}") from None
    return parse_scenario(
        doc, name=path.stem, overrides=overrides, source=str(path), ropes=ropes, cell=cell
    )

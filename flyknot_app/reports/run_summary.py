"""What a scenario's runs did: :class:`RunSummary` (a run's ``result.json``) and
:class:`ScenarioSummary` (the run directory's ``summary.json``).

A run's options are not repeated here: a summary keeps the run's :meth:`RunSpec.to_json
<flyknot_app.scenario.RunSpec.to_json>` as written, and reads its learner options back through
:func:`flyknot.options.from_mapping`. On disk the options and the outcome sit side by side in
one flat JSON object, with the two derived values ``confirmed`` and ``repeat_success_rate``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from flyknot.errors import ConfigError
from flyknot.options import ReadOnlyMap, from_mapping, option_names
from flyknot.verdict import KNOT
from flyknot_app.scenario import RunSpec
from learner.ilc_params import ILCParams

OPTION_KEYS = (*option_names(RunSpec), "ropes", "cell", "cell_options")
"""The keys of a summary that are the run's options (:meth:`RunSpec.to_json`)."""
DERIVED_KEYS = ("confirmed", "repeat_success_rate")
"""Keys a summary's JSON carries for readers, computed from the others."""


@dataclass(frozen=True)
class RunSummary:
    """One run of a scenario: its options and what happened.

    Attributes:
        options: The run's options as it ran (:meth:`RunSpec.to_json`).
        costs: Critical-point cost of each counted trial, None where unmeasured.
        knots: Whether each counted trial tied a knot in the hanging rope.
        faults: Each counted trial's fault, or None.
        verdicts: Each counted trial's verdict (``Verdict.to_json``), or None.
        trials_to_success: Trials until the first knot (1-based), or None.
        stopped_because: Why the learning loop stopped.
        attempts: Trials played in learning, tracking repeats included.
        repeat_classes: Verdict class of each play of the final command after learning, ``"fault"``
            for a faulted one, None for one without a verdict.
        repeat_verdicts: The verdict of each repeat (``Verdict.to_json``), or None.
        judge: The name of the judge whose verdicts these are (``flyknot.verdict.JUDGE_NAME``).
        initial_guess: The initial guess's solve (status, cost, errors, T, t_c), or empty
            when the run started from another run's command.
        T: Duration of the command [s] (None: not known).
        t_c: Critical time of the demonstration [s] (None: not known).
        wall_s: Wall time of the run [s].
        custom_rope: A custom rope's ``rope_name``, ``rope_params`` and ``ropes_file``, or
            empty for a rope of the paper's.
    """

    options: Mapping[str, Any]
    costs: tuple[float | None, ...] = ()
    knots: tuple[bool, ...] = ()
    faults: tuple[str | None, ...] = ()
    verdicts: tuple[Mapping[str, Any] | None, ...] = ()
    trials_to_success: int | None = None
    stopped_because: str = ""
    attempts: int = 0
    repeat_classes: tuple[str | None, ...] = ()
    repeat_verdicts: tuple[Mapping[str, Any] | None, ...] = ()
    judge: str = ""
    initial_guess: Mapping[str, Any] = field(default_factory=dict)
    T: float | None = None
    t_c: float | None = None
    wall_s: float = 0.0
    custom_rope: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key in self.options:
            if key not in OPTION_KEYS:
                raise ConfigError(f"options.{key}", "unknown field", OPTION_KEYS)
        if "name" not in self.options:
            raise ConfigError("options.name", "a run summary needs its run's name")
        for name in ("costs", "knots", "faults", "verdicts", "repeat_classes", "repeat_verdicts"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        for name in ("options", "initial_guess", "custom_rope"):
            object.__setattr__(self, name, ReadOnlyMap(getattr(self, name)))

    @property
    def name(self) -> str:
        """The run's name."""
        return str(self.options["name"])

    @property
    def rope(self) -> int | str:
        """The run's rope: a paper rope's id or a custom rope's name."""
        return self.options.get("rope", 1)

    @property
    def seed(self) -> int | None:
        """The run's lab seed (None when the summary does not say)."""
        return self.options.get("seed")

    @property
    def demo(self) -> str:
        """The run's demonstration (a name under ``assets/demos`` or a path)."""
        return str(self.options.get("demo", ""))

    @property
    def start_from(self) -> str | None:
        """The run whose final command started this one, or None."""
        return self.options.get("start_from")

    @property
    def label(self) -> str:
        """The run's label for figures: its ``label`` option, else its name."""
        return str(self.options.get("label") or self.name)

    @property
    def learner(self) -> ILCParams:
        """The run's learning-loop options (:class:`learner.ilc.ILCParams`)."""
        own = set(option_names(ILCParams))
        return from_mapping(ILCParams, {k: v for k, v in self.options.items() if k in own})

    @property
    def confirmed(self) -> bool:
        """The run stopped on a confirmed success."""
        return self.stopped_because == "confirmed"

    @property
    def n_knots_repeated(self) -> int:
        """Repeats of the final command that tied a knot."""
        return sum(r == KNOT for r in self.repeat_classes)

    @property
    def repeat_success_rate(self) -> float | None:
        """Fraction of the repeats that tied a knot, None without repeats."""
        return self.n_knots_repeated / len(self.repeat_classes) if self.repeat_classes else None

    def to_json(self) -> dict[str, Any]:
        """The summary as one flat JSON object (module docstring)."""
        out: dict[str, Any] = _plain(dict(self.options))
        for f in fields(self):
            if f.name != "options":
                out[f.name] = _plain(getattr(self, f.name))
        out.update({"confirmed": self.confirmed, "repeat_success_rate": self.repeat_success_rate})
        return out

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> RunSummary:
        """Read :meth:`to_json`'s object back.

        Raises:
            ConfigError: A key that is neither an option nor a field of the summary.
        """
        own = tuple(f.name for f in fields(cls) if f.name != "options")
        options, outcome = {}, {}
        for key, value in doc.items():
            if key in OPTION_KEYS:
                options[key] = value
            elif key in own:
                outcome[key] = value
            elif key not in DERIVED_KEYS:
                raise ConfigError(f"summary.{key}", "unknown field", (*OPTION_KEYS, *own))
        return cls(options=options, **outcome)


@dataclass(frozen=True)
class ScenarioSummary:
    """Every run of a scenario (``summary.json``)."""

    scenario: str
    kind: str
    runs: tuple[RunSummary, ...]
    paper: str = ""

    def to_json(self) -> dict[str, Any]:
        """The summary as JSON: the scenario's name, kind, the paper's result, every run."""
        head = {"scenario": self.scenario, "kind": self.kind, "paper": self.paper}
        return {**head, "runs": [r.to_json() for r in self.runs]}

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> ScenarioSummary:
        """Read :meth:`to_json`'s object back (a missing ``paper`` is empty)."""
        for key in ("scenario", "kind", "runs"):
            if key not in doc:
                raise ConfigError(f"summary.{key}", "missing: not a scenario's summary.json")
        runs = tuple(RunSummary.from_json(r) for r in doc["runs"])
        return cls(str(doc["scenario"]), str(doc["kind"]), runs, str(doc.get("paper", "")))


def runs_of(runs: Sequence[RunSummary | Mapping[str, Any]]) -> list[RunSummary]:
    """Summaries from summaries or their JSON objects."""
    return [r if isinstance(r, RunSummary) else RunSummary.from_json(r) for r in runs]


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if hasattr(value, "__dataclass_fields__"):
        return _plain(asdict(value))
    return value

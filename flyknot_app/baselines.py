"""Black-box baselines to compare Task-Level ILC with, played through the gym env.

Both search the offset x (80,) of the command's knots from the initial command (the one ILC
starts from), scaled by ``scale`` [rad per unit for joint rows, m per unit for base rows],
made a valid command by :meth:`flyknot_app.gym_env.FlyknotEnv.constrain`, and see only the
env's reward (minus the critical-point cost, plus the knot bonus) and whether the knot tied:

- ``random``: random search around the best offset so far, x = x_best + sigma N(0, I); the
  first trial plays the initial command (x = 0).
- ``cma``: CMA-ES (the ``cma`` package) on the loss -reward from x = 0 with step sigma; the
  first trial plays the mean (the initial command).

A search stops at the first knot (like the paper's ILC) or after ``budget`` trials; its best
command (the knotted one, else the highest reward) is then repeated ``repeats`` times on the
same lab (the success rate). ``flyknot baseline NAME --rope R --budget B --seeds 0-4`` runs
it per seed and writes ``baseline.json`` and ``baseline.md``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, check_positive

BASELINES = ("random", "cma")


@dataclass(frozen=True)
class BaselineParams:
    """How a baseline searches.

    Attributes:
        budget: Trials at most (the initial command's included).
        sigma: Step of the search in offset units.
        scale: Knot change per offset unit [rad] (joint rows) or [m] (base rows).
        repeats: Plays of the best command after the search.
        popsize: CMA-ES population (None: the package's default 4 + 3 ln 80 = 17).
    """

    budget: int = 30
    sigma: float = 0.3
    scale: float = 0.1
    repeats: int = 0
    popsize: int | None = None

    def __post_init__(self) -> None:
        for name in ("budget", "repeats"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (1 if name == "budget" else 0):
                raise ConfigError(name, f"must be an integer >= {int(name == 'budget')}, got {v!r}")
        check_positive("sigma", self.sigma)
        check_positive("scale", self.scale)
        if self.popsize is not None and (not isinstance(self.popsize, int) or self.popsize < 2):
            raise ConfigError("popsize", f"must be an integer >= 2, got {self.popsize!r}")


@dataclass
class BaselineResult:
    """One search: per-trial reward, cost and knot, trials to the first knot, the repeats."""

    name: str
    seed: int
    rewards: list[float] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)
    knots: list[bool] = field(default_factory=list)
    trials_to_success: int | None = None
    repeats: list[str | None] = field(default_factory=list)

    @property
    def success_rate(self) -> float | None:
        """Share of trefoils in the repeats, or None without repeats."""
        if not self.repeats:
            return None
        return sum(r == "trefoil" for r in self.repeats) / len(self.repeats)


class _Search:
    """Plays offsets and keeps the score (shared by both baselines)."""

    def __init__(self, env: Any, params: BaselineParams, result: BaselineResult):
        self.env, self.params, self.result = env, params, result
        self.knots0 = np.array(env.knots)
        self.best_x = np.zeros(self.knots0.size)
        self.best_reward = -np.inf
        self.done = False

    def knots(self, x: np.ndarray) -> np.ndarray:
        return self.knots0 + self.params.scale * np.asarray(x).reshape(self.knots0.shape)

    def play(self, x: np.ndarray) -> float:
        _, reward, tied, _, info = self.env.play(self.knots(x))
        r = self.result
        r.rewards.append(float(reward))
        r.costs.append(float(info["cost"]))
        r.knots.append(bool(tied))
        if tied and r.trials_to_success is None:
            r.trials_to_success = len(r.knots)
            self.done = True
        if tied or reward > self.best_reward:
            self.best_reward, self.best_x = (np.inf if tied else reward), np.array(x)
        if len(r.knots) >= self.params.budget:
            self.done = True
        return float(reward)


def _random(search: _Search, rng: np.random.Generator) -> None:
    search.play(np.zeros_like(search.best_x))
    while not search.done:
        search.play(search.best_x + search.params.sigma * rng.standard_normal(search.best_x.size))


def _cma(search: _Search, rng: np.random.Generator) -> None:
    import cma

    opts = {"seed": int(rng.integers(1, 2**31 - 1)), "verbose": -9}
    if search.params.popsize is not None:
        opts["popsize"] = search.params.popsize
    es = cma.CMAEvolutionStrategy(np.zeros(search.best_x.size), search.params.sigma, opts)
    search.play(es.mean)
    while not search.done:
        xs = es.ask()
        losses = []
        for x in xs:
            if search.done:
                break
            losses.append(-search.play(x))
        if len(losses) < len(xs):
            break
        es.tell(xs, losses)


SEARCHES: dict[str, Callable[[_Search, np.random.Generator], None]] = {
    "random": _random,
    "cma": _cma,
}


def run_baseline(
    name: str, env: Any, params: BaselineParams = BaselineParams(), seed: int = 0
) -> BaselineResult:
    """Search with baseline ``name`` on ``env`` (a :class:`~flyknot_app.gym_env.FlyknotEnv`).

    ``env.reset(seed=seed)`` plays nothing of the search: its one trial (the initial command)
    is not counted; the search's own first trial plays the initial command again.
    """
    if name not in SEARCHES:
        raise ConfigError("baseline", f"unknown baseline {name!r}", BASELINES)
    env.reset(seed=seed)
    result = BaselineResult(name, seed)
    search = _Search(env, params, result)
    SEARCHES[name](search, np.random.default_rng(seed))
    knots = search.knots(search.best_x)
    for _ in range(params.repeats):
        _, _, _, _, info = env.play(knots)
        result.repeats.append("fault" if info["fault"] else info["knot"])
    return result


def write_results(
    out: str | Path, results: Sequence[BaselineResult], params: BaselineParams, rope: int | str
) -> Path:
    """``baseline.json`` and a ``baseline.md`` table of the searches in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "rope": rope,
        "params": asdict(params),
        "runs": [{**asdict(r), "success_rate": r.success_rate} for r in results],
    }
    (out / "baseline.json").write_text(json.dumps(doc, indent=2))
    lines = [
        "| baseline | seed | trials until knot | best cost | repeats tied |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        ttk = r.trials_to_success if r.trials_to_success is not None else f">{len(r.knots)}"
        rep = f"{sum(x == 'trefoil' for x in r.repeats)}/{len(r.repeats)}" if r.repeats else "-"
        lines.append(f"| {r.name} | {r.seed} | {ttk} | {min(r.costs):.3g} | {rep} |")
    path = out / "baseline.md"
    path.write_text("\n".join(lines) + "\n")
    return path

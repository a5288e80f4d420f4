"""Baselines to compare Task-Level ILC with, played through the gym envs.

The black-box searches ``random`` and ``cma`` play whole commands through
:class:`flyknot_app.gym.env.FlyknotEnv`. Both search the offset x (80,) of the command's
knots from the initial command (the one ILC starts from), scaled by ``scale`` [rad per unit
for joint rows, m per unit for base rows], made a valid command by
:meth:`flyknot_app.gym.env.FlyknotEnv.constrain`, and see only the env's reward (minus the
critical-point cost, plus the knot bonus) and whether the knot tied:

- ``random``: random search around the best offset so far, x = x_best + sigma N(0, I); the
  first trial plays the initial command (x = 0).
- ``cma``: CMA-ES (the ``cma`` package) on the loss -reward from x = 0 with step sigma; the
  first trial plays the mean (the initial command).

``ppo`` (the ``rl`` extra: stable-baselines3 and torch) trains PPO on the tick-level env
:class:`flyknot_app.gym.tick_env.FlyknotTickEnv`, one episode per trial: a Gaussian policy
with state-dependent exploration (gSDE, its noise matrix drawn anew for every episode: the
smooth exploration a 250 Hz arm needs, see the env's docstring) from the initial command (a
zero action replays it); reward, cost and knot are the env's (:class:`PPOParams`).

A baseline stops at the first knot (like the paper's ILC) or after ``budget`` trials; its
best command (the knotted one, else the highest reward; for PPO the actions of that episode,
replayed open loop) is then repeated ``repeats`` times on the same lab: the success rate
after the budget. ``flyknot baseline NAME --rope R --budget B --seeds 0-4 [--repeats N]``
runs it per seed and writes ``baseline.json`` and ``baseline.md`` (the success rates with
95 % Wilson intervals).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, check_positive
from flyknot.verdict import JUDGE_NAME, KNOT
from flyknot_app.learner_settings import SCENARIO_DEMO, scenario_weights

BASELINES = ("random", "cma", "ppo")
RL_HINT = (
    "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu (the CPU "
    "wheel first), then pip install -e '.[rl]'"
)
"""How to install the ``rl`` extra (a plain ``torch`` from PyPI is a multi-GB CUDA build)."""


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
        """Share of knots in the hanging rope (verdict ``knot``) in the repeats, or None."""
        if not self.repeats:
            return None
        return sum(r == KNOT for r in self.repeats) / len(self.repeats)


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


@dataclass(frozen=True)
class PPOParams:
    """PPO's settings (stable-baselines3's names) for the tick-level env.

    Attributes:
        episodes_per_update: Rollout length in episodes (``n_steps`` = this times the
            command's ticks, rounded up to a multiple of 4; 4 minibatches per epoch).
        n_epochs: Passes over a rollout per update.
        learning_rate: Adam's step.
        gamma: Discount (1: the only reward comes at the episode's end).
        gae_lambda: GAE's lambda.
        log_std_init: Initial log std of the gSDE noise weights.
    """

    episodes_per_update: int = 2
    n_epochs: int = 10
    learning_rate: float = 3e-4
    gamma: float = 1.0
    gae_lambda: float = 0.95
    log_std_init: float = -1.0

    def __post_init__(self) -> None:
        for name in ("episodes_per_update", "n_epochs"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(name, f"must be an integer >= 1, got {v!r}")
        check_positive("learning_rate", self.learning_rate)
        for name in ("gamma", "gae_lambda"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v <= 1):
                raise ConfigError(name, f"must lie in (0, 1], got {v!r}")
        if not (isinstance(self.log_std_init, (int, float)) and np.isfinite(self.log_std_init)):
            raise ConfigError("log_std_init", f"must be a finite number, got {self.log_std_init!r}")


def require_rl() -> None:
    """Raise :class:`ConfigError` (with how to install it) unless the ``rl`` extra is there."""
    import importlib.util

    missing = [m for m in ("torch", "stable_baselines3") if importlib.util.find_spec(m) is None]
    if missing:
        raise ConfigError(
            "baseline", f"ppo needs the rl extra ({', '.join(missing)} missing): {RL_HINT}"
        )


def run_ppo(
    env: Any, params: BaselineParams = BaselineParams(), seed: int = 0, ppo: PPOParams = PPOParams()
) -> BaselineResult:
    """Train PPO on ``env`` (a :class:`~flyknot_app.gym.tick_env.FlyknotTickEnv`) until its
    first knot or ``params.budget`` episodes, then replay the best episode's actions
    ``params.repeats`` times. The lab's variation starts at trial 0 of ``seed``; the policy's
    initial weights and noise come from ``seed`` too. Torch runs on one CPU thread.

    Raises:
        ConfigError: The ``rl`` extra is not installed.
    """
    require_rl()
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    result = BaselineResult("ppo", seed)
    episodes: list[tuple[float, bool, np.ndarray]] = []

    class _Trials(BaseCallback):
        """Books every finished episode as a trial; stops at the first knot or the budget."""

        def _on_step(self) -> bool:
            go = True
            loc = self.locals
            for done, info, reward in zip(loc["dones"], loc["infos"], loc["rewards"], strict=True):
                if not done:
                    continue
                tied = bool(info["success"])
                result.rewards.append(float(reward))
                result.costs.append(float(info["cost"]))
                result.knots.append(tied)
                episodes.append((float(reward), tied, np.array(info["actions"])))
                if tied and result.trials_to_success is None:
                    result.trials_to_success = len(result.knots)
                go = go and not tied and len(result.knots) < params.budget
                self.model.policy.reset_noise(1)  # a new exploration for the next episode
            return go

    n_steps = 4 * -(-ppo.episodes_per_update * env.n_ticks // 4)
    model = PPO(
        "MlpPolicy",
        env,
        n_steps=n_steps,
        batch_size=n_steps // 4,
        n_epochs=ppo.n_epochs,
        learning_rate=ppo.learning_rate,
        gamma=ppo.gamma,
        gae_lambda=ppo.gae_lambda,
        use_sde=True,
        policy_kwargs={"log_std_init": ppo.log_std_init},
        seed=seed,
        device="cpu",
        verbose=0,
    )
    model.learn(total_timesteps=(params.budget + 1) * env.n_ticks + n_steps, callback=_Trials())
    if episodes and params.repeats:
        best = max(range(len(episodes)), key=lambda i: (episodes[i][1], episodes[i][0]))
        actions = episodes[best][2]
        for _ in range(params.repeats):
            env.reset()
            for a in actions:
                *_, terminated, _, info = env.step(a)
                if terminated:
                    break
            result.repeats.append("fault" if info["fault"] else info["verdict"])
    return result


def run_baseline(
    name: str, env: Any, params: BaselineParams = BaselineParams(), seed: int = 0
) -> BaselineResult:
    """Search with baseline ``name`` on ``env`` (a :class:`~flyknot_app.gym.env.FlyknotEnv`;
    for ``ppo`` a :class:`~flyknot_app.gym.tick_env.FlyknotTickEnv`, see :func:`run_ppo`).

    ``env.reset(seed=seed)`` plays nothing of the search: its one trial (the initial command)
    is not counted, and the lab is rewound (``env.restart_variation()``), so the search's
    trial i (from 1) meets the lab's trial i - 1 of ``seed``, as ILC's trial i does in
    ``flyknot run`` and PPO's episode i does: paired comparisons. The search's own first
    trial plays the initial command again.
    """
    if name not in BASELINES:
        raise ConfigError("baseline", f"unknown baseline {name!r}", BASELINES)
    if name == "ppo":
        return run_ppo(env, params, seed)
    env.reset(seed=seed)
    env.restart_variation()
    result = BaselineResult(name, seed)
    search = _Search(env, params, result)
    SEARCHES[name](search, np.random.default_rng(seed))
    knots = search.knots(search.best_x)
    for _ in range(params.repeats):
        _, _, _, _, info = env.play(knots)
        result.repeats.append("fault" if info["fault"] else info["verdict"])
    return result


def search_seeds(
    name: str,
    seeds: Sequence[int],
    params: BaselineParams = BaselineParams(),
    *,
    rope: int | str = 1,
    demo: str = SCENARIO_DEMO,
    settle_s: float | None = None,
    progress: bool = False,
) -> tuple[list[BaselineResult], dict[str, Any]]:
    """:func:`run_baseline` ``name`` once per lab seed from ``demo``'s initial command on
    ``rope``, scored with the scenarios' critical weights (the env's default); the results
    and the settings :func:`write_results` records (the env's)."""
    from tqdm import tqdm

    from flyknot.progress import bar_disable
    from flyknot_app.scenario import check_demo

    if name not in BASELINES:
        raise ConfigError("baseline", f"unknown baseline {name!r}", BASELINES)
    check_demo(demo)  # before the initial guess is computed
    settings: dict[str, Any] = {"demo": demo, "weights": asdict(scenario_weights())}
    if name == "ppo":
        from flyknot_app.gym.tick_env import FlyknotTickEnv

        require_rl()  # before the initial guess is computed
        env = FlyknotTickEnv(rope=rope, demo=demo, settle_s=settle_s)
        settings |= {
            "env": "flyknot/FlyingKnotTick-v0",
            "action_scale": env.action_scale,
            "smoothing_s": env.smoothing_s,
            "ppo": asdict(PPOParams()),
        }
    else:
        from flyknot_app.gym.env import FlyknotEnv

        n = params.budget + params.repeats + 1
        env = FlyknotEnv(rope=rope, demo=demo, max_trials=n, settle_s=settle_s)
    bar = tqdm(seeds, desc=name, unit="seed", disable=bar_disable(progress))
    return [run_baseline(name, env, params, seed) for seed in bar], settings


def write_results(
    out: str | Path,
    results: Sequence[BaselineResult],
    params: BaselineParams,
    rope: int | str,
    settings: dict[str, Any] | None = None,
) -> Path:
    """``baseline.json`` and ``baseline.md`` of the searches in ``out``: per seed the trials
    until the first knot, the best cost and the knots in the repeats with a 95 % Wilson
    interval; below, the mean trials until the first knot (a seed without a knot counted as
    its trials + 1: then a lower bound, >=) and the repeats pooled over the seeds (the success
    rate after the budget). ``settings``: more to record in the JSON (e.g. the env's)."""
    from flyknot_app.reports.report import wilson_interval

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "rope": rope,
        "params": asdict(params),
        **({"settings": settings} if settings else {}),
        "runs": [
            {**asdict(r), "success_rate": r.success_rate, "judge": JUDGE_NAME} for r in results
        ],
    }
    (out / "baseline.json").write_text(json.dumps(doc, indent=2))
    lines = [
        "| baseline | seed | trials until knot | best cost | repeats tied (95 % CI) |",
        "|---|---|---|---|---|",
    ]

    def tied(reps: Sequence[str | None]) -> str:
        if not reps:
            return "-"
        k = sum(x == KNOT for x in reps)
        lo, hi = wilson_interval(k, len(reps))
        return f"{k}/{len(reps)} ({lo:.0%}-{hi:.0%})"

    for r in results:
        ttk = r.trials_to_success if r.trials_to_success is not None else f">{len(r.knots)}"
        lines.append(f"| {r.name} | {r.seed} | {ttk} | {min(r.costs):.3g} | {tied(r.repeats)} |")
    if results:
        trials = [r.trials_to_success or len(r.knots) + 1 for r in results]
        bound = ">=" if any(r.trials_to_success is None for r in results) else ""
        n_tied = sum(r.trials_to_success is not None for r in results)
        lines += [
            "",
            f"Knot within the budget of {params.budget}: {n_tied} of {len(results)} seeds; "
            f"mean trials until the first knot: {bound}{np.mean(trials):.3g}.",
        ]
        pooled = [x for r in results for x in r.repeats]
        if pooled:
            lines.append(f"Success after the budget (repeats, pooled): {tied(pooled)}.")
    path = out / "baseline.md"
    path.write_text("\n".join(lines) + "\n")
    return path

"""A robot command that ties in most varied trials, searched from one that ties.

The command of a robot demonstration (:mod:`flyknot_tools.robot_demo`) is found on the lab
without variation and kept for its rate in a few varied trials; :func:`rate_search` then
maximises the rate itself (``flyknot-tools demo robot-rate``): CMA-ES over the same decision
vector, each candidate scored by the mean :func:`~flyknot_tools.robot_demo.command_score` of
``trials`` varied trials, every candidate of a generation on the same fresh lab seeds, the
result judged on check seeds the search never played (``docs/learning.md``).
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, check_int, check_positive
from flyknot.limits import JointLimits
from flyknot.progress import bar_disable
from flyknot_tools.robot_demo import N_DECISION, CommandCoding, CommandSpace, command_score

__all__ = ["RateSearchConfig", "RateSearchResult", "rate_search"]


@dataclass(frozen=True)
class RateSearchConfig:
    """Settings of :func:`rate_search`.

    Attributes:
        rope: Rope id of the lab.
        generations: CMA-ES generations.
        popsize: Candidates per generation.
        trials: Varied trials per candidate; every candidate of a generation plays the same
            lab seeds, and each generation draws fresh ones (so the search cannot fit a
            fixed handful of ropes).
        sigma: CMA-ES initial step [normalised units of ``space``].
        space: How the decision vector moves the command.
        frame_s: Spacing of the judged truth frames [s].
        seed_base: Lab seed of the search's first trial (generation g, trial k plays
            ``seed_base + g * trials + k``); keep it clear of the check's seeds.
        check_seeds: Lab seeds (lo, hi), hi exclusive, that measure the start command and the
            result after the search, unseen by it.
    """

    rope: int = 1
    generations: int = 24
    popsize: int = 8
    trials: int = 8
    sigma: float = 0.2
    space: CommandSpace = field(default_factory=CommandSpace)
    frame_s: float = 0.05
    seed_base: int = 1000
    check_seeds: tuple[int, int] = (10, 50)

    def __post_init__(self) -> None:
        for f in ("generations", "trials", "seed_base"):
            check_int(f, getattr(self, f), 1)
        check_int("popsize", self.popsize, 2)
        for f in ("sigma", "frame_s"):
            check_positive(f, getattr(self, f))
        lo, hi = (int(v) for v in self.check_seeds)
        if not 0 <= lo < hi:
            raise ConfigError("check_seeds", f"need 0 <= lo < hi, got {self.check_seeds}")
        search = range(self.seed_base, self.seed_base + self.generations * self.trials)
        if lo < search.stop and search.start < hi:
            raise ConfigError(
                "seed_base",
                f"the search's seeds {search.start}..{search.stop - 1} overlap the check's "
                f"{lo}..{hi - 1}",
            )
        object.__setattr__(self, "check_seeds", (lo, hi))


@dataclass(frozen=True)
class RateSearchResult:
    """Outcome of :func:`rate_search`.

    Attributes:
        knots: The result's knots (10, 8): CMA-ES's mean, or the start if no mean beat it.
        T: Its duration [s].
        start_ties: The start command's knots on the check seeds.
        ties: The result's knots on the check seeds.
        n_check: Check trials.
        history: Per generation: (mean score, best candidate's tie fraction, mean tie
            fraction) over its candidates, shape (generations, 3).
        simulated: Trials simulated by the search (check trials not counted).
        wall_s: Wall time [s].
    """

    knots: np.ndarray
    T: float
    start_ties: int
    ties: int
    n_check: int
    history: np.ndarray = field(repr=False)
    simulated: int = 0
    wall_s: float = 0.0

    def summary(self, timing: bool = True) -> dict[str, Any]:
        """Plain data (without the knots); ``timing`` adds the wall time."""
        out = {
            "T": round(self.T, 4),
            "start_ties": self.start_ties,
            "ties": self.ties,
            "n_check": self.n_check,
            "generations": int(self.history.shape[0]),
            "simulated": self.simulated,
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def _varied_trial(job: tuple[np.ndarray, float, int, int, float]) -> tuple[float, bool]:
    """(score, tied) of a command's trial in the varied lab of one seed (a worker's job)."""
    from flyknot_sim.lab import LabParams, SimLab
    from learner.bezier import BezierCommand

    knots, T, rope, seed, frame_s = job
    rec = SimLab(LabParams(rope=rope, seed=seed)).run(BezierCommand(knots, T).joint_command())
    return command_score(rec, T, frame_s), bool(rec.succeeded)


def _play_generation(
    pool, cands: list, limit: list, seeds: range, config: RateSearchConfig
) -> tuple[list[float], list[float], int]:
    """Scores and tie fractions of one generation's candidates (a candidate outside the limits
    keeps its limit score and ties nothing) and the number of trials played."""
    jobs = [
        (k, T, config.rope, s, config.frame_s)
        for (k, T), v in zip(cands, limit, strict=True)
        if v is None
        for s in seeds
    ]
    results = iter(pool.map(_varied_trial, jobs))
    scores, rates = [], []
    for v in limit:
        if v is not None:
            scores.append(v)
            rates.append(0.0)
            continue
        played = [next(results) for _ in seeds]
        scores.append(float(np.mean([s for s, _ in played])))
        rates.append(float(np.mean([t for _, t in played])))
    return scores, rates, len(jobs)


def rate_search(
    start_knots: np.ndarray,
    T0: float,
    config: RateSearchConfig = RateSearchConfig(),
    *,
    seed: int = 0,
    workers: int = 1,
    progress: bool = False,
) -> RateSearchResult:
    """CMA-ES for a command that ties the knot in most varied trials, from a tying command.

    Maximises the mean :func:`command_score` over ``trials`` varied trials (the tie term,
    100 per knot, dominates, so this is the tie rate with the near-miss shaping breaking ties)
    with the decision vector of :func:`search_command`; a candidate that breaks a limit scores
    as there, without being simulated. The result is CMA-ES's final mean (the distribution's
    centre, not the luckiest sample), kept only if it ties more check trials than the start.
    """
    import cma
    from tqdm import tqdm

    from learner.kinematics import RobotModel

    check_int("seed", seed, 0)
    check_int("workers", workers, 1)
    tic = time.perf_counter()
    coding = CommandCoding(np.asarray(start_knots, dtype=float), T0, config.space)
    robot, limits = RobotModel.from_mjcf(), JointLimits()

    n_check = config.check_seeds[1] - config.check_seeds[0]
    bar = tqdm(
        total=config.generations + 2 * n_check,
        desc="robot demo rate",
        disable=bar_disable(progress),
    )
    history, simulated = [], 0
    with ProcessPoolExecutor(max_workers=workers) as pool:

        def ties_on_check(knots: np.ndarray, T: float) -> int:
            jobs = [(knots, T, config.rope, s, config.frame_s) for s in range(*config.check_seeds)]
            out = list(pool.map(_varied_trial, jobs))
            bar.update(len(jobs))
            return sum(t for _, t in out)

        start_ties = ties_on_check(np.asarray(start_knots, dtype=float), float(T0))
        es = cma.CMAEvolutionStrategy(
            np.zeros(N_DECISION),
            config.sigma,
            {"seed": seed + 1, "verbose": -9, "popsize": config.popsize},
        )
        for g in range(config.generations):
            ys = [np.asarray(y) for y in es.ask()]
            seeds = range(
                config.seed_base + g * config.trials, config.seed_base + (g + 1) * config.trials
            )
            cands = [coding.decode(y) for y in ys]
            limit = [coding.limit_score(k, T, robot, limits) for k, T in cands]
            scores, rates, n = _play_generation(pool, cands, limit, seeds, config)
            simulated += n
            es.tell(ys, [-s for s in scores])
            history.append((float(np.mean(scores)), max(rates), float(np.mean(rates))))
            bar.update(1)
            bar.set_postfix(best=f"{max(rates):.2f}", mean=f"{np.mean(rates):.2f}")
        knots, T = coding.decode(np.asarray(es.result.xfavorite))
        inside = coding.limit_score(knots, T, robot, limits) is None
        ties = ties_on_check(knots, T) if inside else -1
    bar.close()
    if ties <= start_ties:
        knots, T, ties = np.asarray(start_knots, dtype=float), float(T0), start_ties
    return RateSearchResult(
        knots=knots,
        T=T,
        start_ties=start_ties,
        ties=ties,
        n_check=n_check,
        history=np.array(history).reshape(-1, 3),
        simulated=simulated,
        wall_s=time.perf_counter() - tic,
    )

"""CMA-ES search of the motion family for a robust flying knot, and its evaluation.

A motion is scored (:mod:`flyknot_tools.hand_demos.score`) on simulated trials of the hand
lab (:mod:`flyknot_sim.hand`) under the lab's trial-to-trial variation; :func:`search` runs
CMA-ES inside a variant's box (:mod:`flyknot_tools.hand_demos.variants`) and confirms
the candidates that tie. How it works: ``docs/demo-synthesis.md``; the shipped
demonstrations' searches (trials, minutes, varied checks): ``assets/demos/README.md``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, check_positive
from flyknot_sim.hand import HandLab, HandTrial
from flyknot_sim.hand_motion import N_PARAMS, KnotMotion
from flyknot_sim.hand_params import HandParams
from flyknot_tools.hand_demos.score import (
    ScoreWeights,
    TrialSummary,
    limit_penalty,
    score,
    writhe,
)
from flyknot_tools.hand_demos.variants import PARAM_SCALE, Variant, get_variant, param_bounds


# ----------------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------------
def motion_summary(motion: KnotMotion, variant: Variant) -> TrialSummary:
    """The limit terms of a motion alone (``simulated`` False): peak speed, excursion and
    the variant's violation."""
    speed, excursion = motion.hand_limits()
    return TrialSummary(
        peak_speed=speed,
        excursion=excursion,
        violation=variant.violation(motion),
        simulated=False,
    )


def trial_summary(trial: HandTrial, limits: TrialSummary) -> TrialSummary:
    """Summary of a simulated trial (limit terms copied from ``limits``)."""
    if trial.diverged:
        return replace(limits, simulated=True)
    wr = max((abs(writhe(trial.vertices[k])) for k in trial.judged), default=0.0)
    return replace(
        limits,
        tied=trial.tied,
        settle_fraction=trial.settle_fraction,
        knot_any=trial.knot_any,
        contact=trial.first_contact is not None,
        writhe=wr,
        simulated=True,
    )


def within_limits(limits: TrialSummary) -> bool:
    """No speed, excursion or variant violation (the motion is worth simulating)."""
    return limit_penalty(limits) == 0.0


@dataclass(frozen=True)
class Evaluation:
    """Trials of one motion.

    Attributes:
        motion: The motion.
        summaries: One per trial (a single rejected one if the limits are broken).
        scores: :func:`score` of each summary.
    """

    motion: KnotMotion
    summaries: tuple[TrialSummary, ...]
    scores: tuple[float, ...]

    @property
    def mean_score(self) -> float:
        """Mean score over the trials."""
        return float(np.mean(self.scores))

    @property
    def ties(self) -> int:
        """Trials that ended with a knot."""
        return sum(s.tied for s in self.summaries)

    @property
    def rate(self) -> float:
        """Fraction of trials that ended with a knot."""
        return self.ties / len(self.summaries)


def evaluate(
    lab: HandLab,
    motion: KnotMotion,
    variant: Variant,
    variations: Sequence[Mapping[str, Any]],
    weights: ScoreWeights = ScoreWeights(),  # noqa: B008 (a frozen dataclass)
    *,
    max_failures: int | None = None,
) -> Evaluation:
    """Score ``motion`` once per variation (:meth:`HandLab.draw_variation` dicts); a motion
    that breaks the limits is scored once without simulation. With ``max_failures``, stop
    after the trial that makes the untied trials exceed it (the rest are not played)."""
    limits = motion_summary(motion, variant)
    if not within_limits(limits):
        return Evaluation(motion, (limits,), (score(limits, weights),))
    sums: list[TrialSummary] = []
    for v in variations:
        sums.append(trial_summary(lab.run(motion, variation=v), limits))
        if max_failures is not None and sum(not s.tied for s in sums) > max_failures:
            break
    return Evaluation(motion, tuple(sums), tuple(score(s, weights) for s in sums))


# ----------------------------------------------------------------------------------------
# search
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SearchConfig:
    """Budget and settings of :func:`search`.

    Attributes:
        budget: Most simulated trials in total (exploration + confirmation + refinement).
        sigma0: CMA-ES initial step in normalised units (:data:`PARAM_SCALE`).
        popsize: CMA-ES population (0: CMA's default 4 + 3 ln 21 = 13).
        confirm_trials: Trials that confirm a candidate: the nominal one plus
            ``confirm_trials - 1`` varied ones (the same variations for every candidate).
        target_rate: The search stops at the first candidate whose nominal trial ties and
            whose confirmation rate reaches this.
        refine_after: Trials after which, if some candidate was confirmed with a rate below
            the target, CMA-ES restarts around the best one with ``refine_sigma`` and
            ``refine_repeats`` varied trials per candidate (mean score).
        refine_sigma: Step of the refinement [normalised units].
        refine_repeats: Trials per candidate in the refinement.
        confirm_abort: Stop a confirmation as soon as ``target_rate`` is out of reach (a
            knotted trial lasts until the rope rests, up to 15 s simulated, so a full
            confirmation of a weak candidate is the search's largest cost); the candidate's
            rate is then ties / ``confirm_trials``, the unplayed trials counted as untied.
        hand: Hand-lab settings (rope, settling time, variation).
    """

    budget: int = 900
    sigma0: float = 0.3
    popsize: int = 0
    confirm_trials: int = 20
    target_rate: float = 0.8
    refine_after: int = 400
    refine_sigma: float = 0.1
    refine_repeats: int = 2
    confirm_abort: bool = False
    hand: HandParams = field(default_factory=HandParams)

    def __post_init__(self) -> None:
        for f in ("budget", "confirm_trials", "refine_after", "refine_repeats"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"SearchConfig.{f}", f"must be an integer >= 1, got {v!r}")
        if isinstance(self.popsize, bool) or not isinstance(self.popsize, int) or self.popsize < 0:
            raise ConfigError(
                "SearchConfig.popsize", f"must be an integer >= 0, got {self.popsize!r}"
            )
        check_positive("SearchConfig.sigma0", self.sigma0)
        check_positive("SearchConfig.refine_sigma", self.refine_sigma)
        if not 0.0 < self.target_rate <= 1.0:
            raise ConfigError(
                "SearchConfig.target_rate", f"must lie in (0, 1], got {self.target_rate!r}"
            )
        if not isinstance(self.confirm_abort, bool):
            raise ConfigError(
                "SearchConfig.confirm_abort", f"must be true or false, got {self.confirm_abort!r}"
            )

    @property
    def confirm_failures(self) -> int | None:
        """Most untied confirmation trials that still reach ``target_rate`` (None: no abort)."""
        if not self.confirm_abort:
            return None
        return math.floor((1.0 - self.target_rate) * self.confirm_trials + 1e-9)


@dataclass(frozen=True)
class Candidate:
    """A confirmed candidate.

    Attributes:
        motion: The motion.
        trial: Trial count at which it was found.
        rate: Knot rate over the confirmation trials.
        nominal_tied: Its nominal (unvaried) trial tied.
        mean_score: Mean score over the confirmation trials.
    """

    motion: KnotMotion
    trial: int
    rate: float
    nominal_tied: bool
    mean_score: float

    def key(self) -> tuple[bool, float, float]:
        """Ordering: nominal trial tied, then rate, then mean score."""
        return (self.nominal_tied, self.rate, self.mean_score)


@dataclass(frozen=True)
class SearchResult:
    """Outcome of :func:`search`.

    Attributes:
        variant: Variant name.
        seed: Search seed.
        best: Best confirmed candidate, or None if nothing tied.
        trials: Simulated trials used.
        evaluations: Candidate motions evaluated by CMA-ES.
        first_tie: Trial count at the first knotted trial, or None.
        ties: Knotted trials among the CMA-ES evaluations.
        candidates: Every confirmed candidate, in order.
        history: Per CMA-ES evaluation: (trial count, mean score, ties), shape (E, 3).
        wall_s: Wall time [s].
        stopped: Why the search stopped (``target``, ``budget``).
    """

    variant: str
    seed: int
    best: Candidate | None
    trials: int
    evaluations: int
    first_tie: int | None
    ties: int
    candidates: tuple[Candidate, ...]
    history: np.ndarray
    wall_s: float
    stopped: str

    def to_dict(self, timing: bool = True) -> dict[str, Any]:
        """Plain-data summary (for metadata and reports); ``timing`` adds the wall time
        (left out of saved demonstrations so that a rerun writes the same file)."""
        out = {
            "variant": self.variant,
            "seed": self.seed,
            "trials": self.trials,
            "evaluations": self.evaluations,
            "first_tie": self.first_tie,
            "ties": self.ties,
            "confirmed": len(self.candidates),
            "best_rate": None if self.best is None else self.best.rate,
            "best_nominal_tied": None if self.best is None else self.best.nominal_tied,
            "best_found_at": None if self.best is None else self.best.trial,
            "stopped": self.stopped,
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def variations(lab: HandLab, seed: Sequence[int], n: int, *, nominal_first: bool) -> list[dict]:
    """``n`` trial variations from ``np.random.default_rng(seed)``; the first one nominal if
    ``nominal_first``."""
    rng = np.random.default_rng(list(seed))
    out = [lab.draw_variation(rng) for _ in range(n)]
    if nominal_first and n:
        out[0] = HandLab.nominal_variation()
    return out


def _stream_seed(seed: int, stream: int, what: int) -> int:
    """A CMA-ES seed (>= 1) derived from (seed, stream, what)."""
    return int(np.random.default_rng([seed, stream, what]).integers(1, 2**31 - 1))


def search(
    variant: str | Variant,
    seed: int,
    config: SearchConfig = SearchConfig(),
    *,
    start: KnotMotion | None = None,
    stream: int = 0,
    lab: HandLab | None = None,
    bar: Any = None,
    weights: ScoreWeights = ScoreWeights(),  # noqa: B008 (a frozen dataclass)
) -> SearchResult:
    """CMA-ES over the family for a robust flying knot (see ``docs/demo-synthesis.md``).

    CMA-ES (package ``cma``) runs in normalised coordinates z = (x - x_start) / scale
    (:data:`PARAM_SCALE`) inside the variant's box (:func:`param_bounds`), maximising the
    :func:`score` of one varied trial per candidate (every candidate of a generation sees
    the same variation). A candidate whose trial ties is confirmed on ``confirm_trials``
    trials (nominal first, then fixed variations). The search stops at the first candidate
    whose nominal trial ties with a confirmation rate >= ``target_rate``, or when the trial
    budget is spent. After ``refine_after`` trials with only weaker confirmed candidates,
    CMA-ES restarts around the best of them with a smaller step, scoring each candidate by
    its mean over ``refine_repeats`` varied trials.

    Args:
        variant: Variant or its name.
        seed: Seed of CMA-ES and of the trial variations.
        config: Budget and settings.
        start: Start motion (default: the variant's seed motion).
        stream: Sub-stream of the seed (the stages of
            :func:`~flyknot_tools.hand_demos.synthesis.synthesize_motion` use 0, 1, ...).
        lab: Hand lab to use (default: a new one from ``config.hand``).
        bar: A tqdm bar to advance by simulated trials (None: none).
        weights: Score weights.

    Returns:
        The result; ``best`` is None if nothing tied.
    """
    v = get_variant(variant) if isinstance(variant, str) else variant
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", f"must be an integer >= 0, got {seed!r}")
    tic = time.perf_counter()
    lab = HandLab(config.hand) if lab is None else lab
    lo, hi = param_bounds(v)
    x_start = np.clip((v.seed_motion() if start is None else start).x, lo, hi)
    confirm_set = variations(lab, (seed, stream, 1), config.confirm_trials, nominal_first=True)
    run = _Search(lab, v, config, weights, confirm_set, bar)
    stopped = "budget"
    es, center = _strategy(x_start, config.sigma0, (lo, hi), (seed, stream, 3), config.popsize)
    repeats, generation, refined = 1, 0, False
    while run.trials < config.budget and stopped == "budget":
        if not refined and run.best is not None and run.trials >= config.refine_after:
            es, center = _strategy(
                run.best.motion.x, config.refine_sigma, (lo, hi), (seed, stream, 4), config.popsize
            )
            repeats, refined = config.refine_repeats, True
        zs = es.ask()
        gen_vars = variations(lab, (seed, stream, 2, generation), repeats, nominal_first=False)
        generation += 1
        motions = [KnotMotion(np.clip(center + PARAM_SCALE * np.asarray(z), lo, hi)) for z in zs]
        fitness, stopped = run.generation(motions, gen_vars)
        if stopped == "budget" and len(fitness) == len(zs):
            es.tell(zs, fitness)
    return SearchResult(
        variant=v.name,
        seed=seed,
        best=run.best,
        trials=run.trials,
        evaluations=run.evals,
        first_tie=run.first_tie,
        ties=run.ties,
        candidates=tuple(run.candidates),
        history=np.array(run.history, dtype=float).reshape(-1, 3),
        wall_s=time.perf_counter() - tic,
        stopped=stopped,
    )


def _strategy(
    center: np.ndarray,
    sigma: float,
    box: tuple[np.ndarray, np.ndarray],
    stream: tuple[int, int, int],
    popsize: int | None,
) -> tuple[Any, np.ndarray]:
    """A CMA-ES in z = (x - center) / scale with step ``sigma``, bounded by the box, seeded
    from the (seed, stream, stage) ``stream``; and its center."""
    import cma

    lo, hi = box
    opts = {
        "bounds": [((lo - center) / PARAM_SCALE).tolist(), ((hi - center) / PARAM_SCALE).tolist()],
        "seed": _stream_seed(*stream),
        "verbose": -9,
    }
    if popsize:
        opts["popsize"] = popsize
    return cma.CMAEvolutionStrategy(np.zeros(N_PARAMS), sigma, opts), center


@dataclass
class _Search:
    """A search's bookkeeping: trials spent, ties, candidates and the best of them."""

    lab: HandLab
    variant: Variant
    config: SearchConfig
    weights: ScoreWeights
    confirm_set: Sequence[Mapping[str, Any]]
    bar: Any
    trials: int = 0
    ties: int = 0
    first_tie: int | None = None
    evals: int = 0
    history: list[tuple[int, float, int]] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    best: Candidate | None = None

    def spend(self, n: int) -> None:
        """Count ``n`` simulated trials."""
        self.trials += n
        if self.bar is not None:
            self.bar.update(n)

    def generation(
        self, motions: Sequence[KnotMotion], gen_vars: Sequence[Mapping[str, Any]]
    ) -> tuple[list[float], str]:
        """Score a generation's motions on its variations (a motion that ties confirmed);
        the fitness of each motion scored (CMA-ES minimises: minus the mean score) and
        ``"target"`` when a candidate reached the target (the generation stops there), else
        ``"budget"`` (also when the budget ran out mid-generation)."""
        fitness = []
        for motion in motions:
            ev = evaluate(self.lab, motion, self.variant, gen_vars, self.weights)
            self.evals += 1
            self.spend(sum(sm.simulated for sm in ev.summaries))
            fitness.append(-ev.mean_score)
            self.history.append((self.trials, ev.mean_score, ev.ties))
            if ev.ties and self._confirmed(motion, ev.ties):
                return fitness, "target"
            if self.bar is not None:
                self.bar.set_postfix(
                    stage=self.variant.name.split("/")[-1],
                    ties=self.ties,
                    best="-" if self.best is None else f"{self.best.rate:.1f}",
                )
            if self.trials >= self.config.budget:
                break
        return fitness, "budget"

    def _confirmed(self, motion: KnotMotion, ties: int) -> bool:
        """Confirm a motion that tied on the confirmation set and keep it as a candidate;
        whether its nominal trial ties at the target rate."""
        self.ties += ties
        if self.first_tie is None:
            self.first_tie = self.trials
        cfg = self.config
        conf = evaluate(
            self.lab, motion, self.variant, self.confirm_set, self.weights,
            max_failures=cfg.confirm_failures,
        )  # fmt: skip
        self.spend(len(conf.summaries))
        cand = Candidate(
            motion=motion,
            trial=self.trials,
            rate=conf.ties / cfg.confirm_trials,
            nominal_tied=conf.summaries[0].tied,
            mean_score=conf.mean_score,
        )
        self.candidates.append(cand)
        if self.best is None or cand.key() > self.best.key():
            self.best = cand
        return cand.nominal_tied and cand.rate >= cfg.target_rate

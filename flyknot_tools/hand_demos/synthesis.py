"""Synthesis of a hand demonstration: staged search, recording, check.

:func:`synthesize_motion` searches a variant's motion in stages (a throw, then a slow
wind-up), :func:`make_demonstration` records its nominal trial as the motion capture would
and :func:`synthesize` does both and checks the saved demonstration with varied replays
(:func:`flyknot_sim.hand_replay.replay`). Command line: ``flyknot-tools demo synthesize``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, check_positive
from flyknot.progress import bar_disable
from flyknot_sim.hand import HandLab, HandTrial, trial_demonstration
from flyknot_sim.hand_motion import WINDUP_SPEED_MIN, KnotMotion
from flyknot_sim.hand_params import HandParams, HandVariation
from flyknot_sim.hand_replay import ReplayResult, hand_metadata, replay
from flyknot_sim.mocap import MocapParams
from flyknot_tools.hand_demos.search import SearchConfig, SearchResult, evaluate, search, variations
from flyknot_tools.hand_demos.variants import PACE_FIELDS, THROW_WINDOW, Variant, get_variant

GENERATOR = "flyknot_tools.hand_demos"
"""The ``generator`` in a synthesized demonstration's metadata: this tool."""
GENERATOR_VERSION = 1
"""Bump when a change alters what a given (variant, seed) produces."""
LEGACY_GENERATORS = ("flyknot_sim.demo_synth", "flyknot_tools.demo_synth")
"""Earlier names of this tool in stored demonstrations (the shipped ``assets/demos`` carry
the first); nothing reads the name, it only records where a file came from."""


def rope_metadata(rope_id: int | str | Any, ropes: str | None = None) -> dict[str, Any]:
    """The rope's parameters and the simulation settings, as plain data (a shipped demo is
    stale when these differ from ``assets/ropes.toml``). ``rope_id``: anything
    :func:`flyknot_sim.rope_custom.resolve_rope` takes (with the ropes file ``ropes``)."""
    from flyknot_sim.rope_custom import resolve_rope
    from flyknot_sim.rope_table import load_sim_settings

    rope = resolve_rope(rope_id, ropes).to_dict()
    data = {"rope": rope, "simulation": load_sim_settings().to_dict()}
    return json.loads(json.dumps(data))  # as stored: tuples become lists


def make_demonstration(
    motion: KnotMotion,
    *,
    variant: str,
    seed: int,
    hand: HandParams | None = None,
    mocap_params: MocapParams | None = None,
    extra: Mapping[str, Any] | None = None,
) -> tuple[Demonstration, HandTrial]:
    """Play ``motion`` once, nominally, and record it as the motion capture would.

    The capture noise is seeded by ``(seed, 3)``; t_c is the simulation's first rope
    self-contact. Metadata: generator and version, variant, seed, the 23 motion numbers, the
    motion's start on the demonstration clock, the hand and rope settings, the settled
    outcome and ``extra``.

    Raises:
        ConfigError: The rope never touched itself (no t_c) or the simulation diverged.
    """
    import mujoco

    hand = HandParams() if hand is None else hand
    if hand.rope_params.custom:
        raise ConfigError(
            "rope",
            f"a demonstration records one of the paper's ropes 1..7, got the custom rope "
            f"{hand.rope_params.name!r} (custom ropes replay demonstrations)",
        )
    hand = replace(hand, variation=HandVariation.none())
    mocap_params = MocapParams() if mocap_params is None else mocap_params
    lab = HandLab(hand)
    trial = lab.run(motion)
    meta = {
        "generator": GENERATOR,
        "generator_version": GENERATOR_VERSION,
        "variant": variant,
        "seed": seed,
        "motion": motion.to_dict(),
        "motion_start": trial.motion_start,
        "motion_duration": motion.duration,
        "hand": hand_metadata(hand),
        "hand_frame": "fingertip: origin at the held end, z along the rope's exit",
        "mocap": asdict(mocap_params),
        "settle_outcome": trial.knot,
        "knot_any": trial.knot_any,
        "settle_fraction": trial.settle_fraction,
        "mujoco": mujoco.__version__,
        **rope_metadata(hand.rope_params),
        **dict(extra or {}),
    }
    demo = trial_demonstration(
        trial,
        lab.rope,
        mocap_params,
        np.random.default_rng([seed, 3]),
        rope_id=hand.rope,
        metadata=meta,
    )
    return demo, trial


# ----------------------------------------------------------------------------------------
# synthesis: staged search, demonstration, check
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SynthConfig:
    """Settings of :func:`synthesize_motion` and :func:`synthesize`.

    Attributes:
        search: The throw stage's search (its ``budget``, ``sigma0``, ``target_rate``, the
            confirmation and the hand); later stages copy it with the fields below.
        stage_budget: Trial budget of every later stage.
        stage_sigma: CMA-ES step of every later stage [normalised units].
        stage_target: Confirmation rate that ends an intermediate stage.
        windup_speeds: Wind-up speeds r tried as the wind-up stage's start (the one tying
            most often in ``windup_trials`` trials, nominal first, is taken).
        windup_trials: Trials per wind-up speed tried.
        total_budget: Most simulated trials over all stages.
    """

    search: SearchConfig = field(default_factory=lambda: SearchConfig(budget=900))
    stage_budget: int = 500
    stage_sigma: float = 0.15
    stage_target: float = 0.5
    windup_speeds: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25)
    windup_trials: int = 3
    total_budget: int = 3000

    def __post_init__(self) -> None:
        for f in ("stage_budget", "windup_trials", "total_budget"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"SynthConfig.{f}", f"must be an integer >= 1, got {v!r}")
        check_positive("SynthConfig.stage_sigma", self.stage_sigma)
        if not 0.0 < self.stage_target <= 1.0:
            raise ConfigError(
                "SynthConfig.stage_target", f"must lie in (0, 1], got {self.stage_target!r}"
            )
        speeds = tuple(float(r) for r in self.windup_speeds)
        if not speeds or not all(WINDUP_SPEED_MIN <= r < 1.0 for r in speeds):
            raise ConfigError(
                "SynthConfig.windup_speeds",
                f"need values in [{WINDUP_SPEED_MIN}, 1), got {self.windup_speeds!r}",
            )
        object.__setattr__(self, "windup_speeds", speeds)


@dataclass(frozen=True)
class StagedResult:
    """Outcome of :func:`synthesize_motion`.

    Attributes:
        variant: Variant name.
        seed: Seed.
        motion: The final motion.
        stages: Per stage: its kind and search result (skipped stages are absent).
        trials: Simulated trials over all stages.
        wall_s: Wall time [s].
    """

    variant: str
    seed: int
    motion: KnotMotion
    stages: tuple[tuple[str, SearchResult], ...]
    trials: int
    wall_s: float

    def to_dict(self, timing: bool = True) -> dict[str, Any]:
        """Plain-data summary (``timing``: with wall times)."""
        out = {
            "variant": self.variant,
            "seed": self.seed,
            "trials": self.trials,
            "stages": [{"kind": k, **r.to_dict(timing)} for k, r in self.stages],
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def _pick_windup(
    lab: HandLab,
    motion: KnotMotion,
    stage: Variant,
    seed: int,
    stream: int,
    config: SynthConfig,
) -> tuple[KnotMotion, int]:
    """The wind-up stage's start: ``motion`` lengthened to the stage's mid duration with the
    wind-up speed (of ``config.windup_speeds``) that ties most often; returns it and the
    trials spent."""
    duration = float(np.mean(stage.duration))
    trials = variations(lab, (seed, stream, 5), config.windup_trials, nominal_first=True)
    best: tuple[tuple[int, float], KnotMotion] | None = None
    spent = 0
    for r in config.windup_speeds:
        cand = motion.with_windup(max(duration, motion.core_duration), r)
        ev = evaluate(lab, cand, stage, trials)
        spent += sum(sm.simulated for sm in ev.summaries)
        key = (ev.ties, ev.mean_score)
        if best is None or key > best[0]:
            best = (key, cand)
    assert best is not None  # windup_speeds is never empty (SynthConfig checks it)
    return best[1], spent


def synthesize_motion(
    variant: str | Variant,
    seed: int,
    config: SynthConfig = SynthConfig(),
    *,
    progress: bool = False,
    on_stage: Callable[[str, Variant, SearchResult, bool], None] | None = None,
    start: KnotMotion | None = None,
    last_stage: bool = False,
    first_stage: bool = False,
) -> StagedResult:
    """Search a robust flying-knot motion of ``variant`` in stages (:meth:`Variant.stages`).

    Each stage runs :func:`search` from the previous stage's best motion (the first from the
    variant's seed motion, with the variant's ``throw_sigma``) on its own sub-stream of
    ``seed``; a wind-up stage starts from the best of :meth:`KnotMotion.with_windup` over
    ``config.windup_speeds``. Intermediate stages end at
    ``config.stage_target``, the last at ``config.search.target_rate``. ``on_stage`` is
    called with each finished stage's kind, variant, result and whether it is the run's last
    (before a stage that tied nothing raises: :func:`stage_keeper` saves what it found).
    ``start`` replaces the variant's seed motion as the first stage's start (e.g. a
    demonstration found under looser pace limits).
    ``last_stage``: run the last stage alone from ``start`` (a motion of the variant already,
    its wind-up kept), with the later stages' budget and step: a local search that can raise a
    demonstration's tie rate without squeezing it into the throw stage's window.
    ``first_stage``: run the first stage alone, ending at the search's target rate (e.g. the
    throw of a wind-up variant, found where its wind-up is not).

    Raises:
        ConfigError: ``last_stage`` without ``start``; both ``first_stage`` and ``last_stage``.
        SolverError: A stage found no motion whose nominal trial ties, or the total budget
            ran out.
    """
    from tqdm import tqdm

    from flyknot.errors import SolverError

    v = get_variant(variant) if isinstance(variant, str) else variant
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", f"must be an integer >= 0, got {seed!r}")
    tic = time.perf_counter()
    lab = HandLab(config.search.hand)
    stages = v.stages()
    if first_stage and last_stage:
        raise ConfigError("first_stage", "the first stage alone or the last stage alone, not both")
    if last_stage and start is None:
        raise ConfigError("start", "the last stage alone needs a start motion (--start)")
    if first_stage:
        stages = stages[:1]
    first = len(stages) - 1 if last_stage else 0
    motion = replace(v, duration=THROW_WINDOW).seed_motion() if start is None else start
    bar = tqdm(
        total=config.total_budget,
        unit="trial",
        desc=f"demo {v.name} seed {seed}",
        disable=bar_disable(progress),
    )
    used = 0
    done: list[tuple[str, SearchResult]] = []
    try:
        for k, (kind, stage) in enumerate(stages[first:], start=first):
            last = k == len(stages) - 1
            if kind == "windup" and not last_stage:
                motion, spent = _pick_windup(lab, motion, stage, seed, k, config)
                used += spent
                bar.update(spent)
            cfg = replace(config.search, sigma0=v.throw_sigma)
            if k > 0 or last_stage:
                cfg = replace(cfg, budget=config.stage_budget, sigma0=config.stage_sigma)
            if not last:
                cfg = replace(cfg, target_rate=config.stage_target)
            left = config.total_budget - used
            if left < 1:
                raise SolverError("demo search", "budget", f"spent before stage {stage.name}")
            cfg = replace(cfg, budget=min(cfg.budget, left))
            res = search(stage, seed, cfg, start=motion, stream=k, lab=lab, bar=bar)
            used += res.trials
            done.append((kind, res))
            if on_stage is not None:
                on_stage(kind, stage, res, last)
            if res.best is None or not res.best.nominal_tied:
                raise SolverError(
                    "demo search",
                    "no knot",
                    f"stage {stage.name} found no motion whose nominal trial ties in "
                    f"{res.trials} trials; try another seed or a larger budget",
                )
            motion = res.best.motion
    finally:
        bar.close()
    return StagedResult(v.name, seed, motion, tuple(done), used, time.perf_counter() - tic)


def stage_path(out: Path, kind: str) -> Path:
    """Where :func:`stage_keeper` saves an intermediate stage's best: ``OUT.<kind>.npz``."""
    return out.with_name(f"{out.stem}.{kind}{out.suffix}")


def stage_keeper(
    seed: int,
    hand: HandParams,
    out: Path,
    notify: Callable[[str], None] = lambda line: None,
) -> Callable[[str, Variant, SearchResult, bool], None]:
    """An ``on_stage`` for :func:`synthesize_motion` that records the best motion of every
    intermediate stage whose nominal trial ties as a demonstration at
    :func:`stage_path` (under the stage's name, e.g. ``swipe/throw``; no check replays), so
    that a later stage that fails does not lose it. ``notify`` gets one line per file."""

    def keep(kind: str, stage: Variant, res: SearchResult, last: bool) -> None:
        if last or res.best is None or not res.best.nominal_tied:
            return
        demo, _ = make_demonstration(
            res.best.motion,
            variant=stage.name,
            seed=seed,
            hand=hand,
            extra={"search": res.to_dict(timing=False), **pace_metadata(stage)},
        )
        path = stage_path(out, kind)
        demo.save(path)
        notify(f"stage {stage.name}: its best motion (nominal trial ties) saved to {path}")

    return keep


@dataclass(frozen=True)
class SynthResult:
    """Outcome of :func:`synthesize`.

    Attributes:
        demo: The demonstration (metadata includes the search summary and the check).
        staged: The staged search.
        check: The varied replays of the saved demonstration, or None if skipped.
    """

    demo: Demonstration
    staged: StagedResult
    check: ReplayResult | None

    def summary(self) -> dict[str, Any]:
        """What the command line prints."""
        m = self.demo.metadata
        return {
            "variant": m["variant"],
            "seed": m["seed"],
            "rope": self.demo.rope,
            "duration_s": round(m["motion_duration"], 4),
            "t_c": round(self.demo.t_c, 4),
            "settle_outcome": m["settle_outcome"],
            "trials": self.staged.trials,
            "search_wall_s": round(self.staged.wall_s, 1),
            "check": None
            if self.check is None
            else f"{self.check.knots}/{len(self.check.outcomes)}",
        }


def pace_metadata(variant: Variant) -> dict[str, Any]:
    """The variant's finite pace limits as plain data (empty if it has none)."""
    out = {}
    for f in PACE_FIELDS:
        v = getattr(variant, f)
        if math.isfinite(v):
            out[f] = float(v)
    return {"pace": out} if out else {}


def synthesize(
    variant: str | Variant,
    seed: int,
    config: SynthConfig = SynthConfig(),
    *,
    check_repeats: int = 20,
    progress: bool = False,
    start: KnotMotion | None = None,
    last_stage: bool = False,
    first_stage: bool = False,
    on_stage: Callable[[str, Variant, SearchResult, bool], None] | None = None,
) -> SynthResult:
    """Search a motion (:func:`synthesize_motion`), record it as a demonstration
    (:func:`make_demonstration`) and check it with ``check_repeats`` varied replays
    (:func:`replay` with seed ``seed``; the count goes into the metadata as ``check``).
    ``start``, ``last_stage``, ``first_stage``, ``on_stage``: as in :func:`synthesize_motion`
    (the first stage alone is recorded under that stage's name, e.g. ``swipe/throw``)."""
    v = get_variant(variant) if isinstance(variant, str) else variant
    staged = synthesize_motion(
        v,
        seed,
        config,
        progress=progress,
        start=start,
        last_stage=last_stage,
        first_stage=first_stage,
        on_stage=on_stage,
    )
    if first_stage:
        v = v.stages()[0][1]
    hand = config.search.hand
    demo, _ = make_demonstration(
        staged.motion,
        variant=v.name,
        seed=seed,
        hand=hand,
        extra={
            "search": staged.to_dict(timing=False),
            "variant_description": v.description,
            **pace_metadata(v),
        },
    )
    check = None
    if check_repeats > 0:
        check = replay(demo, repeats=check_repeats, seed=seed, progress=progress)
        meta = dict(demo.metadata)
        meta["check"] = {"repeats": check_repeats, "seed": seed, "knots": check.knots}
        demo = replace(demo, metadata=meta)
    return SynthResult(demo, staged, check)

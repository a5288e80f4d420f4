"""Robot demonstrations: a command the simulated arm ties the knot with, recorded as a demo.

The hand demonstrations (``flyknot_tools.hand_demos``) flick the wrist far faster than the arm
can turn (``docs/learning.md``), so the learner's target lies out of the arm's reach. A robot
demonstration is what a person would record by guiding the arm (kinesthetic teaching): a
motion the arm can make. It is made in two steps:

1. :func:`search_command`: CMA-ES (package ``cma``) over Bezier commands near a start command
   (usually the initial guess of a hand demonstration), in the lab without trial-to-trial
   variation. Decision: 37 numbers, y in normalised units. For joints 1-6 the 6 free knots
   (knot 1 copies knot 0 and knot 6 copies knot 7: rest at both ends) are offset by
   ``space.knot_scale`` y [rad]; joint 7 (it only twists the rope, which has no torsion)
   and the base rows stay; T = T0 + ``space.duration_scale`` y_37, kept in
   ``space.duration`` (:class:`CommandSpace`). A command that breaks a limit on its 250 Hz
   samples scores -30 - 20 min(v, 5) without being simulated (v: largest violation as a
   fraction of the half range). Otherwise
   :func:`command_score`. The search stops at the first command whose trial ends tied.
2. :func:`record_demonstration`: that command's nominal trial as the motion capture sees it:
   the fingertip pose (hand frame = fingertip frame), the 11 markers at 200 Hz (noise, loss
   after contact), t_c = the first rope self-contact.

Score of a trial (higher is better), on truth centrelines every ``frame_s`` from 0.3 T on:
100 [tied at the end] + 30 (knotted fraction of the settling frames) + 10 [a knot in any
frame] + 5 (largest trefoil share of the ray closures) + 2 (mean share while settling)
+ 3 [self-contact] + 3 (1 - min(d_min / 0.3 m, 1)), with d_min the closest approach of rope
points at least 8 vertices apart; a faulted trial scores -20 (+3 if the rope touched itself).
Only a first self-contact during the motion (t <= T) counts, for the contact and the knot
terms: a demonstration's critical point is where the motion makes the rope cross itself, not
where a rope swinging after the motion happens to.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, FlyknotError, check_int, check_positive
from flyknot.limits import JointLimits
from flyknot.progress import bar_disable
from flyknot.record import TrialRecord

__all__ = [
    "CommandCoding",
    "CommandSearchConfig",
    "CommandSearchResult",
    "CommandSpace",
    "check_duration",
    "command_score",
    "free_from_knots",
    "knots_from_free",
    "record_demonstration",
    "search_command",
]

FREE = (0, 2, 3, 4, 5, 7)  # free knots of an arm row; knot 1 = knot 0, knot 6 = knot 7
N_SEARCHED_JOINTS = 6  # joints 1-6; joint 7 only twists the rope
N_DECISION = N_SEARCHED_JOINTS * len(FREE) + 1  # 37
HIT_SCORE = 100.0


def free_from_knots(knots: np.ndarray) -> np.ndarray:
    """The free arm knots of a command, shape (7, 6) [rad] (knots 0, 2, 3, 4, 5, 7)."""
    k = np.asarray(knots, dtype=float)
    if k.shape != (10, 8):
        raise ConfigError("knots", f"must have shape (10, 8), got {k.shape}")
    return k[:7, list(FREE)].copy()


def knots_from_free(free: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Knots (10, 8) from free arm knots (7, 6) [rad] and the base rows (3, 8) [m]; knot 1 =
    knot 0 and knot 6 = knot 7, so the command starts and ends at rest."""
    free = np.asarray(free, dtype=float)
    base = np.asarray(base, dtype=float)
    if free.shape != (7, len(FREE)) or base.shape != (3, 8):
        raise ConfigError(
            "free", f"need free (7, 6) and base (3, 8), got {free.shape} and {base.shape}"
        )
    k = np.empty((10, 8))
    k[:7, list(FREE)] = free
    k[:7, 1] = free[:, 0]
    k[:7, 6] = free[:, -1]
    k[7:] = base
    return k


def check_duration(duration: tuple[float, float]) -> tuple[float, float]:
    """A search's allowed command duration (lo, hi) [s], 0.1 <= lo < hi <= 5.

    Raises:
        ConfigError: Outside those bounds (named ``duration``).
    """
    lo, hi = (float(v) for v in duration)
    if not 0.1 <= lo < hi <= 5.0:
        raise ConfigError("duration", f"need 0.1 <= lo < hi <= 5 s, got {duration}")
    return lo, hi


@dataclass(frozen=True)
class CommandSpace:
    """How the searches' decision vector moves a command (shared by both searches).

    Attributes:
        knot_scale: Knot offset per normalised unit [rad].
        duration_scale: Duration change per normalised unit [s].
        duration: Allowed command duration (lo, hi) [s].
    """

    knot_scale: float = 0.12
    duration_scale: float = 0.036
    duration: tuple[float, float] = (0.6, 1.1)

    def __post_init__(self) -> None:
        for f in ("knot_scale", "duration_scale"):
            check_positive(f, getattr(self, f))
        object.__setattr__(self, "duration", check_duration(self.duration))


@dataclass(frozen=True)
class CommandCoding:
    """The searches' decision vector y (37,) [normalised units] and the command it codes.

    For joints 1-6 the free knots of ``start_knots`` are offset by ``space.knot_scale``
    y[:36] [rad]; T = T0 + ``space.duration_scale`` y[36] [s]; joint 7 and the base rows stay
    (module docstring).

    Attributes:
        start_knots: Knots of the start command (10, 8).
        T0: Its duration [s].
        space: Scales and the allowed duration.
    """

    start_knots: np.ndarray
    T0: float
    space: CommandSpace

    def decode(self, y: np.ndarray) -> tuple[np.ndarray, float]:
        """The command (knots (10, 8), T [s]) of decision vector y (37,)."""
        free = free_from_knots(self.start_knots)
        y = np.asarray(y, dtype=float)
        free[:N_SEARCHED_JOINTS] += self.space.knot_scale * y[:-1].reshape(N_SEARCHED_JOINTS, -1)
        base = np.asarray(self.start_knots, dtype=float)[7:]
        return knots_from_free(free, base), float(self.T0 + self.space.duration_scale * y[-1])

    def limit_score(self, knots: np.ndarray, T: float, robot, limits) -> float | None:
        """The score of a command outside its duration or the joint limits on its 250 Hz
        samples (-30 - 100 |T - T_clipped|, or -30 - 20 min(v, 5) with v the largest violation
        as a fraction of the half range); None inside them."""
        from learner.bezier import BezierCommand
        from learner.limit_rows import sampled_violation

        lo, hi = self.space.duration
        if not lo <= T <= hi:
            return -30.0 - 100.0 * abs(T - min(max(T, lo), hi))
        v = sampled_violation(knots, T, BezierCommand(knots, T).sample_times(), robot, limits)
        return -30.0 - 20.0 * min(v, 5.0) if v > 0 else None


@dataclass(frozen=True)
class CommandSearchConfig:
    """Settings of :func:`search_command`.

    Attributes:
        rope: Rope id of the lab.
        evaluations: Most candidate commands evaluated.
        sigma0: CMA-ES initial step [normalised units].
        space: How the decision vector moves the command.
        frame_s: Spacing of the judged truth frames [s].
        confirm: Varied trials (seeds 0..confirm-1) that confirm a tying command.
        local_evaluations: Most candidates of the local phase (0: stop at the first knot).
        local_sigma: CMA-ES step of the local phase [normalised units].
        target_rate: The local phase stops at a command tying in this fraction of the
            confirmation trials.
        check: Fresh varied trials (seeds confirm..confirm+check-1) that measure the chosen
            command's rate.
    """

    rope: int = 1
    evaluations: int = 1500
    sigma0: float = 1.0
    space: CommandSpace = field(default_factory=CommandSpace)
    frame_s: float = 0.05
    confirm: int = 10
    local_evaluations: int = 300
    local_sigma: float = 0.25
    target_rate: float = 0.6
    check: int = 20

    def __post_init__(self) -> None:
        check_int("evaluations", self.evaluations, 1)
        for f in ("confirm", "local_evaluations", "check"):
            check_int(f, getattr(self, f), 0)
        if not (isinstance(self.target_rate, (int, float)) and 0 < self.target_rate <= 1):
            raise ConfigError("target_rate", f"must lie in (0, 1], got {self.target_rate!r}")
        for f in ("sigma0", "frame_s", "local_sigma"):
            check_positive(f, getattr(self, f))


@dataclass(frozen=True)
class CommandSearchResult:
    """Outcome of :func:`search_command`.

    Attributes:
        knots: Best command's knots (10, 8).
        T: Its duration [s].
        score: Its score.
        tied: Its nominal trial ended with a knot.
        evaluations: Candidates evaluated.
        simulated: Candidates simulated (the others broke a limit).
        first_hit: Evaluation count at the first tied trial, or None.
        confirm_knots: Knots of the chosen command in the varied confirmation trials.
        confirmed_candidates: Tying candidates that were confirmed.
        check_knots: Knots of the chosen command in ``check`` fresh varied trials (seeds
            after the confirmation seeds): its rate without the selection's bias.
        wall_s: Wall time [s].
        history: Best score so far per evaluation, shape (evaluations,).
    """

    knots: np.ndarray
    T: float
    score: float
    tied: bool
    evaluations: int
    simulated: int
    first_hit: int | None
    confirm_knots: int
    confirmed_candidates: int
    check_knots: int
    wall_s: float
    history: np.ndarray = field(repr=False)

    def summary(self, timing: bool = True) -> dict[str, Any]:
        """Plain data (without the knots); ``timing`` adds the wall time (left out of saved
        demonstrations so that a rerun writes the same file)."""
        out = {
            "T": round(self.T, 4),
            "score": round(self.score, 2),
            "tied": self.tied,
            "evaluations": self.evaluations,
            "simulated": self.simulated,
            "first_hit": self.first_hit,
            "confirm_knots": self.confirm_knots,
            "confirmed_candidates": self.confirmed_candidates,
            "check_knots": self.check_knots,
        }
        if timing:
            out["wall_s"] = round(self.wall_s, 1)
        return out


def command_score(record: TrialRecord, T: float, frame_s: float = 0.05) -> float:
    """Shaped score of one trial (module docstring); needs the record's simulator truth."""
    from flyknot.knot import TREFOIL, closure_votes, plurality

    during = record.first_contact_time is not None and record.first_contact_time <= T
    contact = 3.0 if during else 0.0
    if record.fault is not None:
        return -20.0 + contact
    if "centreline" not in record.truth:
        raise ConfigError("record", "needs the simulator's truth (a simulated trial)")
    tt = np.asarray(record.truth["t_truth"])
    C = np.asarray(record.truth["centreline"])
    if not during:  # no credit for knots of a rope swinging after the motion
        return float(3.0 * (1.0 - min(_closest_approach(C) / 0.3, 1.0)))
    stride = max(1, round(frame_s / float(tt[1] - tt[0])))
    idx = np.arange(0, len(tt), stride)
    idx = idx[tt[idx] >= 0.3 * T]
    shares, knotted = [], []
    for i in idx:
        votes = closure_votes(C[i], n_directions=11)
        shares.append(votes.get(TREFOIL, 0) / 11.0)
        knotted.append(plurality(votes) == TREFOIL)
    shares_a, knotted_a = np.array(shares), np.array(knotted)
    settle = tt[idx] >= T
    s = HIT_SCORE * record.succeeded
    if settle.any():
        s += 30.0 * knotted_a[settle].mean() + 2.0 * shares_a[settle].mean()
    if idx.size:
        s += 10.0 * knotted_a.any() + 5.0 * shares_a.max()
    return float(s + contact + 3.0 * (1.0 - min(_closest_approach(C) / 0.3, 1.0)))


def _closest_approach(C: np.ndarray) -> float:
    """Closest distance between rope points at least 8 vertices apart over the frames
    (every second frame) of centrelines C (frames, vertices, 3) [m]."""
    n = C.shape[1]
    far = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) >= 8
    D = np.linalg.norm(C[::2, :, None] - C[::2, None, :], axis=-1)
    return float(D[:, far].min())


class _Trials:
    """A search's trials: the nominal lab scores candidates, varied labs confirm them."""

    def __init__(self, coding: CommandCoding, config: CommandSearchConfig) -> None:
        from flyknot_sim.lab import LabParams, SimLab, VariationParams
        from learner.kinematics import RobotModel

        self.coding, self.config = coding, config
        self.robot, self.limits = RobotModel.from_mjcf(), JointLimits()
        self.lab = SimLab(LabParams(rope=config.rope, variation=VariationParams.none()))
        self.evals = self.simulated = 0

    def score(self, y: np.ndarray) -> tuple[float, np.ndarray, float]:
        """(score, knots, T) of decision vector y: its limit score, or its nominal trial's."""
        from learner.bezier import BezierCommand

        knots, T = self.coding.decode(y)
        self.evals += 1
        out_of_limits = self.coding.limit_score(knots, T, self.robot, self.limits)
        if out_of_limits is not None:
            return out_of_limits, knots, T
        self.simulated += 1
        rec = self.lab.run(BezierCommand(knots, T).joint_command())
        return command_score(rec, T, self.config.frame_s), knots, T

    def ties(self, knots: np.ndarray, T: float, seeds: range | None = None) -> int:
        """Knots in the varied trials of lab ``seeds`` (default 0 .. confirm - 1)."""
        from flyknot_sim.lab import LabParams, SimLab
        from learner.bezier import BezierCommand

        seeds = range(self.config.confirm) if seeds is None else seeds
        command = BezierCommand(knots, T).joint_command()
        return sum(
            SimLab(LabParams(rope=self.config.rope, seed=s)).run(command).succeeded for s in seeds
        )


def _global_phase(trials: _Trials, best: tuple, history: list, bar, seed: int) -> tuple:
    """Phase 1: CMA-ES from the start until the first tying nominal trial or the budget.

    Returns:
        (best (score, knots, T), first_hit evaluation or None, its decision vector or None).
    """
    import cma

    config = trials.config
    es = cma.CMAEvolutionStrategy(
        np.zeros(N_DECISION), config.sigma0, {"seed": seed + 1, "verbose": -9}
    )
    while trials.evals < config.evaluations:
        ys = es.ask()
        scores = []
        for y in ys:
            s, knots, T = trials.score(np.asarray(y))
            scores.append(s)
            if s > best[0]:
                best = (s, knots, T)
            history.append(best[0])
            bar.update(1)
            bar.set_postfix(best=f"{best[0]:.1f}", simulated=trials.simulated)
            if s >= HIT_SCORE:
                return best, trials.evals, np.asarray(y)
            if trials.evals >= config.evaluations:
                break
        if len(scores) == len(ys):
            es.tell(ys, [-s for s in scores])
    return best, None, None


def _local_phase(
    trials: _Trials, best: tuple, hit_y: np.ndarray, history: list, bar, seed: int
) -> tuple[tuple[int, float, np.ndarray, float], int]:
    """Phase 2: CMA-ES around the first tying command; every candidate whose nominal trial
    ties is confirmed on the varied trials, and the one tying most often is kept.

    Returns:
        (chosen (ties, score, knots, T), confirmed candidates).
    """
    import cma

    config = trials.config
    chosen = (trials.ties(best[1], best[2]), best[0], best[1], best[2])
    confirmed = 1
    target = math.ceil(config.target_rate * config.confirm)
    es = cma.CMAEvolutionStrategy(hit_y, config.local_sigma, {"seed": seed + 2, "verbose": -9})
    start = trials.evals
    while trials.evals - start < config.local_evaluations and chosen[0] < target:
        ys = es.ask()
        scores = []
        for y in ys:
            s, knots, T = trials.score(np.asarray(y))
            scores.append(s)
            if s >= HIT_SCORE:
                ties = trials.ties(knots, T)
                confirmed += 1
                if (ties, s) > chosen[:2]:
                    chosen = (ties, s, knots, T)
            history.append(max(history[-1], s))
            bar.update(1)
            bar.set_postfix(best_ties=f"{chosen[0]}/{config.confirm}", confirmed=confirmed)
            if chosen[0] >= target or trials.evals - start >= config.local_evaluations:
                break
        if len(scores) == len(ys):
            es.tell(ys, [-s for s in scores])
    return chosen, confirmed


def search_command(
    start_knots: np.ndarray,
    T0: float,
    config: CommandSearchConfig = CommandSearchConfig(),
    *,
    seed: int = 0,
    progress: bool = False,
) -> CommandSearchResult:
    """CMA-ES for a command whose trial ties the knot (module docstring).

    Phase 1 (global) runs until the first nominal trial that ties. Phase 2 (local, up to
    ``local_evaluations`` candidates) restarts CMA-ES at that command with step
    ``local_sigma``; every candidate whose nominal trial ties is confirmed on ``confirm``
    varied trials (seeds 0..confirm-1), and the search keeps the one that ties most often,
    stopping early once it ties in ``target_rate`` of them.
    """
    from tqdm import tqdm

    check_int("seed", seed, 0)
    tic = time.perf_counter()
    trials = _Trials(CommandCoding(np.asarray(start_knots, dtype=float), T0, config.space), config)
    total = config.evaluations + config.local_evaluations
    bar = tqdm(total=total, desc="robot demo search", disable=bar_disable(progress))
    history: list[float] = []
    best = (-math.inf, np.asarray(start_knots), T0)
    best, first_hit, hit_y = _global_phase(trials, best, history, bar, seed)
    chosen, confirmed = None, 0
    if hit_y is not None:
        chosen, confirmed = _local_phase(trials, best, hit_y, history, bar, seed)
    bar.close()
    if chosen is None:
        score, knots, T = best
        ties = check = 0
    else:
        ties, score, knots, T = chosen
        check = trials.ties(knots, T, range(config.confirm, config.confirm + config.check))
    return CommandSearchResult(
        knots=np.asarray(knots),
        T=T,
        score=score,
        tied=score >= HIT_SCORE,
        evaluations=trials.evals,
        simulated=trials.simulated,
        first_hit=first_hit,
        confirm_knots=ties,
        confirmed_candidates=confirmed,
        check_knots=check,
        wall_s=time.perf_counter() - tic,
        history=np.array(history),
    )


def record_demonstration(
    knots: np.ndarray,
    T: float,
    *,
    rope: int = 1,
    metadata: dict[str, Any] | None = None,
    lab_params=None,
) -> Demonstration:
    """The nominal trial of a command as a demonstration (module docstring).

    ``lab_params`` (a :class:`flyknot_sim.lab.LabParams`; default: the lab's defaults without
    variation) selects the lab it is recorded in; its rope is ``rope``. The metadata's
    ``command_knots`` are ``knots`` with the base-offset rows 7-9 set to the lab's base
    position (the demonstration frame is the lab's), so that the stored command starts a
    learner as it is.

    Raises:
        FlyknotError: The trial faulted, or the rope did not touch itself during the motion.
    """
    import dataclasses

    from scipy.spatial.transform import Rotation, Slerp

    from flyknot_sim.lab import LabParams, SimLab, VariationParams
    from learner.bezier import BezierCommand

    if lab_params is None:
        lab_params = LabParams(rope=rope, variation=VariationParams.none())
    lab = SimLab(dataclasses.replace(lab_params, rope=rope))
    rec = lab.run(BezierCommand(np.asarray(knots, dtype=float), float(T)).joint_command())
    if rec.fault is not None:
        raise FlyknotError(f"the command faulted: {rec.fault}")
    if rec.first_contact_time is None:
        raise FlyknotError("the rope never touched itself, so there is no t_c")
    if rec.first_contact_time > T:
        raise FlyknotError(
            f"the rope first touched itself at {rec.first_contact_time:.3f} s, after the "
            f"motion ended at {T:.3f} s; a demonstration needs t_c during the motion"
        )
    t = rec.t_marker
    t_pose = np.clip(t, rec.t_joint[0], rec.t_joint[-1])
    pos = np.column_stack(
        [np.interp(t_pose, rec.t_joint, rec.fingertip_pos[:, i]) for i in range(3)]
    )
    rot = Rotation.from_quat(rec.fingertip_quat, scalar_first=True)
    quat = Slerp(rec.t_joint, rot)(t_pose).as_quat(scalar_first=True)
    # The demonstration is recorded in the lab's frame, so the command's base-offset rows (the
    # robot base in the demonstration frame, learner.bezier) are the lab's base position: a
    # learner started from the stored command then maps its markers as the demonstration's.
    stored = np.array(knots, dtype=float)
    stored[7:] = np.asarray(lab.base_pose[:3], dtype=float)[:, None]
    meta = {
        "generator": "flyknot_tools.robot_demo",
        "source": "robot lab, nominal trial (kinesthetic demonstration)",
        "command_T": float(T),
        "command_knots": stored.tolist(),
        "knot": rec.knot,
        **(metadata or {}),
    }
    return Demonstration(
        t=t,
        hand_pos=pos,
        hand_quat=quat,
        markers=rec.markers,
        t_c=float(rec.first_contact_time),
        rope=rope,
        metadata=meta,
    )

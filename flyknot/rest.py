"""When a hanging rope is "at rest": the criterion a lab checks before a throw and before a verdict.

The paper's trials start "in a static state hanging down from the fingertip" and succeed with
"a topological overhand knot in a rope hanging down at the end of motion". Both need one
definition of rest that a real lab can check with its motion capture and a simulated lab can
apply to its state. Here it is, for the free end of the rope:

* speed: the free end moves slower than ``speed_m_s`` throughout a window of ``window_s``;
* displacement: the free end lies within ``displacement_m`` of its hanging position.

Defaults and why:

* ``speed_m_s = 0.03`` [m/s]: a swing at this peak speed has an amplitude of at most
  v / omega_1 = 8.4 mm at the free end (omega_1 = 1.2024 sqrt(g / L) = 3.59 rad/s for
  L = 1.1 m, the first swing mode of a uniform hanging chain; an end mass lowers it toward
  sqrt(g / L) = 2.99 rad/s), about the rope's own diameter: still to the eye. A
  motion-capture system sees it: with 1 mm marker noise at 200 Hz, a least-squares speed over
  0.1 s has a noise of about sqrt(12) * 1 mm / (0.1 s * sqrt(20)) ~ 8 mm/s, a quarter of the
  threshold.
* ``window_s = 1.0`` [s]: about half a swing period (pi / omega_1 = 0.87 s for the uniform
  chain, 1.05 s in the end-mass limit; the time between a swing's speed peaks), so a rope
  passing slowly through a turning point is not taken for a rope at rest.
* ``displacement_m = speed_m_s / omega_1`` (8.4 mm): the amplitude of a swing at the speed
  threshold in the fastest first mode, so a rope within it never swings faster than the
  speed bound.

:func:`settled_start` draws a start state uniformly within this criterion (the state of a
rope a lab waits for before it throws); :func:`free_end_at_rest` checks it on measurements.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from flyknot.constants import GRAVITY, ROPE_LENGTH
from flyknot.errors import ConfigError, check_nonnegative, check_positive, check_share

UNKNOT = "unknot"

__all__ = [
    "RestCriterion",
    "SettleMonitor",
    "SettleOutcome",
    "SettleParams",
    "free_end_at_rest",
    "pendulum_omega",
    "settled_start",
    "start_with_sway",
]


def pendulum_omega(length: float = ROPE_LENGTH) -> float:
    """First swing frequency of a uniform hanging chain, omega_1 = 1.2024 sqrt(g / L) [rad/s].

    1.2024 is half the first zero of J_0 (2.4048); an end mass lowers the frequency toward the
    simple pendulum's sqrt(g / L), so this is the fastest first swing of the paper's ropes.

    Args:
        length: Rope length L [m].
    """
    check_positive("length", length)
    return 1.2024 * math.sqrt(GRAVITY / length)


@dataclass(frozen=True)
class RestCriterion:
    """Rest of the rope's free end (module docstring for the numbers and why).

    Attributes:
        speed_m_s: Largest free-end speed of a rope at rest [m/s].
        window_s: The speed must stay below ``speed_m_s`` for this long [s].
        displacement_m: Largest distance of the free end from its hanging position [m];
            None: ``speed_m_s / pendulum_omega()``.
    """

    speed_m_s: float = 0.03
    window_s: float = 1.0
    displacement_m: float | None = None

    def __post_init__(self) -> None:
        check_positive("speed_m_s", self.speed_m_s)
        check_positive("window_s", self.window_s)
        if self.displacement_m is not None:
            check_positive("displacement_m", self.displacement_m)

    def max_displacement(self, length: float = ROPE_LENGTH) -> float:
        """The displacement bound [m] (explicit, or the swing amplitude at the speed bound)."""
        if self.displacement_m is not None:
            return self.displacement_m
        return self.speed_m_s / pendulum_omega(length)


@dataclass(frozen=True)
class SettleParams:
    """How long a lab waits after the motion before it judges the knot.

    The lab holds the last command and runs until the free end has been at rest
    (:class:`RestCriterion`) for ``rest.window_s`` and the knot verdict, sampled every
    ``verdict_interval_s``, has not changed over that window; at least ``min_s``, at most
    ``max_s`` after the end of the command (then the trial is marked unsettled and judged as it
    hangs).

    Attributes:
        rest: The rest criterion.
        min_s: Shortest wait [s].
        max_s: Longest wait [s] (cap).
        verdict_interval_s: Interval of the knot verdicts of the history [s].
        contact_free_unknot: Judge a rope early that has been unknotted and free of
            self-contact over a whole window: a knot forms only where the rope's end passes
            through a loop of itself, and a hanging rope that does not touch itself is not
            doing that (``docs/rope-model.md``, "The lab around the rope"). No measurement
            compares its verdicts with the capped settle's: it is no key of
            :data:`EARLY_ENDS`, so ``flyknot-tools settle-compare`` cannot turn it off.
            Without it, an unknotted rope that swings on (air drag damps a large swing over
            minutes) runs to the cap.
        knot_set_s: Judge a knotted rope early once its knot has *set*: every verdict sample
            over this long [s] was the same knot, and the rope round its self-contacts (the
            knot) kept its shape, no two of its vertices moving closer or apart by more than
            ``knot_set_tol`` rope diameters (:func:`shape_change`). A knot pulled tight by the
            hanging rope's weight holds (the validation suite's static hold: no slip over 60
            s; ``docs/rope-model.md``); a knot that still swings and works has a changing
            shape. Without it, a rope with a knot in it swings on above the rest speed past
            the cap (air drag damps it over minutes). None: off.
        knot_set_tol: The shape tolerance of ``knot_set_s``, in rope diameters [-].
        unknot_held_s: Judge a rope early whose every verdict sample over this long [s] was
            unknotted, touching itself or not (a rope wrapped round the grip, or hanging in a
            loose loop, swings on above the rest speed for minutes). Chosen from the paper
            protocol's 1,456 verdict histories at lab seed 0: the longest run of unknotted
            samples that a knotted sample followed was 3.0 s (that knot opened again); the
            protocol run again with it gave the same knot verdict in 1,461 of 1,461 trials
            (``docs/performance.md``). None: off.
    """

    rest: RestCriterion = RestCriterion()
    min_s: float = 1.5
    max_s: float = 15.0
    verdict_interval_s: float = 0.25
    contact_free_unknot: bool = True
    knot_set_s: float | None = 2.0
    knot_set_tol: float = 0.5
    unknot_held_s: float | None = 3.0

    def __post_init__(self) -> None:
        if not isinstance(self.rest, RestCriterion):
            raise ConfigError("rest", f"must be a RestCriterion, got {type(self.rest).__name__}")
        check_nonnegative("min_s", self.min_s)
        check_positive("max_s", self.max_s)
        check_positive("verdict_interval_s", self.verdict_interval_s)
        if not isinstance(self.contact_free_unknot, bool):
            raise ConfigError(
                "contact_free_unknot", f"must be true or false, got {self.contact_free_unknot!r}"
            )
        if self.max_s < self.min_s:
            raise ConfigError("max_s", f"must be >= min_s ({self.min_s}), got {self.max_s}")
        if self.knot_set_s is not None:
            check_positive("knot_set_s", self.knot_set_s)
        check_positive("knot_set_tol", self.knot_set_tol)
        if self.unknot_held_s is not None:
            check_positive("unknot_held_s", self.unknot_held_s)

    def without(self, *ends: str) -> SettleParams:
        """The same settle with the named early ends off (keys of :data:`EARLY_ENDS`).

        Raises:
            ConfigError: An unknown end, listing the valid ones.
        """
        for end in ends:
            if end not in EARLY_ENDS:
                raise ConfigError("end", f"unknown early end {end!r}", list(EARLY_ENDS))
        return replace(self, **{EARLY_ENDS[end]: None for end in ends})

    @classmethod
    def fixed(cls, seconds: float) -> SettleParams:
        """Wait exactly ``seconds`` and judge, rested or not (min = max)."""
        check_nonnegative("settle_s", seconds)
        return cls(min_s=seconds, max_s=max(seconds, 1e-9))


EARLY_ENDS = {"knot_set": "knot_set_s", "unknot_held": "unknot_held_s"}
"""The settle's early ends that can be turned off: name -> the :class:`SettleParams` field
that is None when it is off."""


def shape_change(reference: np.ndarray, now: np.ndarray) -> float:
    """How far a set of points moved relative to itself [m].

    change = max_{a, b} | |p_a - p_b| - |r_a - r_b| |: zero for any rigid motion of the set
    (a knot that swings with the rope without working), the largest change of a distance
    between two of its points otherwise.

    Args:
        reference: The points then, shape (k, 3) [m].
        now: The same points now, shape (k, 3) [m].
    """
    r = np.asarray(reference, dtype=float)
    p = np.asarray(now, dtype=float)
    if r.shape != p.shape or r.ndim != 2 or r.shape[1] != 3:
        raise ConfigError("now", f"must have the reference's shape {r.shape}, got {p.shape}")
    dr = np.linalg.norm(r[:, None, :] - r[None, :, :], axis=-1)
    dp = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    return float(np.max(np.abs(dp - dr))) if len(r) else 0.0


def free_end_at_rest(
    speed: np.ndarray, displacement: np.ndarray, criterion: RestCriterion, length: float
) -> bool:
    """Whether a window of free-end samples shows a rope at rest.

    rest <=> max_k |v_k| <= speed_m_s and max_k |d_k| <= displacement bound.

    Args:
        speed: Free-end speeds over the window, shape (k,) [m/s].
        displacement: Free-end distances from the hanging position, shape (k,) [m].
        criterion: The criterion.
        length: Rope length [m] (for the default displacement bound).
    """
    speed = np.asarray(speed, dtype=float)
    displacement = np.asarray(displacement, dtype=float)
    if speed.size == 0:
        return False
    return bool(
        np.nanmax(speed) <= criterion.speed_m_s
        and np.nanmax(displacement) <= criterion.max_displacement(length)
    )


def settled_start(
    rng: np.random.Generator,
    criterion: RestCriterion,
    length: float = ROPE_LENGTH,
    scale: float = 1.0,
) -> tuple[float, float, float]:
    """Draw a start state uniformly within the rest criterion (or a share of it).

    The rope is taken as a rigid pendulum in its lowest swing: free-end displacement
    a cos(phi) and velocity -a omega sin(phi) along a horizontal azimuth psi, with (a, phi)
    uniform over the disc of radius A = s max_displacement (a = A sqrt(u), s = ``scale``) and
    psi uniform; A omega <= speed bound by construction when the displacement bound is the
    default. The same draws at another ``scale`` give the same start, scaled.

    Args:
        rng: Source of the draw.
        criterion: The criterion.
        length: Rope length L [m].
        scale: The disc's radius as a share of the criterion's, in [0, 1] (1: any start
            the criterion calls static; 0: hanging still).

    Returns:
        ``(tilt [rad], tilt_rate [rad/s], azimuth [rad])``: the rope's angle from vertical
        toward ``azimuth`` and its rate of change (tilt may be negative: toward azimuth + pi).
    """
    check_share("scale", scale)
    omega = pendulum_omega(length)
    amp = criterion.max_displacement(length)
    amp = scale * min(amp, criterion.speed_m_s / omega)
    a = amp * math.sqrt(float(rng.uniform()))
    phi = float(rng.uniform(0.0, 2.0 * math.pi))
    psi = float(rng.uniform(0.0, 2.0 * math.pi))
    return a * math.cos(phi) / length, -a * omega * math.sin(phi) / length, psi


@dataclass(frozen=True)
class SettleOutcome:
    """How a settle ended.

    Attributes:
        settled: The free end came to rest and the verdict held over the final window.
        contact_free: Not at rest, but judged early: unknotted and free of self-contact over
            the final window (``SettleParams.contact_free_unknot``).
        knot_set: Not at rest, but judged early: the knot had set
            (``SettleParams.knot_set_s``).
        unknot_held: Not at rest, but judged early: every verdict over
            ``SettleParams.unknot_held_s`` was unknotted (and no other end came first).
        settle_s: Time from the end of the command to the verdict [s].
        verdict: The knot verdict at the end.
        free_end_speed_m_s: Largest free-end speed over the final window [m/s].
        history_t: Times of the verdicts [s] (the caller's clock).
        history: The verdicts, oldest first.
    """

    settled: bool
    contact_free: bool
    settle_s: float
    verdict: str
    free_end_speed_m_s: float
    history_t: tuple[float, ...]
    history: tuple[str, ...]
    knot_set: bool = False
    unknot_held: bool = False

    def as_metadata(self, params: SettleParams) -> dict:
        """Plain data for a trial record's metadata."""
        return {
            "settled": self.settled,
            "contact_free": self.contact_free,
            "knot_set": self.knot_set,
            "unknot_held": self.unknot_held,
            "settle_s": self.settle_s,
            "free_end_speed_m_s": self.free_end_speed_m_s,
            "verdict_stable_s": _stable_for(self.history_t, self.history),
            "criterion": {
                "speed_m_s": params.rest.speed_m_s,
                "window_s": params.rest.window_s,
                "min_s": params.min_s,
                "max_s": params.max_s,
                "verdict_interval_s": params.verdict_interval_s,
                "contact_free_unknot": params.contact_free_unknot,
                "knot_set_s": params.knot_set_s,
                "knot_set_tol": params.knot_set_tol,
                "unknot_held_s": params.unknot_held_s,
            },
            "knot_history": {"t": list(self.history_t), "verdict": list(self.history)},
        }


def _stable_for(t: tuple[float, ...], verdicts: tuple[str, ...]) -> float:
    """How long the last verdict has held, from its first sample in the final run [s]."""
    if not verdicts:
        return 0.0
    k = len(verdicts) - 1
    while k > 0 and verdicts[k - 1] == verdicts[-1]:
        k -= 1
    return float(t[-1] - t[k])


class SettleMonitor:
    """Decides when a rope after a motion is at rest and its knot verdict is stable.

    Feed it the free-end speed at every sample (:meth:`observe`); it asks ``judge()`` for a
    verdict every ``verdict_interval_s`` and says when to stop: after ``min_s``, once the speed
    has stayed below the threshold for ``window_s`` and every verdict within that window agrees
    (at least two), once an unknotted rope has been free of self-contact over that window,
    once a knot has set (``knot_set_s``), once every verdict has been unknotted for
    ``unknot_held_s``, or at ``max_s``.
    """

    def __init__(self, params: SettleParams, t_end: float, diameter: float | None = None):
        """Start monitoring; ``t_end`` is the end of the command on the caller's clock [s],
        ``diameter`` the rope's [m] (needed for ``knot_set_s``; None: no knot-set check)."""
        self.params = params
        self.t_end = float(t_end)
        self._last_fast = float(t_end)
        self._t: list[float] = []
        self._v: list[str] = []
        self._speeds: deque[tuple[float, float]] = deque()
        self._next_verdict = float(t_end)
        self._last_contact = float(t_end)
        self._done: SettleOutcome | None = None
        self._tol = None
        if diameter is not None and params.knot_set_s is not None:
            check_positive("diameter", diameter)
            self._tol = params.knot_set_tol * float(diameter)
        self._knot: tuple[float, str, tuple[int, int], np.ndarray] | None = None
        self._unknot_since: float | None = None  # first sample of the current unknotted run

    def observe(
        self, t: float, speed: float, judge, contact: bool | None = None, knot_region=None
    ) -> bool:
        """Take one sample; return True when the verdict is final (see :meth:`outcome`).

        Args:
            t: Sample time on the caller's clock [s], >= ``t_end``, increasing.
            speed: Free-end speed [m/s] (NaN counts as moving).
            judge: Callable returning the knot verdict of the rope's current shape.
            contact: Whether the rope touches itself now (None: unknown). With
                ``params.contact_free_unknot``, a rope that has been free of self-contact and
                unknotted over a whole window is judged without waiting for rest.
            knot_region: Callable returning ``(span, vertices)``: the first and last vertex
                index touched by the rope's self-contacts (None if it touches nothing) and
                the rope's vertices, shape (n + 1, 3) [m]; asked at knotted verdict samples
                only. None: no knot-set check.
        """
        if self._done is not None:
            return True
        p, rest = self.params, self.params.rest
        if not speed <= rest.speed_m_s:  # NaN included
            self._last_fast = t
        if contact is None or contact:
            self._last_contact = t
        self._speeds.append((t, speed))
        while self._speeds and self._speeds[0][0] <= t - rest.window_s + 1e-9:
            self._speeds.popleft()
        elapsed = t - self.t_end
        cap = elapsed >= p.max_s - 1e-9
        sampled = t >= self._next_verdict - 1e-9
        if sampled:
            self._t.append(t)
            self._v.append(judge())
            self._next_verdict = t + p.verdict_interval_s
            if self._v[-1] != UNKNOT:
                self._unknot_since = None
            elif self._unknot_since is None:
                self._unknot_since = t
            if knot_region is not None and self._tol is not None:
                self._track_knot(t, self._v[-1], knot_region)
        if elapsed < p.min_s - 1e-9 and not cap:
            return False
        quiet = t - self._last_fast >= rest.window_s - 1e-9
        window = self._window(t)
        stable = len(window) >= 2 and len(set(window)) == 1
        fixed = p.max_s <= p.min_s + 1e-9
        free = (
            p.contact_free_unknot
            and t - self._last_contact >= rest.window_s - 1e-9
            and stable
            and window[-1] == UNKNOT
        )
        knot_set = self._knot is not None and t - self._knot[0] >= p.knot_set_s - 1e-9
        held = (  # judged at a verdict sample: the outcome's verdict is that sample's
            sampled
            and p.unknot_held_s is not None
            and self._unknot_since is not None
            and t - self._unknot_since >= p.unknot_held_s - 1e-9
        )
        if (quiet and stable) or free or knot_set or held or cap or fixed:
            self._finish(t, elapsed, quiet, free, knot_set, held, judge)
            return True
        return False

    def _window(self, t: float) -> list[str]:
        """The verdicts of the last ``rest.window_s``."""
        w = self.params.rest.window_s
        return [v for tv, v in zip(self._t, self._v, strict=True) if tv >= t - w - 1e-9]

    def _track_knot(self, t: float, verdict: str, knot_region) -> None:
        """Follow a knot's shape: keep the reference while the verdict and the shape hold,
        start a new one from the current self-contact span otherwise."""
        if verdict == UNKNOT:
            self._knot = None
            return
        span, vertices = knot_region()
        if self._knot is not None:
            _, kind, (lo, hi), ref = self._knot
            if kind == verdict and shape_change(ref, vertices[lo : hi + 1]) <= self._tol:
                return
        self._knot = None
        if span is not None:
            lo, hi = span
            self._knot = (t, verdict, (lo, hi), np.array(vertices[lo : hi + 1], dtype=float))

    def _finish(self, t, elapsed, quiet, free, knot_set, held, judge) -> None:
        if not self._t or self._t[-1] < t - 1e-9:
            self._t.append(t)
            self._v.append(judge())
        final = self._window(t)
        settled = quiet and len(final) >= 2 and len(set(final)) == 1
        speeds = [s for ts, s in self._speeds]
        self._done = SettleOutcome(
            settled=bool(settled),
            contact_free=bool(free and not settled),
            settle_s=float(elapsed),
            verdict=self._v[-1],
            free_end_speed_m_s=float(np.nanmax(speeds)) if speeds else float("nan"),
            history_t=tuple(self._t),
            history=tuple(self._v),
            knot_set=bool(knot_set and not settled and not free),
            unknot_held=bool(held and not settled and not free and not knot_set),
        )

    @property
    def outcome(self) -> SettleOutcome:
        """How the settle ended (only after :meth:`observe` returned True)."""
        if self._done is None:
            raise ConfigError("outcome", "the settle has not ended yet (observe more samples)")
        return self._done


def start_with_sway(
    rng: np.random.Generator,
    criterion: RestCriterion,
    length: float,
    sway: float,
    azimuth: float,
    scale: float = 1.0,
) -> tuple[float, float, float]:
    """A settled start (:func:`settled_start`, drawn from ``rng``) plus an extra tilt.

    Small tilts add as vectors: (sway, azimuth) + (tilt, psi) -> (angle, direction). The start's
    rate acts along psi; the part along the composed direction is kept, the part across it
    (below 0.01 rad/s at the default criterion) is dropped.

    Args:
        rng: Source of the settled start.
        criterion: The rest criterion.
        length: Rope length [m].
        sway: Extra tilt [rad] (>= 0).
        azimuth: Its direction about world z [rad].
        scale: The settled start's share of the criterion (:func:`settled_start`).

    Returns:
        ``(angle [rad] >= 0, azimuth [rad], rate [rad/s])`` for ``set_hanging``.
    """
    tilt, rate, psi = settled_start(rng, criterion, length, scale)
    tx = sway * math.cos(azimuth) + tilt * math.cos(psi)
    ty = sway * math.sin(azimuth) + tilt * math.sin(psi)
    angle, direction = math.hypot(tx, ty), math.atan2(ty, tx)
    return angle, direction, rate * math.cos(psi - direction)

"""How the ILC loop runs: :class:`ILCParams` and the confirmed-success rule's parser."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from flyknot.errors import ConfigError, check_int, check_nonnegative, check_positive
from flyknot.limits import JointLimits
from flyknot.options import INLINE
from learner.jacobians import jacobian_kind
from learner.rope_model import RopeModelParams
from learner.steps import DampingParams, step_kind
from learner.update import UpdateSettings


@dataclass(frozen=True)
class PlateauParams:
    """The plateau stop rule's settings (:class:`learner.stops.Plateau`).

    Attributes:
        patience: Counted trials without progress after which the loop stops (0: never).
        noise: Trial-to-trial noise floor of the critical cost [-]: a trial makes progress
            when it lowers the best cost by more than this. Default 0.05, three standard
            deviations of one command's cost over varied plays near the reachable floor
            (0.104 +- 0.016 over 12 plays, rope 1, ``fast-paced``; docs/measuring-sticks.md).
    """

    patience: int = 0
    noise: float = 0.05

    def __post_init__(self) -> None:
        check_int("plateau.patience", self.patience)
        check_nonnegative("plateau.noise", self.noise)


@dataclass(frozen=True)
class ExploreParams:
    """The exploring step's settings (:class:`learner.stops.Explore`).

    Attributes:
        size: RMS of the random offset r over the 56 arm knot entries [rad]; 0: no exploring
            (the default, and the paper's).
        patience: Counted trials in a row near the noise floor without a new lowest cost
            after which the next command explores (>= 1).
        band: Near the noise floor: a measured cost within (1 + band) of the lowest; a
            larger rise, or a trial that measured nothing, starts the count again (the
            damped step's to mend) (>= 0). 0.5: about three relative standard deviations of
            one command's cost over the lab's variation, 0.15 each (``damping.noise``).
        w_control: The QP's control weight of an exploring step [1/rad^2] (the damped step's
            first lambda, :class:`learner.steps.DampingParams`).
        seed: Seed of the offsets: trial k's is drawn from ``(seed, k)``.
    """

    size: float = 0.0
    patience: int = 2
    band: float = 0.5
    w_control: float = 0.25
    seed: int = 0

    def __post_init__(self) -> None:
        check_nonnegative("explore.size", self.size)
        check_nonnegative("explore.band", self.band)
        check_positive("explore.w_control", self.w_control)
        check_int("explore.patience", self.patience, 1)
        check_int("explore.seed", self.seed)


def parse_confirm(value: object, stop_at_success: bool = True) -> tuple[int, int] | None:
    """The confirmed-success rule ``(k, n)`` from ``[k, n]``, ``(k, n)`` or ``"k/n"`` (or None).

    Raises:
        ConfigError: Not two integers with 1 <= k <= n, or ``stop_at_success`` is off.
    """
    if value is None:
        return None
    c = value
    if isinstance(c, str) and "/" in c:
        try:
            c = tuple(int(v) for v in c.split("/"))
        except ValueError:
            c = value
    if isinstance(c, list | tuple):
        c = tuple(c)
    ok = isinstance(c, tuple) and len(c) == 2
    ok = ok and all(isinstance(v, int) and not isinstance(v, bool) for v in c)
    if not ok or not 1 <= c[0] <= c[1]:
        raise ConfigError("confirm", f"must be [k, n] (or k/n) with 1 <= k <= n, got {value!r}")
    if not stop_at_success:
        raise ConfigError("confirm", "needs stop_at_success = true")
    return c


@dataclass(frozen=True)
class ILCParams:
    """How the learning loop runs.

    Its options, and those of its ``update`` beside them, are what a scenario's runs and
    ``flyknot run --set`` may give (:func:`flyknot.options.from_mapping`).

    Attributes:
        max_trials: Trials at most (tracking-failure repeats not counted); 0 plays the
            initial command once and keeps it (tracking alone).
        stop_at_success: Stop at the first tied knot (the paper does).
        converged_knot: Stop at a knot only once the learner has converged on it: its trial's
            critical cost is not below (1 - ``damping.noise``) times the lowest measured before
            it (the step that tied no longer lowered the cost beyond the trial-to-trial
            noise), or it is the last trial. A knot reached while the cost still falls beyond
            the noise is counted (the run's first knot) and learning goes on from it; a run
            that then runs out of trials keeps the command of its last knot. It changes the
            stop at a knot, so it does nothing without ``stop_at_success`` or with
            ``confirm``.
        tracking_retries: Repeats of a trial whose markers were lost before t_c.
        gain: ILC learning gain alpha in (0, 1]: the command moves by alpha dkappa (the
            paper: 1).
        rope_model: The learner's rope model (default: the paper's).
        confirm: Confirmed-success stop rule ``(k, n)``, or None for the paper's (stop at the
            first knot). With it, a command that ties is played again until n trials of it
            have run (the tying one included; every repeat is a trial and counts towards
            ``max_trials``); the run stops when k of them tie, and otherwise learns on from the
            last of them. Needs ``stop_at_success``. A file or the command line may give
            ``[k, n]`` or ``"k/n"``.
        safeguard: Reject an update whose trial measured a higher critical-point cost than
            the best trial so far: the next command is the best trial's command moved by its
            own update, shrunk by 1/2 per consecutive rejection (the paper has none).
        average: Plays of each command before an update (>= 1; the paper: 1); the update
            uses the mean critical-point error of the plays (each play is a trial).
        average_first: Plays of the initial command before the first update (>= 1; None:
            ``average``), the update on their mean error; the damped step weighs their mean
            cost and steps from it again on their mean error. The first update is the longest
            step, and the one a single trial's variation moves most (``docs/rope-model.md``,
            "The lab's trial-to-trial variation").
        step: How far each update moves the command (:data:`learner.steps.STEPS`):
            ``"gain"`` (the paper's fixed gain) or ``"damped"`` (Levenberg-Marquardt on the
            measured cost, back to the best command when the cost rose).
        damping: The damped step's settings (``step = "damped"``).
        plateau: Stop when the best measured cost has not fallen by more than the noise
            floor in ``patience`` counted trials (off by default; the paper has none).
        explore: At the noise floor, step from the best command toward a random offset that
            the model says keeps the objective's rope states (off by default; the paper has
            none).
        step_halvings: Halvings of an update's step at most while its command breaks a
            joint limit on its samples (the QP holds torque limits to first order only); the
            last is taken anyway and the cell's controller decides (>= 0).
        update: How every update forms and solves its QP (objective, weights, trust region,
            solver...: :class:`learner.update.UpdateSettings`; its options sit beside these).
            Its joint limits are the cell's, given to :func:`learner.ilc.learn`.
    """

    max_trials: int = 10
    stop_at_success: bool = True
    converged_knot: bool = False
    tracking_retries: int = 2
    gain: float = 1.0
    rope_model: RopeModelParams = field(default_factory=RopeModelParams)
    confirm: tuple[int, int] | None = None
    safeguard: bool = False
    average: int = 1
    average_first: int | None = None
    step: str = "gain"
    damping: DampingParams = field(default_factory=DampingParams)
    plateau: PlateauParams = field(default_factory=PlateauParams)
    explore: ExploreParams = field(default_factory=ExploreParams)
    step_halvings: int = 4
    update: UpdateSettings = field(default_factory=UpdateSettings, metadata=INLINE)

    def __post_init__(self) -> None:
        for name in ("max_trials", "tracking_retries", "step_halvings"):
            check_int(name, getattr(self, name))
        if isinstance(self.gain, bool) or not (
            isinstance(self.gain, (int, float)) and 0 < self.gain <= 1
        ):
            raise ConfigError("gain", f"must lie in (0, 1], got {self.gain!r}")
        check_int("average", self.average, 1)
        if self.average_first is not None:
            check_int("average_first", self.average_first, 1)
        if self.safeguard and (self.average_first or 1) > 1:
            raise ConfigError(
                "average_first", "the safeguard steps by a trial's own update: it takes no "
                "average_first > 1"
            )  # fmt: skip
        if not isinstance(self.safeguard, bool):
            raise ConfigError("safeguard", f"must be true or false, got {self.safeguard!r}")
        if not isinstance(self.stop_at_success, bool):
            raise ConfigError(
                "stop_at_success", f"must be true or false, got {self.stop_at_success!r}"
            )
        if not isinstance(self.converged_knot, bool):
            raise ConfigError(
                "converged_knot", f"must be true or false, got {self.converged_knot!r}"
            )
        step_kind(self.step)
        if self.step == "damped" and (self.safeguard or self.average > 1):
            raise ConfigError(
                "step", "'damped' returns to the best command itself: it takes no safeguard "
                "or average > 1"
            )  # fmt: skip
        for name, cls in (
            ("rope_model", RopeModelParams),
            ("update", UpdateSettings),
            ("damping", DampingParams),
            ("plateau", PlateauParams),
            ("explore", ExploreParams),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(name, f"must be a {cls.__name__}, got {getattr(self, name)!r}")
        if jacobian_kind(self.update.jacobian).learns and self.average > 1:
            raise ConfigError(
                "jacobian",
                f"{self.update.jacobian!r} learns from every play: it takes no average > 1",
            )
        object.__setattr__(self, "confirm", parse_confirm(self.confirm, self.stop_at_success))

    @property
    def trials(self) -> int:
        """Trials the loop plays at most: ``max_trials``, and 1 for tracking alone (0)."""
        return max(1, self.max_trials)

    def update_settings(self, limits: JointLimits | None) -> UpdateSettings:
        """The settings of every update of the run, with ``limits`` on the updated commands."""
        return replace(self.update, limits=limits)

"""How the ILC loop runs: :class:`ILCParams` and the confirmed-success rule's parser."""

from __future__ import annotations

from dataclasses import dataclass, field

from flyknot.errors import ConfigError, check_choice, check_positive
from flyknot.limits import JointLimits
from learner.inverse_qp import BACKENDS, InverseModelWeights
from learner.rope_model import RopeModelParams
from learner.update import OBJECTIVES, UpdateSettings


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

    Attributes:
        max_trials: Trials at most (tracking-failure repeats not counted).
        stop_at_success: Stop at the first tied knot (the paper does).
        objective: ``"critical"`` (the paper's) or ``"equal"`` (equally weighted baseline).
        backend: QP solver, ``"clarabel"`` or ``"osqp"``.
        tracking_retries: Repeats of a trial whose markers were lost before t_c.
        follow_through: Include the follow-through fingertip tracking term.
        gain: ILC learning gain alpha in (0, 1]: the command moves by alpha dkappa (the
            paper: 1).
        weights: Inverse-model weights (default: the paper's).
        rope_model: The learner's rope model (default: the paper's).
        trust_region: Largest change of any arm knot per update [rad] (a box in the QP),
            or None for none (the paper's).
        confirm: Confirmed-success stop rule ``(k, n)``, or None for the paper's (stop at the
            first knot). With it, a command that ties is played again until n trials of it
            have run (the tying one included; every repeat is a trial and counts towards
            ``max_trials``); the run stops when k of them tie, and otherwise learns on from the
            last of them. Needs ``stop_at_success``.
        safeguard: Reject an update whose trial measured a higher critical-point cost than
            the best trial so far: the next command is the best trial's command moved by its
            own update, shrunk by 1/2 per consecutive rejection (the paper has none).
        average: Plays of each command before an update (>= 1; the paper: 1); the update
            uses the mean critical-point error of the plays (each play is a trial).
    """

    max_trials: int = 10
    stop_at_success: bool = True
    objective: str = "critical"
    backend: str = "clarabel"
    tracking_retries: int = 2
    follow_through: bool = True
    gain: float = 1.0
    weights: InverseModelWeights = field(default_factory=InverseModelWeights)
    rope_model: RopeModelParams = field(default_factory=RopeModelParams)
    trust_region: float | None = None
    confirm: tuple[int, int] | None = None
    safeguard: bool = False
    average: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.max_trials, int) or self.max_trials < 1:
            raise ConfigError("max_trials", f"must be an integer >= 1, got {self.max_trials!r}")
        if not isinstance(self.tracking_retries, int) or self.tracking_retries < 0:
            raise ConfigError(
                "tracking_retries", f"must be an integer >= 0, got {self.tracking_retries!r}"
            )
        check_choice("objective", self.objective, OBJECTIVES)
        check_choice("backend", self.backend, BACKENDS)
        if not (isinstance(self.gain, (int, float)) and 0 < self.gain <= 1):
            raise ConfigError("gain", f"must lie in (0, 1], got {self.gain!r}")
        if self.trust_region is not None:
            check_positive("trust_region", self.trust_region)
        if isinstance(self.average, bool) or not isinstance(self.average, int) or self.average < 1:
            raise ConfigError("average", f"must be an integer >= 1, got {self.average!r}")
        if not isinstance(self.safeguard, bool):
            raise ConfigError("safeguard", f"must be true or false, got {self.safeguard!r}")
        object.__setattr__(self, "confirm", parse_confirm(self.confirm, self.stop_at_success))

    def update_settings(self, limits: JointLimits | None) -> UpdateSettings:
        """The settings of every update of the run, with ``limits`` on the updated commands."""
        return UpdateSettings(
            objective=self.objective,
            weights=self.weights,
            limits=limits,
            follow_through=self.follow_through,
            trust_region=self.trust_region,
            backend=self.backend,
        )

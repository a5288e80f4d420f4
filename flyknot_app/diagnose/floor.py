"""The reachable floor: the lowest critical-point cost a command within the limits reaches.

A measuring stick (``flyknot diagnose floor``): if the floor for a demonstration is far above
the cost at which knots happen, its rope state at t_c is out of the arm's reach whatever a
learner does. The search is Levenberg-Marquardt on the critical cost in the simulated lab
without variation, with the lab's own Jacobian (:class:`flyknot_app.diagnose.oracle.LabJacobian`):

    M_i = dx(t_c)/dkappa at kappa_i                      (66, 80), measured
    dk  = argmin ||M_i dk - e_i||_Q^2 + lambda ||dk_arm||^2
          s.t. every joint limit row of kappa_i - dk (:mod:`learner.limit_rows`), rest at both
          ends, constant base                             the update's QP, no follow-through
    kappa_{i+1} = kappa_i - dk   if its measured cost is lower, lambda <- lambda / shrink
                  kappa_i        else, lambda <- lambda * grow (at most ``tries`` times)

with e_i = x(kappa_i; t_c) - x_demo(t_c) and Q the critical weights of the objective
(a run's own; for a demonstration alone the scenarios', w_crit_vel 0.1). The budget
counts the lab's plays (a Jacobian is 91 of them, each cut shortly after t_c). The result
splits the floor into its position and velocity parts and per-marker errors, so a miss says
which part of the rope state the arm cannot reach.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from flyknot.errors import ConfigError, check_positive
from flyknot.limits import JointLimits
from flyknot_app.diagnose.oracle import LabJacobian, OracleParams, knot_groups

N_MARKERS = 11


@dataclass(frozen=True)
class FloorParams:
    """The floor search's settings.

    Attributes:
        budget: Plays of the lab at most (>= 1 Jacobian: 91 plays).
        damping: Initial lambda (the QP's control weight) [1/rad^2].
        grow: lambda's factor after a step that did not lower the cost (> 1).
        shrink: lambda's divisor after one that did (> 1).
        tries: Steps tried per Jacobian (>= 1).
        oracle: How each Jacobian is measured.
    """

    budget: int = 1500
    damping: float = 0.05
    grow: float = 4.0
    shrink: float = 3.0
    tries: int = 8
    oracle: OracleParams = field(default_factory=OracleParams)

    def __post_init__(self) -> None:
        for name in ("budget", "tries"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(name, f"must be an integer >= 1, got {value!r}")
        check_positive("damping", self.damping)
        for name in ("grow", "shrink"):
            value = getattr(self, name)
            check_positive(name, value)
            if value <= 1:
                raise ConfigError(name, f"must be > 1, got {value!r}")


@dataclass(frozen=True)
class FloorResult:
    """What the floor search found.

    Attributes:
        costs: Critical cost of the accepted command after each Jacobian (first: kappa_0).
        plays: The lab's plays spent.
        knots: The floor's command (10, 8).
        cost: Its critical cost ||e||_Q^2.
        position_part: w_crit_pos ||e_p||^2, the marker positions' share.
        velocity_part: w_crit_vel ||e_v||^2, the marker velocities' share.
        marker_position_error: |e_p| per marker (11,) [m], held end first.
        marker_velocity_error: |e_v| per marker (11,) [m/s].
        demo_marker_speed: |v_demo| per marker at t_c (11,) [m/s], for scale.
        stopped_because: ``"budget"`` or ``"no lower cost"`` (every try of a Jacobian rose).
        w_crit_pos: The cost's marker position weight [1/m^2].
        w_crit_vel: The cost's marker velocity weight [s^2/m^2].
    """

    costs: tuple[float, ...]
    plays: int
    knots: np.ndarray
    cost: float
    position_part: float
    velocity_part: float
    marker_position_error: tuple[float, ...]
    marker_velocity_error: tuple[float, ...]
    demo_marker_speed: tuple[float, ...]
    stopped_because: str
    w_crit_pos: float
    w_crit_vel: float

    def to_json(self) -> dict:
        """Plain data (the knots as nested lists)."""
        out = asdict(self)
        out["knots"] = np.asarray(self.knots).tolist()
        return out


def cost_parts(err: np.ndarray, w_pos: float, w_vel: float) -> tuple[float, float]:
    """(w_pos |e_p|^2, w_vel |e_v|^2) of a critical error e = [e_p (33,), e_v (33,)]."""
    err = np.asarray(err, dtype=float)
    half = err.size // 2
    return float(w_pos * err[:half] @ err[:half]), float(w_vel * err[half:] @ err[half:])


def _error(record, knots: np.ndarray, target) -> np.ndarray | None:
    """x(t_c) - x_demo(t_c) (66,) of an oracle play, or None when it faulted before t_c."""
    from flyknot.errors import RecordError
    from learner.critical_state import critical_state_from_record

    try:
        return critical_state_from_record(record, target.t_c, knots[7:, 0]) - target.x_c
    except RecordError:
        return None


class _Search:
    """The search's state: the accepted command, its record and error, and the damping."""

    def __init__(self, oracle: LabJacobian, target, robot, rope_model, limits, params, weights):
        self.oracle, self.target, self.robot = oracle, target, robot
        self.rope_model, self.limits, self.params = rope_model, limits, params
        self.weights = weights
        self.lam = params.damping

    def cost(self, err: np.ndarray | None) -> float:
        from learner.ilc_step import critical_cost

        return float("inf") if err is None else critical_cost(err, self.weights)

    def step(self, knots: np.ndarray, record, M: np.ndarray) -> np.ndarray | None:
        """kappa - dk of the damped QP at lambda (None if the QP did not solve)."""
        from learner.bezier import BezierCommand
        from learner.ilc_step import safe_step
        from learner.update import UpdateSettings, ilc_update

        settings = UpdateSettings(
            weights=replace(self.weights, w_control=self.lam),
            limits=self.limits,
            follow_through=False,
        )
        command = BezierCommand(knots, self.target.T)
        res = ilc_update(
            record, command, self.target, self.robot, self.rope_model, settings, jacobian=M
        )
        if not res.solved:
            return None
        return safe_step(knots, np.asarray(res.dkappa), self.target.T, self.robot, self.limits)


def reachable_floor(
    lab_params,
    target,
    knots0: np.ndarray,
    robot,
    rope_model,
    params: FloorParams = FloorParams(),
    *,
    limits: JointLimits = JointLimits(),  # noqa: B008 - frozen value
    weights=None,
    on_iteration=None,
) -> FloorResult:
    """The Levenberg-Marquardt search of the module docstring from ``knots0``.

    Args:
        lab_params: The simulated lab (:class:`flyknot_sim.lab.LabParams`); its variation
            is switched off.
        target: The demonstration target (:class:`learner.target.DemoTarget`).
        knots0: The start (10, 8), e.g. the demonstration's initial guess.
        robot: The learner's robot model (limits, torques).
        rope_model: The learner's rope model parameters (only its step is used).
        params: The search's settings.
        limits: Joint limits every command keeps.
        weights: The objective's QP weights (:class:`learner.inverse_qp.InverseModelWeights`;
            its critical part is the cost, its control weight is replaced by the damping).
            None: the scenarios' (:func:`flyknot_app.learner_settings.scenario_weights`).
        on_iteration: Called with (plays, cost) after each Jacobian.

    Returns:
        The :class:`FloorResult`.
    """
    from flyknot_app.learner_settings import scenario_weights

    weights = scenario_weights() if weights is None else weights
    oracle = LabJacobian(lab_params, target.t_c, params.oracle)
    search = _Search(oracle, target, robot, rope_model, limits, params, weights)
    knots = np.asarray(knots0, dtype=float)
    record = oracle.play(knots, target.T)
    err = _error(record, knots, target)
    if err is None:
        raise ConfigError("knots0", "the start command faults before t_c in the lab")
    costs = [search.cost(err)]
    per_jacobian = 1 + 2 * len(knot_groups())
    stopped = "budget"
    while oracle.plays + per_jacobian + 1 <= params.budget:
        M = oracle(knots, target.T)
        for _ in range(params.tries):
            new = search.step(knots, record, M)
            new_record = None if new is None else oracle.play(new, target.T)
            new_err = None if new is None else _error(new_record, new, target)
            if search.cost(new_err) < costs[-1]:
                knots, record, err = new, new_record, new_err
                search.lam = search.lam / params.shrink
                break
            search.lam *= params.grow
        else:
            costs.append(costs[-1])
            stopped = "no lower cost"
            break
        costs.append(search.cost(err))
        if on_iteration is not None:
            on_iteration(oracle.plays, costs[-1])
    return _result(costs, oracle.plays, knots, err, target, stopped, weights)


def _result(costs, plays, knots, err, target, stopped, w) -> FloorResult:
    """The :class:`FloorResult` of the accepted command ``knots`` with error ``err``, its cost
    split with the weights ``w``."""
    pos, vel = cost_parts(err, w.w_crit_pos, w.w_crit_vel)
    e = np.asarray(err).reshape(2, N_MARKERS, 3)
    v_demo = np.asarray(target.x_c).reshape(2, N_MARKERS, 3)[1]
    return FloorResult(
        costs=tuple(float(c) for c in costs),
        plays=int(plays),
        knots=np.asarray(knots),
        cost=pos + vel,
        position_part=pos,
        velocity_part=vel,
        marker_position_error=tuple(np.linalg.norm(e[0], axis=1).round(4).tolist()),
        marker_velocity_error=tuple(np.linalg.norm(e[1], axis=1).round(3).tolist()),
        demo_marker_speed=tuple(np.linalg.norm(v_demo, axis=1).round(3).tolist()),
        stopped_because=stopped,
        w_crit_pos=float(w.w_crit_pos),
        w_crit_vel=float(w.w_crit_vel),
    )


__all__ = ["FloorParams", "FloorResult", "cost_parts", "reachable_floor"]

"""A gymnasium environment for comparing learners on the flying knot, trial by trial.

One environment step is one trial in the simulated lab, as in iterative learning: the agent
proposes a change of the command's Bezier knots, the lab plays the command with its
trial-to-trial variation, and the agent observes what the learner would observe (the rope
state error at the critical time, from the motion-capture markers) plus the knots.

* Observation (146,), bounded: the critical-point error x(t_c) - x_demo(t_c) in the
  demonstration frame (66: 11 marker positions [m], clipped to +-:data:`POS_BOUND`, then
  velocities [m/s], clipped to +-:data:`VEL_BOUND`; zeros when the trial faulted or lost
  tracking before t_c) followed by the current knots (80: 7 joint rows [rad] within the
  paper's joint limits widened by :data:`KNOT_MARGIN`, so the paper's initial guess is kept
  as it is, 3 base-offset rows [m] within +-:data:`BASE_BOUND`; 8 knots each, row-major).
* Action (80,) in [-1, 1]: the knot change divided by ``action_scale`` (joint rows [rad],
  base rows [m]); the base rows' change is averaged over the knots (the base stays fixed
  within a command) and the first/last two knots of each joint row move together (the
  command stays at rest at both ends); the knots are then clipped to the bounds above. An
  action of the wrong shape, or with NaN or infinity, is refused before anything changes.
* ``reset(seed=s)`` restarts the lab's trial-to-trial variation at trial 0 of seed ``s``
  (trial i of an episode meets the same variation for the same seed); ``reset()`` without
  a seed continues the variation sequence.
* ``info``: the trial number, fault, knot, cost, ``failure`` (the failure class of
  :mod:`flyknot_app.anatomy.diagnosis`: ``success``, ``shaken_loose``, ...) and ``record`` (the
  saved trial record's path under ``record_dir``, a temporary directory by default).
* Reward: -(critical-point cost ||x(t_c) - x_demo(t_c)||^2_Q) + ``knot_bonus`` when the
  trial's verdict is a knot in the hanging rope (:mod:`flyknot.verdict`; a rope wrapped at
  the grip earns no bonus); ``fault_penalty`` replaces the cost when the robot faults or tracking
  is lost before t_c.
* The episode terminates at the first knot and is truncated after ``max_trials`` trials.

The initial command is the paper's initial guess for the demonstration (cached per env).
Defaults as the scenario files (:mod:`flyknot_app.learner_settings`): the person's demonstration
``fast-paced`` with the window (follow-through t_f - t_c = 0.25 s, t_0 at the start of the
hand motion; ``window=(0.035, 0.05)`` is the paper's) and the scenarios' critical weights
(w_crit_vel 0.1; ``weights=InverseModelWeights()`` scores with the paper's), so that a learner
here starts from ILC's initial command and is scored on ILC's objective.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from flyknot.constants import N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import ConfigError, check_positive
from flyknot.limits import JointLimits
from flyknot_app.learner_settings import SCENARIO_DEMO, SCENARIO_WINDOW, scenario_weights
from learner.inverse_qp import InverseModelWeights

POS_BOUND = 5.0
"""Bound of the marker position errors in the observation [m]."""
VEL_BOUND = 100.0
"""Bound of the marker velocity errors in the observation [m/s]."""
BASE_BOUND = 2.0
"""Bound of the base-offset knots [m]: the robot base's position in the demonstration frame,
whose hand starts 1.5 m above the floor (the hand lab's), so the base sits up to about 1.3 m
above the demonstration's origin (`fast-paced`'s initial guess: 1.31 m)."""
KNOT_MARGIN = 0.5
"""How far the joint rows' knots may lie beyond the paper's joint limits [rad]: a Bezier
command stays within its knots' range, not the knots within the command's, and the paper's
initial guess for the robot demonstration has a knot 0.017 rad beyond joint 2's limit (the
command's limits are the lab controller's to check)."""
N_ERR = 66

_KNOTS0: dict[tuple, np.ndarray] = {}


def paper_initial_knots(
    demo: str, window: tuple[float, float], base_height: float, robot=None
) -> np.ndarray:
    """The paper's initial guess (10, 8) for ``demo`` with ``window``, as ILC starts from it
    (:func:`flyknot_app.runner.initial_knots`), computed once per process (about 15 s)."""
    import tempfile
    from pathlib import Path

    from flyknot_app.runner import initial_knots
    from learner.kinematics import RobotModel
    from learner.rope_model import RopeModelParams

    key = (demo, tuple(float(w) for w in window), float(base_height))
    if key not in _KNOTS0:
        robot = RobotModel.from_mjcf() if robot is None else robot
        with tempfile.TemporaryDirectory() as tmp:
            k0, _ = initial_knots(
                demo, Path(tmp), robot, RopeModelParams().dt, float(base_height), key[1]
            )
        _KNOTS0[key] = np.asarray(k0, dtype=float)
    return _KNOTS0[key].copy()


def score_trial(
    record, target, base_offset: np.ndarray, weights, fault_penalty: float
) -> tuple[np.ndarray, float, dict[str, Any]]:
    """The learner's view of a finished trial, the terms of both environments' rewards.

    Returns:
        ``(err, cost, info)``: the critical-point error x(t_c) - x_demo(t_c) (66,) in the
        demonstration frame (``base_offset`` (3,) [m]: the base's position there; zeros when
        the trial faulted or lost tracking before t_c), its cost ||err||^2_Q
        (:func:`learner.ilc.critical_cost`; ``fault_penalty`` instead when the trial faulted or
        lost tracking) and ``info``: ``fault``, ``knot``, ``verdict`` (the verdict's class,
        :mod:`flyknot.verdict`; ``"knot"`` is the success), ``failure`` (the class of
        :mod:`flyknot_app.anatomy.diagnosis`), ``cost`` and, when tracking was lost,
    ``tracking_lost``.
    """
    from flyknot.errors import RecordError
    from flyknot_app.anatomy.diagnosis import diagnose
    from learner.critical_state import critical_state_from_record
    from learner.ilc import critical_cost

    info: dict[str, Any] = {
        "fault": record.fault,
        "knot": record.knot,
        "verdict": None if record.verdict is None else record.verdict.klass,
        "failure": diagnose(record, t_c=target.t_c).label,
    }
    err = np.zeros(N_ERR)
    cost = float(fault_penalty)
    if record.fault is None:
        try:
            err = critical_state_from_record(record, target.t_c, base_offset) - target.x_c
            cost = critical_cost(err, weights)
        except RecordError as e:
            err = np.zeros(N_ERR)
            info["tracking_lost"] = str(e)
    info["cost"] = cost
    return err, cost, info


def checked_action(action, shape: tuple[int, ...]) -> np.ndarray:
    """``action`` as a float array of ``shape``, finite; checked before an env changes anything.

    Raises:
        ConfigError: Wrong shape, or NaN / infinity.
    """
    a = np.asarray(action, dtype=float)
    if a.shape != shape:
        raise ConfigError("action", f"must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError("action", "must be finite (NaN or infinity given); nothing changed")
    return a


class FlyknotEnv(gym.Env):
    """Trial-level flying-knot environment on the simulated lab."""

    metadata = {"render_modes": ()}  # noqa: RUF012 - gymnasium reads this mapping

    def __init__(
        self,
        rope: int | str = 1,
        demo: str = SCENARIO_DEMO,
        *,
        window: tuple[float, float] = SCENARIO_WINDOW,
        weights: InverseModelWeights | None = None,
        max_trials: int = 10,
        action_scale: float = 0.05,
        knot_bonus: float = 100.0,
        fault_penalty: float = 100.0,
        settle_s: float | None = None,
        seed: int = 0,
        ropes: str | None = None,
        record_dir: str | None = None,
    ):
        """``rope``: a paper rope id 1..7 or a rope's name (the paper's, or one of ``ropes``,
        a user's ropes file; see ``assets/ropes_example.toml``); ``record_dir``: where each
        trial's record is saved (a temporary directory if None); ``weights``: the QP weights
        whose critical part scores a trial (None: the scenarios', :func:`scenario_weights`)."""
        super().__init__()
        from flyknot_app.runner import prepare_target
        from flyknot_sim.lab import LabParams, SimLab
        from learner.kinematics import RobotModel
        from learner.rope_model import RopeModelParams

        self._weights = scenario_weights() if weights is None else weights
        if not isinstance(self._weights, InverseModelWeights):
            raise ConfigError("weights", f"must be an InverseModelWeights, got {weights!r}")
        check_positive("action_scale", action_scale)
        if not isinstance(max_trials, int) or isinstance(max_trials, bool) or max_trials < 1:
            raise ConfigError("max_trials", f"must be an integer >= 1, got {max_trials!r}")
        self.max_trials = max_trials
        self.action_scale = float(action_scale)
        self.knot_bonus = float(knot_bonus)
        self.fault_penalty = float(fault_penalty)
        self._lab = SimLab(LabParams(rope=rope, seed=seed, settle_s=settle_s, ropes=ropes))
        self._robot = RobotModel.from_mjcf()
        self._window = (float(window[0]), float(window[1]))
        _, self.target = prepare_target(demo, RopeModelParams().dt, self._window)
        self._demo = demo
        self._knots0: np.ndarray | None = None
        limits = JointLimits()
        self._knot_lo = np.concatenate(
            [
                np.repeat(limits.q_min[:, None] - KNOT_MARGIN, N_KNOTS, 1),
                np.full((N_ROWS - N_JOINTS, N_KNOTS), -BASE_BOUND),
            ]
        )
        self._knot_hi = np.concatenate(
            [
                np.repeat(limits.q_max[:, None] + KNOT_MARGIN, N_KNOTS, 1),
                np.full((N_ROWS - N_JOINTS, N_KNOTS), BASE_BOUND),
            ]
        )
        err_hi = np.concatenate([np.full(N_ERR // 2, POS_BOUND), np.full(N_ERR // 2, VEL_BOUND)])
        self._err_hi = err_hi
        self.observation_space = gym.spaces.Box(
            np.concatenate([-err_hi, self._knot_lo.ravel()]),
            np.concatenate([err_hi, self._knot_hi.ravel()]),
            dtype=np.float64,
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (N_ROWS * N_KNOTS,), np.float64)
        self.knots = np.zeros((N_ROWS, N_KNOTS))
        self.trials = 0
        if record_dir is None:
            import tempfile

            self._tmp = tempfile.TemporaryDirectory(prefix="flyknot_env_")
            record_dir = self._tmp.name
        from pathlib import Path

        self.record_dir = Path(record_dir)

    # ------------------------------------------------------------------------------------
    def initial_knots(self) -> np.ndarray:
        """The paper's initial guess for the demonstration (computed once per process)."""
        if self._knots0 is None:
            self._knots0 = paper_initial_knots(
                self._demo, self._window, float(self._lab.base_pose[2]), self._robot
            )
        return self._knots0.copy()

    def _trial(self) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        from learner.bezier import BezierCommand

        # Named by the lab's variation (seed, trial index): the same seed replays the same trial.
        lab_trial = self._lab.trial_index
        stem = self.record_dir / f"seed_{self._lab.params.seed}" / f"trial_{lab_trial:05d}"
        rec = self._lab.run(BezierCommand(self.knots, self.target.T).joint_command())
        self.trials += 1
        rec.save(stem)
        err, cost, info = score_trial(
            rec, self.target, self.knots[N_JOINTS:, 0], self._weights, self.fault_penalty
        )
        info = {**info, "trial": self.trials, "record": str(stem.with_suffix(".json"))}
        success = rec.succeeded
        reward = -cost + (self.knot_bonus if success else 0.0)
        obs = np.concatenate([np.clip(err, -self._err_hi, self._err_hi), self.knots.ravel()])
        return obs, float(reward), success, info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode from the initial command: one trial, its observation and info."""
        super().reset(seed=seed)
        if seed is not None:
            from dataclasses import replace

            self._lab.params = replace(self._lab.params, seed=int(seed))
            self._lab.trial_index = 0
        knots0 = self.initial_knots()
        if np.any(knots0 < self._knot_lo) or np.any(knots0 > self._knot_hi):
            raise ConfigError(
                "demo", f"{self._demo!r}: its initial command lies outside the env's knot bounds"
            )
        self.knots = knots0
        self.trials = 0
        obs, _, _, info = self._trial()
        return obs, info

    def restart_variation(self) -> None:
        """Make the next trial the lab's trial 0 of the current seed again (the one
        :meth:`reset` played), for paired comparisons: a learner's trial i then meets the
        variation that ILC's trial i meets in ``flyknot run`` with the same seed."""
        self._lab.trial_index = 0

    def constrain(self, knots: np.ndarray) -> np.ndarray:
        """``knots`` (10, 8) made a valid command: each base row constant, each joint row at
        rest at both ends (knots 0 and 1, 6 and 7 equal), all within the bounds."""
        k = np.array(knots, dtype=float)
        if k.shape != (N_ROWS, N_KNOTS) or not np.all(np.isfinite(k)):
            raise ConfigError("knots", f"must be finite, shape {(N_ROWS, N_KNOTS)}, got {k.shape}")
        k[N_JOINTS:] = k[N_JOINTS:].mean(axis=1, keepdims=True)
        k[:N_JOINTS, 1] = k[:N_JOINTS, 0]
        k[:N_JOINTS, -1] = k[:N_JOINTS, -2]
        return np.clip(k, self._knot_lo, self._knot_hi)

    def play(self, knots: np.ndarray):
        """Play the command ``knots`` (10, 8) (made valid by :meth:`constrain`) as the next
        trial of the episode; returns what :meth:`step` returns (for black-box learners)."""
        self.knots = self.constrain(knots)
        obs, reward, success, info = self._trial()
        truncated = not success and self.trials >= self.max_trials
        return obs, reward, success, truncated, info

    def step(self, action):
        """Change the command's knots by ``action`` (scaled, in [-1, 1]) and play it once."""
        a = checked_action(action, self.action_space.shape)
        a = np.clip(a.reshape(N_ROWS, N_KNOTS), -1.0, 1.0)
        d = self.action_scale * a
        d[N_JOINTS:] = d[N_JOINTS:].mean(axis=1, keepdims=True)  # base fixed within a command
        d[:N_JOINTS, 1] = d[:N_JOINTS, 0]  # at rest at the start ...
        d[:N_JOINTS, -1] = d[:N_JOINTS, -2]  # ... and at the end
        self.knots = np.clip(self.knots + d, self._knot_lo, self._knot_hi)
        obs, reward, success, info = self._trial()
        truncated = not success and self.trials >= self.max_trials
        return obs, reward, success, truncated, info


gym.register(id="flyknot/FlyingKnot-v0", entry_point="flyknot_app.gym.env:FlyknotEnv")

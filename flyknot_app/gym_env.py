"""A gymnasium environment for comparing learners on the flying knot, trial by trial.

One environment step is one trial in the simulated lab, as in iterative learning: the agent
proposes a change of the command's Bezier knots, the lab plays the command with its
trial-to-trial variation, and the agent observes what the learner would observe (the rope
state error at the critical time, from the motion-capture markers) plus the knots.

* Observation (146,): the critical-point error x(t_c) - x_demo(t_c) in the demonstration
  frame (66: 11 marker positions [m] then velocities [m/s]; zeros when the trial faulted or
  lost tracking before t_c) followed by the current knots (80: 7 joint rows [rad] and 3
  base-offset rows [m], 8 knots each, row-major).
* Action (80,) in [-1, 1]: the knot change divided by ``action_scale`` (joint rows [rad],
  base rows [m]); the base rows' change is averaged over the knots (the base stays fixed
  within a command) and the first/last two knots of each joint row move together (the
  command stays at rest at both ends).
* Reward: -(critical-point cost ||x(t_c) - x_demo(t_c)||^2_Q) + ``knot_bonus`` when the
  trial ties the knot; ``fault_penalty`` replaces the cost when the robot faults or tracking
  is lost before t_c.
* The episode terminates at the first knot and is truncated after ``max_trials`` trials.

The initial command is the paper's initial guess for the demonstration (cached per env).
Defaults as the scenario files: the robot demonstration with the window (follow-through
t_f - t_c = 0.25 s, t_0 at the start of the hand motion); ``window=(0.035, 0.05)`` is the
paper's.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from flyknot.constants import N_JOINTS, N_KNOTS, N_ROWS
from flyknot.errors import FlyknotError, check_positive


class FlyknotEnv(gym.Env):
    """Trial-level flying-knot environment on the simulated lab."""

    metadata = {"render_modes": ()}  # noqa: RUF012 - gymnasium reads this mapping

    def __init__(
        self,
        rope: int | str = 1,
        demo: str = "robot",
        *,
        window: tuple[float, float] = (0.25, 0.0),
        max_trials: int = 10,
        action_scale: float = 0.05,
        knot_bonus: float = 100.0,
        fault_penalty: float = 100.0,
        settle_s: float | None = None,
        seed: int = 0,
        ropes: str | None = None,
    ):
        """``rope``: a paper rope id 1..7 or a rope's name (the paper's, or one of ``ropes``,
        a user's ropes file; see ``assets/ropes_example.toml``)."""
        super().__init__()
        from flyknot_app.runner import prepare_target
        from flyknot_sim.lab import LabParams, SimLab
        from learner.inverse_qp import InverseModelWeights
        from learner.kinematics import RobotModel
        from learner.rope_model import RopeModelParams

        check_positive("action_scale", action_scale)
        if not isinstance(max_trials, int) or max_trials < 1:
            raise FlyknotError(f"max_trials: must be an integer >= 1, got {max_trials!r}")
        self.max_trials = max_trials
        self.action_scale = float(action_scale)
        self.knot_bonus = float(knot_bonus)
        self.fault_penalty = float(fault_penalty)
        self._lab = SimLab(LabParams(rope=rope, seed=seed, settle_s=settle_s, ropes=ropes))
        self._robot = RobotModel.from_mjcf()
        self._weights = InverseModelWeights()
        self._window = (float(window[0]), float(window[1]))
        _, self.target = prepare_target(demo, RopeModelParams().dt, self._window)
        self._demo = demo
        self._knots0: np.ndarray | None = None
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (66 + N_ROWS * N_KNOTS,), float)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (N_ROWS * N_KNOTS,), float)
        self.knots = np.zeros((N_ROWS, N_KNOTS))
        self.trials = 0

    # ------------------------------------------------------------------------------------
    def initial_knots(self) -> np.ndarray:
        """The paper's initial guess for the demonstration (computed once)."""
        if self._knots0 is None:
            import tempfile
            from pathlib import Path

            from flyknot_app.runner import initial_knots

            with tempfile.TemporaryDirectory() as tmp:
                k0, _ = initial_knots(
                    self._demo,
                    Path(tmp),
                    self._robot,
                    self.target.dt,
                    float(self._lab.base_pose[2]),
                    self._window,
                )
            self._knots0 = np.asarray(k0)
        return self._knots0.copy()

    def _trial(self) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        from flyknot.errors import RecordError
        from learner.bezier import BezierCommand
        from learner.critical_state import critical_state_from_record
        from learner.ilc import critical_cost

        rec = self._lab.run(BezierCommand(self.knots, self.target.T).joint_command())
        self.trials += 1
        info: dict[str, Any] = {"fault": rec.fault, "knot": rec.knot, "trial": self.trials}
        err = np.zeros(66)
        if rec.fault is None:
            try:
                x = critical_state_from_record(rec, self.target.t_c, self.knots[N_JOINTS:, 0])
                err = x - self.target.x_c
                cost = critical_cost(err, self._weights)
            except RecordError as e:
                cost = self.fault_penalty
                info["tracking_lost"] = str(e)
        else:
            cost = self.fault_penalty
        info["cost"] = cost
        success = rec.succeeded
        reward = -cost + (self.knot_bonus if success else 0.0)
        obs = np.concatenate([err, self.knots.ravel()])
        return obs, float(reward), success, info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode from the initial command: one trial, its observation and info."""
        super().reset(seed=seed)
        self.knots = self.initial_knots()
        self.trials = 0
        obs, _, _, info = self._trial()
        return obs, info

    def step(self, action):
        """Change the command's knots by ``action`` (scaled, in [-1, 1]) and play it once."""
        a = np.clip(np.asarray(action, dtype=float).reshape(N_ROWS, N_KNOTS), -1.0, 1.0)
        d = self.action_scale * a
        d[N_JOINTS:] = d[N_JOINTS:].mean(axis=1, keepdims=True)  # base fixed within a command
        d[:N_JOINTS, 1] = d[:N_JOINTS, 0]  # at rest at the start ...
        d[:N_JOINTS, -1] = d[:N_JOINTS, -2]  # ... and at the end
        self.knots = self.knots + d
        obs, reward, success, info = self._trial()
        truncated = not success and self.trials >= self.max_trials
        return obs, reward, success, truncated, info


gym.register(id="flyknot/FlyingKnot-v0", entry_point="flyknot_app.gym_env:FlyknotEnv")

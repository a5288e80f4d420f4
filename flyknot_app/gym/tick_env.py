"""A gymnasium environment on the same simulated lab in which one step is one 4 ms tick.

For policy learning (reinforcement learning) on the flying knot: an episode is one trial of
the lab (:meth:`flyknot_sim.lab.SimLab.start`), the policy sends the arm's joint targets one
control tick at a time and sees what the lab measures between ticks.

* Action (7,) in [-1, 1]: the next tick's joint targets as offsets from the initial
  command's sample c_k at that tick: u_k = ``action_scale`` a_k [rad] passes a first-order
  low-pass, o_k = o_{k-1} + alpha (u_k - o_{k-1}) from o_{-1} = 0 with alpha = 1 -
  exp(-dt / ``smoothing_s``) (``smoothing_s=0``: alpha = 1, o_k = u_k), and the target is
  q_k = clip(c_k + o_k, q_min, q_max), the paper's position limits
  (:class:`flyknot.limits.JointLimits`). **A zero policy replays the initial command** (the
  command ILC and the black-box baselines start from), so a policy explores around a motion
  the arm can make and that nearly ties the knot. Absolute targets were the alternative; they
  were not chosen because almost every target a fresh policy draws is then a jump the
  controller faults on (0.1 rad within one 4 ms tick is 25 rad/s against the 3.14 rad/s
  limit), so no episode would get near a knot. Even offsets must change smoothly: an offset
  that changes by d between ticks adds about d / dt^2 = 62500 d rad/s^2 to the acceleration
  (limit 100 rad/s^2), and an offset at the first tick is a jump from rest. The low-pass
  bounds what any policy adds, whatever it does: the offset's acceleration by
  2 alpha (1 + alpha) ``action_scale`` / dt^2 and its speed by 2 alpha ``action_scale`` / dt,
  with the defaults (0.05 rad, 0.5 s: alpha = 0.008) 50 rad/s^2 and 0.2 rad/s, within the
  margins the paper's initial command leaves on rope 1 (its peak speed is 89 % of the limit
  on joint 4, acceleration 31 % on joint 2, torque 83 % on joint 3). Measured on rope 1 with
  an untrained PPO policy (gSDE, log std -2 and -1): 0 of 12 episodes faulted; with
  ``smoothing_s=0`` (``action_scale`` 0.02 to 0.1 rad) all 45 faulted at their second tick.
  An action of the wrong shape, or with NaN or infinity, is refused with a ConfigError before
  anything changes.
* Observation (59,), bounded (values beyond the bounds are clipped): measured joint angles
  (7) [rad] within the paper's position limits, joint velocities (7) [rad/s] within
  +-:data:`JOINT_VEL_BOUND`, the newest motion-capture frame of the 11 rope markers (33) [m],
  lab frame, within +-:data:`~flyknot_app.gym.env.POS_BOUND` (0 where tracking is lost), the
  markers' validity mask (11: 1 seen, 0 lost), and the time fraction tick / n in [0, 1].
* Episode: the initial command's n ticks from rest at its first sample; after the last, the
  lab holds the last target under its settle rule (``settle_s``: a fixed wait instead) and
  judges the knot; the step that ends the episode terminates it. A controller fault (the
  controller checks the targets online, :class:`flyknot_sim.faults.StreamCheck`) ends the
  episode at once, after the arm has braked.
* Reward: 0 on every step but the last, then ``knot_bonus`` (1) when the knot tied (no fault,
  the settled rope's verdict is a knot in the hanging rope) minus the critical-point cost
  (:func:`flyknot_app.gym.env.score_trial`, as :class:`~flyknot_app.gym.env.FlyknotEnv`
  computes it; ``fault_penalty`` instead when the arm faulted or tracking was lost before
  t_c).
* ``info`` on every step: ``tick``, ``fault``; at the end also ``knot``, ``cost``,
  ``success``, ``failure`` (the failure class of :mod:`flyknot_app.anatomy.diagnosis`), ``trial``
  (the episodes so far), ``record`` (the saved record's path, when ``record_dir`` is given) and
  ``actions`` (the episode's actions as applied, (ticks, 7), to replay the command).
* ``reset(seed=s)`` restarts the lab's trial-to-trial variation at trial 0 of seed ``s``;
  ``reset()`` without a seed continues the sequence (each episode is the lab's next trial).

The initial command is the paper's initial guess for the demonstration (computed once per
process), or ``command``. Registered as ``flyknot/FlyingKnotTick-v0``.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from flyknot.constants import COMMAND_RATE_HZ, N_JOINTS, N_MARKERS
from flyknot.errors import CommandError, ConfigError, check_nonnegative, check_positive
from flyknot.limits import JointLimits
from flyknot.record import JointCommand
from flyknot_app.gym.env import POS_BOUND, checked_action, paper_initial_knots, score_trial
from flyknot_app.learner_settings import SCENARIO_DEMO, SCENARIO_WINDOW, scenario_weights
from learner.inverse_qp import InverseModelWeights

JOINT_VEL_BOUND = 10.0
"""Bound of the joint velocities in the observation [rad/s]."""
ACTION_SCALE = 0.05
"""Default offset of a full action from the initial command [rad]."""
SMOOTHING_S = 0.5
"""Default time constant of the offsets' low-pass [s]."""
N_OBS = 2 * N_JOINTS + 4 * N_MARKERS + 1


class FlyknotTickEnv(gym.Env):
    """Tick-level flying-knot environment on the simulated lab (module docstring)."""

    metadata = {"render_modes": ()}  # noqa: RUF012 - gymnasium reads this mapping

    def __init__(
        self,
        rope: int | str = 1,
        demo: str = SCENARIO_DEMO,
        *,
        window: tuple[float, float] = SCENARIO_WINDOW,
        weights: InverseModelWeights | None = None,
        command: JointCommand | None = None,
        base_offset: np.ndarray | None = None,
        action_scale: float = ACTION_SCALE,
        smoothing_s: float = SMOOTHING_S,
        knot_bonus: float = 1.0,
        fault_penalty: float = 10.0,
        settle_s: float | None = None,
        seed: int = 0,
        ropes: str | None = None,
        record_dir: str | None = None,
    ):
        """``rope`` and ``ropes`` as for :class:`~flyknot_app.gym.env.FlyknotEnv`;
        ``command``: the initial command (its samples at 250 Hz) instead of the paper's
        initial guess; ``base_offset``: the robot base's position in the demonstration frame
        (3,) [m] for the critical-point cost (default: the initial guess's);
        ``record_dir``: where each episode's record is saved (None: not saved); ``demo``,
        ``window`` and ``weights`` as for :class:`~flyknot_app.gym.env.FlyknotEnv` (its
        defaults are the scenario files')."""
        super().__init__()
        from flyknot_app.runner import prepare_target
        from flyknot_sim.lab import LabParams, SimLab
        from learner.bezier import BezierCommand
        from learner.rope_model import RopeModelParams

        self._weights = scenario_weights() if weights is None else weights
        if not isinstance(self._weights, InverseModelWeights):
            raise ConfigError("weights", f"must be an InverseModelWeights, got {weights!r}")
        check_positive("action_scale", action_scale)
        check_nonnegative("smoothing_s", smoothing_s)
        check_nonnegative("fault_penalty", fault_penalty)
        self.action_scale = float(action_scale)
        self.smoothing_s = float(smoothing_s)
        self.knot_bonus = float(knot_bonus)
        self.fault_penalty = float(fault_penalty)
        self._lab = SimLab(LabParams(rope=rope, seed=seed, settle_s=settle_s, ropes=ropes))
        window = (float(window[0]), float(window[1]))
        _, self.target = prepare_target(demo, RopeModelParams().dt, window)
        knots0 = None
        if command is None or base_offset is None:
            knots0 = paper_initial_knots(demo, window, float(self._lab.base_pose[2]))
        if command is None:
            command = BezierCommand(knots0, self.target.T).joint_command()
        if not isinstance(command, JointCommand) or command.rate_hz != COMMAND_RATE_HZ:
            raise ConfigError("command", f"must be a JointCommand at {COMMAND_RATE_HZ:g} Hz")
        self.command = command
        offset = knots0[N_JOINTS:, 0] if base_offset is None else base_offset
        offset = np.asarray(offset, dtype=float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ConfigError("base_offset", f"must be 3 finite numbers [m], got {offset!r}")
        self.base_offset = offset
        limits = JointLimits()
        self._q_lo, self._q_hi = limits.q_min, limits.q_max
        vel = np.full(N_JOINTS, JOINT_VEL_BOUND)
        pos = np.full(3 * N_MARKERS, POS_BOUND)
        lo = np.concatenate([self._q_lo, -vel, -pos, np.zeros(N_MARKERS), [0.0]])
        hi = np.concatenate([self._q_hi, vel, pos, np.ones(N_MARKERS), [1.0]])
        self.observation_space = gym.spaces.Box(lo, hi, dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (N_JOINTS,), np.float64)
        self.record_dir = None if record_dir is None else Path(record_dir)
        self.trials = 0
        self._session = None
        self._actions: list[np.ndarray] = []
        self._offset = np.zeros(N_JOINTS)

    @property
    def smoothing_alpha(self) -> float:
        """alpha = 1 - exp(-dt / smoothing_s) of the offsets' low-pass (1 without one)."""
        if self.smoothing_s == 0:
            return 1.0
        return float(-np.expm1(-self.command.dt / self.smoothing_s))

    @property
    def n_ticks(self) -> int:
        """Ticks of an episode's command (the initial command's samples)."""
        return self.command.n

    # ------------------------------------------------------------------------------------
    def _obs(self, o) -> np.ndarray:
        seen = ~np.isnan(o.markers).any(axis=1)
        markers = np.where(seen[:, None], o.markers, 0.0).ravel()
        obs = np.concatenate(
            [o.q, o.qd, markers, seen.astype(float), [min(o.tick / self.n_ticks, 1.0)]]
        )
        return np.clip(obs, self.observation_space.low, self.observation_space.high)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode: the lab's next trial, the arm at rest at the command's start."""
        super().reset(seed=seed)
        if seed is not None:
            self._lab.params = replace(self._lab.params, seed=int(seed))
            self._lab.trial_index = 0
        self._session = self._lab.start(self.command.q[0], self.command.dt)
        self._actions = []
        self._offset = np.zeros(N_JOINTS)
        return self._obs(self._session.observe()), {"tick": 0, "fault": None}

    def step(self, action):
        """Send the next tick's targets (the initial command's sample plus the scaled offset
        ``action``); the last tick, or a fault, ends the episode with the knot's verdict."""
        a = checked_action(action, self.action_space.shape)
        s = self._session
        if s is None or s.n_sent >= self.n_ticks or s.fault is not None:
            raise ConfigError("step", "the episode has ended (or not begun): reset() first")
        a = np.clip(a, -1.0, 1.0)
        k = s.n_sent
        offset = self._offset + self.smoothing_alpha * (self.action_scale * a - self._offset)
        target = np.clip(self.command.q[k] + offset, self._q_lo, self._q_hi)
        try:
            o = s.tick(target)
        except CommandError as e:  # not expected: the target is finite and in bounds
            raise ConfigError("action", str(e)) from None
        self._actions.append(a)
        self._offset = offset
        info: dict[str, Any] = {
            "tick": s.n_sent,
            "fault": None if o.fault is None else o.fault.reason,
        }
        if o.fault is None and s.n_sent < self.n_ticks:
            return self._obs(o), 0.0, False, False, info
        return self._end(info)

    def _end(self, info: dict[str, Any]):
        s = self._session
        stem = None
        if self.record_dir is not None:
            stem = self.record_dir / f"seed_{self._lab.params.seed}" / f"trial_{s.trial_index:05d}"
        rec = s.finish()
        self.trials += 1
        if stem is not None:
            rec.save(stem)
        _, cost, scored = score_trial(
            rec, self.target, self.base_offset, self._weights, self.fault_penalty
        )
        success = rec.succeeded
        info.update(scored)
        info.update(
            success=success,
            trial=self.trials,
            record=None if stem is None else str(stem.with_suffix(".json")),
            actions=np.array(self._actions),
        )
        reward = (self.knot_bonus if success else 0.0) - cost
        return self._obs(s.observe()), float(reward), True, False, info


gym.register(id="flyknot/FlyingKnotTick-v0", entry_point="flyknot_app.gym.tick_env:FlyknotTickEnv")

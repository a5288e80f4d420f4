"""The simulated lab: one class owns the MuJoCo model and data and plays trials.

:class:`SimLab` is a :class:`flyknot.record.Cell`. A trial:

1. puts the arm at the command's first sample and the rope hanging from the fingertip in a
   state drawn uniformly within the rest criterion a lab checks before a throw
   (:func:`flyknot.rest.settled_start`; an extra seeded sway for robustness studies), servo
   gains perturbed by a seeded few percent;
2. streams the command to the joint servos at 250 Hz (zero-order hold, like the xArm's
   ``set_servo_angle_j`` stream), after a seeded start delay of less than one tick that
   shifts the robot's clock against the motion-capture clock;
3. faults like the real controller when the command breaks the paper's position, velocity,
   acceleration or torque limits: the arm brakes to a hold at that instant and the trial
   is aborted;
4. holds the last sample until the rope's free end is at rest and the knot verdict has held
   over the rest window (:class:`flyknot.rest.SettleMonitor`, capped), then judges the knot
   from the rope's centreline; air drag acts on the rope throughout
   (:mod:`flyknot_sim.aero`);
5. returns what the real lab would measure: commanded and measured joints at 250 Hz,
   fingertip pose, 11 rope markers at 200 Hz through the motion-capture emulation (noise,
   tracking lost shortly after the first self-contact), plus sim-only ``truth``.

:meth:`SimLab.run` plays a whole command; :meth:`SimLab.start` opens a trial for play one
4 ms tick at a time (the controller then checks the stream online). Both run the same loop,
:class:`flyknot_sim.session.TrialSession`.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from flyknot.constants import COMMAND_RATE_HZ
from flyknot.errors import check_int, check_positive
from flyknot.geometry import readonly
from flyknot.record import JointCommand, TrialRecord
from flyknot.rest import start_with_sway
from flyknot_sim import robot
from flyknot_sim.aero import RopeDrag
from flyknot_sim.bend_friction import RopeBendFriction
from flyknot_sim.faults import check_sample
from flyknot_sim.lab_params import LabParams, VariationParams
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_table import RopeParams
from flyknot_sim.scene import ROBOT_PREFIX, robot_base_pose, scene_spec
from flyknot_sim.session import Plant, TrialSession, TrialStart


class SimLab:
    """The simulated lab (a :class:`flyknot.record.Cell`)."""

    def __init__(self, params: LabParams = LabParams()):  # noqa: B008 - frozen value
        self.params = params
        self.rope_params: RopeParams = params.rope_params
        spec = scene_spec(params.scene)
        tip_body, tip_pos, tip_axis = robot.fingertip_anchor()
        self.rope = add_rope(
            spec,
            self.rope_params,
            anchor_body=ROBOT_PREFIX + tip_body,
            anchor_pos=tip_pos,
            axis=tip_axis,
            prefix="rope",
            settings=params.settings,
            twist=params.twist,
        )
        configure_options(spec, [self.rope_params], params.settings)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.rope = self.rope.bind(self.model) if hasattr(self.rope, "bind") else self.rope
        m = self.model
        qadr = np.array([m.jnt_qposadr[m.joint(ROBOT_PREFIX + n).id] for n in robot.JOINT_NAMES])
        dadr = np.array([m.jnt_dofadr[m.joint(ROBOT_PREFIX + n).id] for n in robot.JOINT_NAMES])
        self._servo_default = robot.ServoParams.default()
        self._trial_index = 0
        self.base_pose = robot_base_pose(params.scene)
        bound = self.rope.bind(self.model) if hasattr(self.rope, "bind") else self.rope
        aero = params.aero
        if self.rope_params.cd is not None:  # the rope's own drag coefficient
            aero = dataclasses.replace(aero, cd=self.rope_params.cd)
        self.plant = Plant(
            model=m,
            data=self.data,
            rope=bound,
            rope_params=self.rope_params,
            base_pose=self.base_pose,
            qadr=readonly(qadr, int),
            dadr=readonly(dadr, int),
            act=readonly(robot.actuator_ids(m, ROBOT_PREFIX), int),
            tip_site=m.site(ROBOT_PREFIX + robot.FINGERTIP_SITE).id,
            torque_model=robot.load_robot_model(),
            drag=RopeDrag(bound, aero),
            bend=RopeBendFriction(bound, params.bend_friction.moment_for(self.rope_params)),
        )
        """The model, data and handles a trial drives (:class:`flyknot_sim.session.Plant`)."""

    @property
    def trial_index(self) -> int:
        """Index of the next trial: trial i draws its variation from ``(seed, i)``."""
        return self._trial_index

    @trial_index.setter
    def trial_index(self, value: int) -> None:
        check_int("trial_index", value)
        self._trial_index = value

    # --------------------------------------------------------------------------------
    def _rng(self, trial_index: int) -> np.random.Generator:
        return np.random.default_rng([self.params.seed, trial_index])

    def reset(self, q0: np.ndarray, rng: np.random.Generator) -> float:
        """Arm at ``q0`` at rest, rope hanging in a seeded settled start; return the delay."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        var = self.params.variation
        gains = self._servo_default.perturbed(rng, var.servo_gain_rel)
        robot.apply_servo_params(m, self.plant.act, gains)
        d.qpos[self.plant.qadr] = q0
        d.ctrl[self.plant.act] = q0
        mujoco.mj_kinematics(m, d)
        sway = math.radians(var.sway_deg) * abs(rng.standard_normal())
        azimuth = rng.uniform(0, 2 * math.pi)
        rate = 0.0
        if var.rest_start:
            sway, azimuth, rate = start_with_sway(
                rng,
                self.params.settle.rest,
                self.rope_params.length,
                sway,
                azimuth,
                var.rest_scale,
            )
        self.rope.set_hanging(m, d, sway_angle=sway, sway_azimuth=azimuth, sway_rate=rate)
        mujoco.mj_forward(m, d)
        return float(rng.uniform(0.0, var.start_delay_max_s)) if var.start_delay_max_s else 0.0

    def _open(
        self,
        q0: np.ndarray,
        dt: float,
        *,
        plan: JointCommand | None = None,
        progress: bool = False,
    ) -> TrialSession:
        """Open trial ``trial_index``: draw its variation, set the model's step to a whole
        number of physics steps per tick ``dt`` [s], reset the arm at ``q0`` and the rope, and
        hand the session the plant (the session changes nothing else of the lab's)."""
        check_positive("dt", dt)
        q0 = check_sample(q0)
        index = self.trial_index
        rng = self._rng(index)
        self.trial_index = index + 1
        m = self.model
        substeps = max(1, round(float(dt) / m.opt.timestep))
        m.opt.timestep = float(dt) / substeps
        delay = self.reset(q0, rng)
        start = TrialStart(index, rng, delay, float(dt), substeps)
        return TrialSession(self.plant, self.params, start, q0, plan=plan, progress=progress)

    def start(self, q0: np.ndarray, dt: float = 1.0 / COMMAND_RATE_HZ) -> TrialSession:
        """Open the next trial for tick-by-tick play from rest at ``q0`` (7,) [rad].

        Send one joint target per tick of ``dt`` [s] (:meth:`TrialSession.tick`), then
        :meth:`TrialSession.finish` for the record; the controller checks the stream online
        (:mod:`flyknot_sim.session`).
        """
        return self._open(q0, dt)

    def run(self, command: JointCommand, *, progress: bool = False) -> TrialRecord:
        """Play ``command`` once from rest and return what the lab measured.

        Args:
            command: Joint targets at their rate (250 Hz on the xArm).
            progress: Show a progress bar over simulated time.
        """
        q_cmd = np.asarray(command.q)
        session = self._open(q_cmd[0], command.dt, plan=command, progress=progress)
        for target in q_cmd:
            if session.send(target) is not None:
                break  # the controller faulted: the arm brakes, the trial is aborted
        return session.finish()


__all__ = ["LabParams", "SimLab", "VariationParams"]

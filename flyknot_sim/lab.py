"""The simulated lab: one class owns the MuJoCo model and data and plays trials.

:class:`SimLab` is a :class:`flyknot.record.Cell`. A trial:

1. puts the arm at the command's first sample and the rope hanging at rest from the
   fingertip (with a small seeded sway), servo gains perturbed by a seeded few percent;
2. streams the command to the joint servos at 250 Hz (zero-order hold, like the xArm's
   ``set_servo_angle_j`` stream), after a seeded start delay of less than one tick that
   shifts the robot's clock against the motion-capture clock;
3. faults like the real controller when the command breaks the paper's position, velocity,
   acceleration or torque limits: the arm brakes to a hold at that instant and the trial
   is aborted;
4. holds the last sample while the rope settles, then judges the knot from the rope's
   centreline;
5. returns what the real lab would measure: commanded and measured joints at 250 Hz,
   fingertip pose, 11 rope markers at 200 Hz through the motion-capture emulation (noise,
   tracking lost shortly after the first self-contact), plus sim-only ``truth``.
"""

from __future__ import annotations

import math
import platform
from dataclasses import dataclass, field

import mujoco
import numpy as np
from tqdm import tqdm

from flyknot import __version__
from flyknot.constants import N_JOINTS, SETTLE_S
from flyknot.errors import check_nonnegative, check_positive
from flyknot.record import JointCommand, TrialRecord
from flyknot_sim import faults as faults_mod
from flyknot_sim import mocap, robot
from flyknot_sim.knot import classify_centreline
from flyknot_sim.rope import RopeParams, add_rope, configure_options, get_rope
from flyknot_sim.scene import ROBOT_PREFIX, SceneParams, robot_base_pose, scene_spec

_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}]"


@dataclass(frozen=True)
class VariationParams:
    """Seeded trial-to-trial variation, as in a real lab.

    Attributes:
        sway_deg: Std of the rope's initial tilt from vertical [deg].
        servo_gain_rel: Relative std of each servo's stiffness and damping gains [-].
        start_delay_max_s: The command starts after a uniform delay in [0, this) [s].
    """

    sway_deg: float = 1.0
    servo_gain_rel: float = 0.03
    start_delay_max_s: float = 0.004

    def __post_init__(self) -> None:
        check_nonnegative("sway_deg", self.sway_deg)
        check_nonnegative("servo_gain_rel", self.servo_gain_rel)
        check_nonnegative("start_delay_max_s", self.start_delay_max_s)

    @classmethod
    def none(cls) -> VariationParams:
        """No variation: every trial of a command is the same."""
        return cls(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class LabParams:
    """Everything that defines the simulated lab.

    Attributes:
        rope: Rope id (1..7, see ``assets/ropes.toml``).
        seed: Seed of the trial-to-trial variation and the mocap noise; trial ``i`` of a
            lab uses ``(seed, i)``.
        settle_s: Time the last command sample is held before the knot is judged [s].
        brake_s: After a fault, how long the arm is simulated braking [s].
        truth_rate_hz: Rate of the ground-truth centreline stored in ``truth`` [Hz].
        variation: Trial-to-trial variation.
        mocap: Motion-capture emulation.
        scene: Geometry of the lab.
    """

    rope: int = 1
    seed: int = 0
    settle_s: float = SETTLE_S
    brake_s: float = 0.3
    truth_rate_hz: float = 100.0
    variation: VariationParams = field(default_factory=VariationParams)
    mocap: mocap.MocapParams = field(default_factory=mocap.MocapParams)
    scene: SceneParams = field(default_factory=SceneParams)

    def __post_init__(self) -> None:
        get_rope(self.rope)  # validates the id, listing valid choices
        check_nonnegative("settle_s", self.settle_s)
        check_nonnegative("brake_s", self.brake_s)
        check_positive("truth_rate_hz", self.truth_rate_hz)


class SimLab:
    """The simulated lab (a :class:`flyknot.record.Cell`)."""

    def __init__(self, params: LabParams = LabParams()):
        self.params = params
        self.rope_params: RopeParams = get_rope(params.rope)
        spec = scene_spec(params.scene)
        tip_body, tip_pos, tip_axis = robot.fingertip_anchor()
        self.rope = add_rope(
            spec,
            self.rope_params,
            anchor_body=ROBOT_PREFIX + tip_body,
            anchor_pos=tip_pos,
            axis=tip_axis,
            prefix="rope",
        )
        configure_options(spec, [self.rope_params])
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.rope = self.rope.bind(self.model) if hasattr(self.rope, "bind") else self.rope
        m = self.model
        self._qadr = np.array(
            [m.jnt_qposadr[m.joint(ROBOT_PREFIX + n).id] for n in robot.JOINT_NAMES]
        )
        self._dadr = np.array(
            [m.jnt_dofadr[m.joint(ROBOT_PREFIX + n).id] for n in robot.JOINT_NAMES]
        )
        self._act = robot.actuator_ids(m, ROBOT_PREFIX)
        self._tip_site = m.site(ROBOT_PREFIX + robot.FINGERTIP_SITE).id
        self._servo_default = robot.ServoParams.default()
        self._robot_only = robot.load_robot_model()
        self._trial_index = 0
        self.base_pose = robot_base_pose(params.scene)

    # --------------------------------------------------------------------------------
    def _rng(self, trial_index: int) -> np.random.Generator:
        return np.random.default_rng([self.params.seed, trial_index])

    def reset(self, q0: np.ndarray, rng: np.random.Generator) -> float:
        """Arm at ``q0`` at rest, rope hanging at rest with a seeded sway; return delay."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        var = self.params.variation
        gains = self._servo_default.perturbed(rng, var.servo_gain_rel)
        robot.apply_servo_params(m, self._act, gains)
        d.qpos[self._qadr] = q0
        d.ctrl[self._act] = q0
        mujoco.mj_kinematics(m, d)
        sway = math.radians(var.sway_deg) * abs(rng.standard_normal())
        azimuth = rng.uniform(0, 2 * math.pi)
        self.rope.set_hanging(m, d, sway_angle=sway, sway_azimuth=azimuth)
        mujoco.mj_forward(m, d)
        return float(rng.uniform(0.0, var.start_delay_max_s)) if var.start_delay_max_s else 0.0

    def run(self, command: JointCommand, *, progress: bool = False) -> TrialRecord:
        """Play ``command`` once from rest and return what the lab measured.

        Args:
            command: Joint targets at their rate (250 Hz on the xArm).
            progress: Show a progress bar over simulated time.
        """
        rng = self._rng(self._trial_index)
        trial_index = self._trial_index
        self._trial_index += 1
        m, d = self.model, self.data
        q_cmd = np.asarray(command.q)
        tick = command.dt
        substeps = max(1, round(tick / m.opt.timestep))
        sim_dt = tick / substeps
        m.opt.timestep = sim_dt

        # Controller's limit checks, evaluated on the whole stream up front; the fault
        # takes effect at its tick, mid-motion, like the real controller.
        qd, qdd = faults_mod.command_derivatives(q_cmd, tick)
        tau = faults_mod.command_torques(self._robot_only, q_cmd, qd, qdd)
        fault = faults_mod.first_fault(q_cmd, tick, torques=tau)

        delay = self.reset(q_cmd[0], rng)
        n_cmd = command.n
        n_settle = round(self.params.settle_s / tick)
        n_ticks = n_cmd + n_settle
        if fault is not None:
            n_ticks = fault.tick + round(self.params.brake_s / tick) + 1

        # Ticks run on the robot clock: tick i starts at sim time delay + i * tick.
        # Simulate the delay first (arm holding q0).
        # The arm holds q0 during the delay; the trial's clock starts before it.
        # Timing: after mj_step number j, body positions and contacts in MjData are those of
        # the state *before* that step (MuJoCo computes them in the step's forward pass), so
        # the reading after step j is stored as sample j - 1 (time (j - 1) * sim_dt); the last
        # sample comes from one mj_kinematics at the end.
        pre_steps = round(delay / sim_dt)
        n_steps = pre_steps + n_ticks * substeps
        n_vert = self.rope.vertex_positions(m, d).shape
        vert_hist = np.empty((n_steps + 1, *n_vert))
        t_hist = sim_dt * np.arange(n_steps + 1)
        j = 0  # steps taken
        first_contact: float | None = None

        def step() -> None:
            nonlocal j, first_contact
            mujoco.mj_step(m, d)
            j += 1
            vert_hist[j - 1] = self.rope.vertex_positions(m, d)
            if first_contact is None and self.rope.self_contact(m, d):
                first_contact = float(t_hist[j - 1])

        for _ in range(pre_steps):
            step()
        q_meas = np.empty((n_ticks, N_JOINTS))
        tip_pos = np.empty((n_ticks, 3))
        tip_quat = np.empty((n_ticks, 4))
        q_sent = np.empty((n_ticks, N_JOINTS))
        hold = None
        bar = tqdm(
            total=round(n_ticks * tick, 2),
            unit="sim s",
            disable=not progress,
            desc=f"trial (rope {self.params.rope})",
            bar_format=_BAR,
        )
        for i in range(n_ticks):
            if i % 25 == 0:
                bar.n = round(i * tick, 2)
                bar.refresh()
            mujoco.mj_kinematics(m, d)  # fingertip pose of the current joint angles
            q_meas[i] = d.qpos[self._qadr]
            tip_pos[i] = d.site_xpos[self._tip_site]
            mujoco.mju_mat2Quat(tip_quat[i], d.site_xmat[self._tip_site])
            if fault is not None and i == fault.tick:
                hold = q_meas[i].copy()  # brake: hold where the arm is
            target = hold if hold is not None else q_cmd[min(i, n_cmd - 1)]
            q_sent[i] = target
            d.ctrl[self._act] = target
            for _ in range(substeps):
                step()
        mujoco.mj_kinematics(m, d)
        vert_hist[n_steps] = self.rope.vertex_positions(m, d)
        bar.n = bar.total
        bar.close()
        # Joints are stamped on the robot's clock (0 at the first command sample); markers
        # and contact times on the motion-capture clock (0 at the nominal start). The two
        # differ by the unknown start delay, as unsynchronised lab clocks do.
        t_joint = np.arange(n_ticks) * tick
        markers_true = self.rope.markers_from_vertices(vert_hist)
        t_mocap = mocap.sample_times(t_hist[-1], self.params.mocap.rate_hz)
        markers = mocap.emulate(
            t_hist, markers_true, t_mocap, first_contact, self.params.mocap, rng
        )
        knot = None
        if fault is None:
            knot = classify_centreline(self.rope.centreline(m, d))
        stride = max(1, round(1.0 / (self.params.truth_rate_hz * sim_dt)))
        truth = {
            "t_truth": t_hist[::stride],
            "centreline": self.rope.centrelines_from_vertices(vert_hist[::stride]),
            "markers": markers_true[::stride],
        }
        return TrialRecord(
            t_joint=t_joint,
            q_cmd=q_sent,
            q_meas=q_meas,
            t_marker=t_mocap,
            markers=markers,
            fingertip_pos=tip_pos,
            fingertip_quat=tip_quat,
            base_pose=self.base_pose,
            fault=None if fault is None else fault.reason,
            fault_time=None if fault is None else float(t_joint[fault.tick]),
            first_contact_time=first_contact,
            knot=knot,
            metadata={
                "cell": "sim",
                "rope": self.params.rope,
                "rope_name": self.rope_params.name,
                "seed": self.params.seed,
                "trial_index": trial_index,
                "start_delay_s": delay,
                "command_duration_s": command.duration,
                "sim_duration_s": float(t_hist[-1]),
                "sim_timestep_s": sim_dt,
                "versions": {
                    "flyknot": __version__,
                    "mujoco": mujoco.__version__,
                    "python": platform.python_version(),
                },
            },
            truth=truth,
        )

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
"""

from __future__ import annotations

import dataclasses
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from flyknot import __version__
from flyknot.constants import N_JOINTS
from flyknot.errors import ConfigError, check_int, check_nonnegative, check_positive
from flyknot.knot import classify_centreline
from flyknot.progress import bar_disable
from flyknot.record import JointCommand, TrialRecord
from flyknot.rest import SettleMonitor, SettleParams, start_with_sway
from flyknot_sim import faults as faults_mod
from flyknot_sim import mocap, robot
from flyknot_sim.aero import DRAG_HOLD_S, AeroParams, RopeDrag
from flyknot_sim.bend_friction import BendFrictionParams, RopeBendFriction
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_custom import resolve_rope, rope_record
from flyknot_sim.rope_table import RopeParams
from flyknot_sim.scene import ROBOT_PREFIX, SceneParams, robot_base_pose, scene_spec

_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}]"


@dataclass(frozen=True)
class VariationParams:
    """Seeded trial-to-trial variation, as in a real lab.

    Attributes:
        sway_deg: Std of an extra initial tilt of the rope from vertical [deg], |N(0, s^2)|
            toward a uniform azimuth, for robustness studies (0: the settled start alone;
            before issue 10 the lab used 1 deg).
        servo_gain_rel: Relative std of each servo's stiffness and damping gains [-].
        start_delay_max_s: The command starts after a uniform delay in [0, this) [s].
        rest_start: Draw the rope's start state uniformly within the lab's rest criterion
            (a rope that a lab would call static; :func:`flyknot.rest.settled_start`); False
            starts it hanging straight and still.
    """

    sway_deg: float = 0.0
    servo_gain_rel: float = 0.03
    start_delay_max_s: float = 0.004
    rest_start: bool = True

    def __post_init__(self) -> None:
        check_nonnegative("sway_deg", self.sway_deg)
        check_nonnegative("servo_gain_rel", self.servo_gain_rel)
        check_nonnegative("start_delay_max_s", self.start_delay_max_s)
        if not isinstance(self.rest_start, bool):
            raise ConfigError("rest_start", f"must be true or false, got {self.rest_start!r}")

    @classmethod
    def none(cls) -> VariationParams:
        """No variation: every trial of a command is the same."""
        return cls(0.0, 0.0, 0.0, False)


@dataclass(frozen=True)
class LabParams:
    """Everything that defines the simulated lab.

    Attributes:
        rope: Rope id (1..7, see ``assets/ropes.toml``), a rope's name (the paper's, or one of
            ``ropes``), or a :class:`flyknot_sim.rope_table.RopeParams`
            (:func:`flyknot_sim.rope_custom.resolve_rope`); a paper rope's name becomes its id.
        seed: Seed of the trial-to-trial variation and the mocap noise; trial ``i`` of a
            lab uses ``(seed, i)``.
        settle: When the knot is judged after the command: until the rope is at rest, capped
            (:class:`flyknot.rest.SettleParams`).
        settle_s: A fixed wait instead [s] (judged then, at rest or not); None: ``settle``.
        aero: Air drag on the rope.
        bend_friction: Hysteretic bending friction of the rope (Grosberg's frictional couple;
            off by default: no published value for cords, see ``docs/rope-model.md``).
        twist: Build the rope with a twist hinge per edge (rod torsion; ``add_rope(twist=)``).
        brake_s: After a fault, how long the arm is simulated braking [s].
        truth_rate_hz: Rate of the ground-truth centreline stored in ``truth`` [Hz].
        variation: Trial-to-trial variation.
        mocap: Motion-capture emulation.
        scene: Geometry of the lab.
        ropes: A user's ropes file (``assets/ropes_example.toml``) whose ropes ``rope`` may
            name, or None; kept as an absolute path.
    """

    rope: int | str | RopeParams = 1
    seed: int = 0
    settle: SettleParams = field(default_factory=SettleParams)
    settle_s: float | None = None
    aero: AeroParams = field(default_factory=AeroParams)
    bend_friction: BendFrictionParams = field(default_factory=BendFrictionParams)
    twist: bool = False
    brake_s: float = 0.3
    truth_rate_hz: float = 100.0
    variation: VariationParams = field(default_factory=VariationParams)
    mocap: mocap.MocapParams = field(default_factory=mocap.MocapParams)
    scene: SceneParams = field(default_factory=SceneParams)
    ropes: str | None = None

    def __post_init__(self) -> None:
        if self.ropes is not None:
            object.__setattr__(self, "ropes", str(Path(self.ropes).expanduser().resolve()))
        rope = resolve_rope(self.rope, self.ropes)  # validates, listing valid choices
        if not rope.custom and not isinstance(self.rope, RopeParams):
            object.__setattr__(self, "rope", rope.id)
        if self.settle_s is not None:
            check_nonnegative("settle_s", self.settle_s)
        if not isinstance(self.settle, SettleParams):
            raise ConfigError("settle", f"must be SettleParams, got {type(self.settle).__name__}")
        if not isinstance(self.twist, bool):
            raise ConfigError("twist", f"must be true or false, got {self.twist!r}")
        if not isinstance(self.bend_friction, BendFrictionParams):
            raise ConfigError(
                "bend_friction",
                f"must be BendFrictionParams, got {type(self.bend_friction).__name__}",
            )
        if not isinstance(self.aero, AeroParams):
            raise ConfigError("aero", f"must be AeroParams, got {type(self.aero).__name__}")

    @property
    def rope_params(self) -> RopeParams:
        """The rope."""
        return resolve_rope(self.rope, self.ropes)

    @property
    def settle_rule(self) -> SettleParams:
        """The settle in force: ``settle``, or a fixed wait of ``settle_s``."""
        return self.settle if self.settle_s is None else SettleParams.fixed(self.settle_s)
        check_nonnegative("brake_s", self.brake_s)
        check_positive("truth_rate_hz", self.truth_rate_hz)


class SimLab:
    """The simulated lab (a :class:`flyknot.record.Cell`)."""

    def __init__(self, params: LabParams = LabParams()):
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
            twist=params.twist,
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
        self._bound = self.rope.bind(self.model) if hasattr(self.rope, "bind") else self.rope
        aero = params.aero
        if self.rope_params.cd is not None:  # the rope's own drag coefficient
            aero = dataclasses.replace(aero, cd=self.rope_params.cd)
        self._drag = RopeDrag(self._bound, aero)
        self._bend = RopeBendFriction(self._bound, params.bend_friction.moment)

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
        robot.apply_servo_params(m, self._act, gains)
        d.qpos[self._qadr] = q0
        d.ctrl[self._act] = q0
        mujoco.mj_kinematics(m, d)
        sway = math.radians(var.sway_deg) * abs(rng.standard_normal())
        azimuth = rng.uniform(0, 2 * math.pi)
        rate = 0.0
        if var.rest_start:
            sway, azimuth, rate = start_with_sway(
                rng, self.params.settle.rest, self.rope_params.length, sway, azimuth
            )
        self.rope.set_hanging(m, d, sway_angle=sway, sway_azimuth=azimuth, sway_rate=rate)
        mujoco.mj_forward(m, d)
        return float(rng.uniform(0.0, var.start_delay_max_s)) if var.start_delay_max_s else 0.0

    def run(self, command: JointCommand, *, progress: bool = False) -> TrialRecord:
        """Play ``command`` once from rest and return what the lab measured.

        Args:
            command: Joint targets at their rate (250 Hz on the xArm).
            progress: Show a progress bar over simulated time.
        """
        rng = self._rng(self._trial_index)  # see the trial_index property
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
        rule = self.params.settle_rule
        # Room for the longest trial: the command, then the settle cap (or the brake).
        n_ticks = n_cmd + math.ceil(rule.max_s / tick - 1e-9)
        if fault is not None:
            n_ticks = fault.tick + round(self.params.brake_s / tick) + 1

        # Ticks run on the robot clock: tick i starts at sim time delay + i * tick.
        # The arm holds q0 during the delay; the trial's clock starts before it.
        # Timing: after mj_step number j, body positions and contacts in MjData are those of
        # the state *before* that step (MuJoCo computes them in the step's forward pass), so
        # the reading after step j is stored as sample j - 1 (time (j - 1) * sim_dt); the last
        # sample comes from one mj_kinematics at the end.
        pre_steps = round(delay / sim_dt)
        n_steps_max = pre_steps + n_ticks * substeps
        bound, drag = self._bound, self._drag
        n_vert = bound.n_vert
        vert_hist = np.empty((n_steps_max + 1, n_vert, 3))
        j = 0  # steps taken
        first_contact: float | None = None

        drag_every = max(1, round(DRAG_HOLD_S / sim_dt))
        bend = self._bend

        def step() -> None:
            nonlocal j, first_contact
            if j % drag_every == 0:
                drag.apply(d)
            bend.apply(d)  # adds to the drag; every step (it is solved at the step's end)
            mujoco.mj_step(m, d)
            j += 1
            vert_hist[j - 1] = d.flexvert_xpos[bound.vert_adr : bound.vert_adr + n_vert]
            if first_contact is None and bound.self_contact(m, d):
                first_contact = (j - 1) * sim_dt

        def verdict() -> str:
            return classify_centreline(d.qpos[bound.vert_qpos] + bound.body_pos0)

        for _ in range(pre_steps):
            step()
        q_meas = np.empty((n_ticks, N_JOINTS))
        tip_pos = np.empty((n_ticks, 3))
        tip_quat = np.empty((n_ticks, 4))
        q_sent = np.empty((n_ticks, N_JOINTS))
        hold = None
        # The settle starts when the last command sample has been sent and held one tick.
        monitor = SettleMonitor(rule, t_end=pre_steps * sim_dt + n_cmd * tick)
        end_dof = bound.vert_dof[-1]
        bar = tqdm(
            total=round((n_cmd * tick + rule.min_s) if fault is None else n_ticks * tick, 2),
            unit="sim s",
            disable=bar_disable(progress),
            desc=f"trial (rope {self.rope_params.id})",
            bar_format=_BAR,
        )
        n_done = n_ticks
        for i in range(n_ticks):
            if i % 25 == 0:
                bar.n = min(round(i * tick, 2), bar.total)
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
            if fault is None and i + 1 >= n_cmd:
                speed = float(np.linalg.norm(d.qvel[end_dof]))
                touching = bound.self_contact(m, d)
                if monitor.observe(j * sim_dt, speed, verdict, touching):
                    n_done = i + 1
                    break
        n_ticks = n_done
        n_steps = pre_steps + n_ticks * substeps
        q_meas, tip_pos, tip_quat, q_sent = (
            a[:n_ticks] for a in (q_meas, tip_pos, tip_quat, q_sent)
        )
        vert_hist = vert_hist[: n_steps + 1]
        t_hist = sim_dt * np.arange(n_steps + 1)
        mujoco.mj_kinematics(m, d)
        vert_hist[n_steps] = bound.vertex_positions(m, d)
        bar.n = bar.total
        bar.close()
        # Joints are stamped on the robot's clock (0 at the first command sample); markers
        # and contact times on the motion-capture clock (0 at the nominal start). The two
        # differ by the unknown start delay, as unsynchronised lab clocks do.
        t_joint = np.arange(n_ticks) * tick
        markers_true = bound.markers_from_vertices(vert_hist)
        t_mocap = mocap.sample_times(t_hist[-1], self.params.mocap.rate_hz)
        markers = mocap.emulate(
            t_hist, markers_true, t_mocap, first_contact, self.params.mocap, rng
        )
        knot = None
        settle_meta = None
        if fault is None:
            outcome = monitor.outcome
            knot = outcome.verdict
            settle_meta = outcome.as_metadata(rule)
        truth = _truth(
            t_hist,
            vert_hist,
            bound,
            self.params.truth_rate_hz,
            sim_dt,
            t_full=monitor.t_end + rule.min_s,
        )
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
                **rope_record(self.rope_params, self.params.ropes),
                "seed": self.params.seed,
                "trial_index": trial_index,
                "start_delay_s": delay,
                "command_duration_s": command.duration,
                "sim_duration_s": float(t_hist[-1]),
                "sim_timestep_s": sim_dt,
                "settle": settle_meta,
                "aero": self.params.aero.enabled,
                "versions": {
                    "flyknot": __version__,
                    "mujoco": mujoco.__version__,
                    "python": platform.python_version(),
                },
            },
            truth=truth,
        )


# Truth frames after this long past the command's end are kept at this interval only (the
# rope hangs still; a long settle would otherwise fill the record) [s].
_TRUTH_TAIL_INTERVAL_S = 0.1


def _truth(
    t_hist: np.ndarray,
    vert_hist: np.ndarray,
    rope,
    rate_hz: float,
    sim_dt: float,
    *,
    t_full: float,
) -> dict[str, np.ndarray]:
    """Sim-only truth: centreline and markers at ``rate_hz`` until ``t_full`` [s], then every
    :data:`_TRUTH_TAIL_INTERVAL_S`, always with the last sample."""
    stride = max(1, round(1.0 / (rate_hz * sim_dt)))
    tail = max(stride, round(_TRUTH_TAIL_INTERVAL_S / sim_dt))
    k_full = int(np.searchsorted(t_hist, t_full))
    idx = np.r_[np.arange(0, min(k_full, len(t_hist)), stride)]
    start = idx[-1] + tail if len(idx) else 0
    idx = np.unique(np.r_[idx, np.arange(start, len(t_hist), tail), len(t_hist) - 1])
    verts = vert_hist[idx]
    return {
        "t_truth": t_hist[idx],
        "centreline": rope.centrelines_from_vertices(verts),
        "markers": rope.markers_from_vertices(verts),
    }

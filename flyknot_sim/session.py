"""One trial of the simulated lab, tick by tick: the run loop of :class:`~flyknot_sim.lab.SimLab`.

A :class:`TrialSession` is a trial in progress. :meth:`SimLab.run` plays a whole command
through one (the command known up front); :meth:`SimLab.start` opens one for a caller that
decides each 4 ms target as it goes (a policy, :mod:`flyknot_app.gym.tick_env`):

1. opening it draws the trial's variation from ``(seed, trial index)``, resets the arm at
   ``q0`` with the rope in a settled start and lets the seeded start delay pass;
2. :meth:`TrialSession.tick` sends one joint target: the arm's servos track it for one tick of
   MuJoCo substeps; :meth:`TrialSession.observe` tells what the lab measures now (joints,
   their velocities, the newest motion-capture frame of the 11 markers);
3. :meth:`TrialSession.finish` holds the last target until the settle rule ends (or, after
   a fault, brakes for ``brake_s``) and returns the :class:`~flyknot.record.TrialRecord`.

The controller's limit checks (:mod:`flyknot_sim.faults`): on a whole command they run up
front and the brake takes effect at the offending sample (``run``, as before); on a stream
they run online (:class:`~flyknot_sim.faults.StreamCheck`: a sample's velocity,
acceleration and torque are known when the next sample arrives), so the brake takes effect
when the controller can know the fault: at the offending sample for a position, one tick
later for the rest. Either way the arm then holds where it is, further targets are refused
and the trial is aborted (no knot verdict).

The observed capture frame is the record's: its noise is drawn from the trial's generator in
frame order, as the record's is, so the record of a stream is the record ``run`` gives for the
same targets (when neither faults). Frames are those of the simulated past (the newest at or
before the last stored simulation step). In ``"random"`` loss mode the observed losses are
drawn from a separate generator (the record's are drawn after the trial, from the trial's).
"""

from __future__ import annotations

import math
import platform
from dataclasses import asdict, dataclass
from typing import Any

import mujoco
import numpy as np
from tqdm import tqdm

from flyknot import __version__
from flyknot.errors import CommandError
from flyknot.judge import with_rope_diameter
from flyknot.progress import bar_disable
from flyknot.record import JointCommand, TrialRecord
from flyknot.rest import SettleMonitor
from flyknot.verdict import judge_centreline, tube_axis_of, tube_knot
from flyknot_sim import faults as faults_mod
from flyknot_sim import mocap
from flyknot_sim.aero import DRAG_HOLD_S
from flyknot_sim.lab_params import LabParams
from flyknot_sim.rope_custom import rope_record

_BAR = "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}]"


@dataclass(frozen=True)
class TickObservation:
    """What the lab measures between two ticks.

    Attributes:
        tick: Ticks played so far [-].
        t: Robot clock [s]: ``tick * dt`` (0 at the first target).
        q: Measured joint angles, shape (7,) [rad].
        qd: Joint velocities, shape (7,) [rad/s].
        markers: The newest motion-capture frame, shape (11, 3) [m], lab frame; NaN where
            tracking is lost.
        t_marker: That frame's time on the capture clock [s] (0 at the nominal start, the
            robot clock plus the start delay).
        fault: The controller's fault once it has faulted (the arm brakes), else None.
    """

    tick: int
    t: float
    q: np.ndarray
    qd: np.ndarray
    markers: np.ndarray
    t_marker: float
    fault: faults_mod.Fault | None


@dataclass(frozen=True)
class Plant:
    """What a trial drives: the lab's MuJoCo model and data and the handles into them, built
    once by :class:`~flyknot_sim.lab.SimLab` and handed to every :class:`TrialSession`.

    Attributes:
        model: The lab's model (arm, rope, scene).
        data: Its data, the one state every trial of the lab advances.
        rope: The rope bound to ``model`` (vertices, markers, self-contact).
        rope_params: The rope's parameters.
        base_pose: Robot base in the lab frame, (x, y, z, qw, qx, qy, qz).
        qadr: qpos addresses of the arm's joints, shape (7,).
        dadr: qvel addresses of the arm's joints, shape (7,).
        act: The arm's servo actuators, shape (7,).
        tip_site: The fingertip site (z axis out of the tube).
        torque_model: The arm alone, for the controller's torque checks.
        drag: Air drag on the rope.
        bend: Bending friction of the rope.
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    rope: Any
    rope_params: Any
    base_pose: np.ndarray
    qadr: np.ndarray
    dadr: np.ndarray
    act: np.ndarray
    tip_site: int
    torque_model: mujoco.MjModel
    drag: Any
    bend: Any


@dataclass(frozen=True)
class TrialStart:
    """How the lab opened a trial.

    Attributes:
        index: The trial's index on the lab (its variation is drawn from ``(seed, index)``).
        rng: The trial's generator, after the lab's draws for the start.
        delay: The start delay the lab drew [s].
        dt: The tick [s].
        substeps: Physics steps per tick (the model's step is ``dt / substeps``).
    """

    index: int
    rng: np.random.Generator
    delay: float
    dt: float
    substeps: int


class TrialSession:
    """A trial of a :class:`~flyknot_sim.lab.SimLab` in progress (module docstring)."""

    def __init__(
        self,
        plant: Plant,
        params: LabParams,
        start: TrialStart,
        q0: np.ndarray,
        *,
        plan: JointCommand | None = None,
        progress: bool = False,
    ):
        """Run trial ``start.index`` from the state the lab set: the arm at rest at ``q0``
        (7,) [rad], the rope in its settled start, the model's step ``start.sim_dt``.

        Args:
            plant: The lab's model and data and the handles into them; the session drives
                them and nothing else of the lab's.
            params: The lab's parameters.
            start: How the lab opened the trial (:meth:`~flyknot_sim.lab.SimLab.start`).
            q0: Start pose [rad].
            plan: The whole command when it is known up front (``SimLab.run``; its first
                sample is ``q0``): the controller checks it before the motion, and the trial's
                clock and settle start from its length. None: a stream checked online.
            progress: Show a progress bar over simulated time (with ``plan``).
        """
        q0 = faults_mod.check_sample(q0)
        self.plant, self.params = plant, params
        self.rng = start.rng
        self.trial_index = start.index
        self.dt = tick = start.dt
        self.substeps = start.substeps
        self.sim_dt = sim_dt = tick / self.substeps
        self.plan = plan
        self._stream: faults_mod.StreamCheck | None = None
        self._plan_fault: faults_mod.Fault | None = None
        if plan is not None:
            # The controller's limit checks on the whole stream up front; the fault takes
            # effect at its tick, mid-motion, like the real controller.
            q_cmd = np.asarray(plan.q)
            qd, qdd = faults_mod.command_derivatives(q_cmd, tick)
            tau = faults_mod.command_torques(plant.torque_model, q_cmd, qd, qdd)
            self._plan_fault = faults_mod.first_fault(q_cmd, tick, torques=tau)
        else:
            self._stream = faults_mod.StreamCheck(q0, tick, torque_model=plant.torque_model)
        self.delay = start.delay
        self.fault: faults_mod.Fault | None = None
        """The controller's fault, once it has faulted."""
        self._brake_at: int | None = None
        self._hold: np.ndarray | None = None
        self._last_target = q0
        self.n_sent = 0
        """Targets taken (ticks of the command; the brake and the settle are not counted)."""
        self.n_ticks = 0
        """Ticks played."""
        self._finished = False
        # Ticks run on the robot clock: tick i starts at sim time delay + i * tick.
        # The arm holds q0 during the delay; the trial's clock starts before it.
        # Timing: after mj_step number j, body positions and contacts in MjData are those of
        # the state *before* that step (MuJoCo computes them in the step's forward pass), so
        # the reading after step j is stored as sample j - 1 (time (j - 1) * sim_dt); the last
        # sample comes from one mj_kinematics at the end.
        self.pre_steps = round(self.delay / sim_dt)
        self._n_vert = plant.rope.n_vert
        rule = params.settle_rule
        n_guess = plan.n + math.ceil(rule.max_s / tick - 1e-9) if plan is not None else 256
        self._vert = np.empty((self.pre_steps + n_guess * self.substeps + 1, self._n_vert, 3))
        self.j = 0
        """Simulation steps taken."""
        self.first_contact: float | None = None
        self._drag_every = max(1, round(DRAG_HOLD_S / sim_dt))
        self._q_meas: list[np.ndarray] = []
        self._tip_pos: list[np.ndarray] = []
        self._tip_quat: list[np.ndarray] = []
        self._q_sent: list[np.ndarray] = []
        self._noise = np.empty((0,))  # capture noise of the frames observed so far
        self._obs_rng = np.random.default_rng([params.seed, self.trial_index, 1])
        self._frame: tuple[int, np.ndarray] | None = None  # the newest observed frame
        self._bar = None
        if plan is not None:
            pf = self._plan_fault
            n_total = (
                plan.n * tick + rule.min_s
                if pf is None
                else (pf.tick + round(params.brake_s / tick) + 1) * tick
            )
            self._bar = tqdm(
                total=round(n_total, 2),
                unit="sim s",
                disable=bar_disable(progress),
                desc=f"trial (rope {plant.rope_params.id})",
                bar_format=_BAR,
            )
        for _ in range(self.pre_steps):
            self._step()

    # ------------------------------------------------------------------------------------
    def _step(self) -> None:
        p = self.plant
        m, d, bound = p.model, p.data, p.rope
        if self.j % self._drag_every == 0:
            p.drag.apply(d)
        p.bend.apply(d)  # adds to the drag; every step (it is solved at the step's end)
        mujoco.mj_step(m, d)
        self.j += 1
        if self.j >= self._vert.shape[0]:  # room for this sample and the last one
            grown = np.empty((2 * self._vert.shape[0], self._n_vert, 3))
            grown[: self.j] = self._vert[: self.j]
            self._vert = grown
        n = self._n_vert
        self._vert[self.j - 1] = d.flexvert_xpos[bound.vert_adr : bound.vert_adr + n]
        if self.first_contact is None and bound.self_contact(m, d):
            self.first_contact = (self.j - 1) * self.sim_dt

    def _advance(self, target: np.ndarray) -> None:
        """One tick: measure, send ``target`` (or the brake's hold), run the substeps."""
        p = self.plant
        m, d = p.model, p.data
        i = self.n_ticks
        if self._bar is not None and i % 25 == 0:
            self._bar.n = min(round(i * self.dt, 2), self._bar.total)
            self._bar.refresh()
        mujoco.mj_kinematics(m, d)  # fingertip pose of the current joint angles
        q_meas = d.qpos[p.qadr]
        self._q_meas.append(q_meas)
        self._tip_pos.append(d.site_xpos[p.tip_site].copy())
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, d.site_xmat[p.tip_site])
        self._tip_quat.append(quat)
        if self._brake_at == i:
            self._hold = q_meas.copy()  # brake: hold where the arm is
        sent = self._hold if self._hold is not None else target
        self._q_sent.append(sent)
        d.ctrl[p.act] = sent
        for _ in range(self.substeps):
            self._step()
        self.n_ticks += 1

    def _check_open(self) -> None:
        if self._finished:
            raise CommandError("the trial is finished; start another")
        if self.fault is not None:
            raise CommandError(f"the controller faulted ({self.fault.reason}); finish() the trial")

    def send(self, target: np.ndarray) -> faults_mod.Fault | None:
        """Play the next tick with joint ``target`` (7,) [rad]; the fault if the controller
        faults now (the arm brakes from this tick; :meth:`finish` the trial then).

        Raises:
            CommandError: ``target`` is not 7 finite numbers, or the trial has faulted or is
                finished (nothing changes then).
        """
        self._check_open()
        target = faults_mod.check_sample(target)
        i = self.n_ticks
        if self._stream is not None:
            fault = self._stream.push(target)
        else:
            pf = self._plan_fault
            fault = pf if pf is not None and pf.tick == i else None
        if fault is not None:
            self.fault, self._brake_at = fault, i
        self._last_target = target
        self._advance(target)
        self.n_sent += 1
        return fault

    def tick(self, target: np.ndarray) -> TickObservation:
        """:meth:`send` ``target``, then :meth:`observe`."""
        self.send(target)
        return self.observe()

    # ------------------------------------------------------------------------------------
    def observe(self) -> TickObservation:
        """What the lab measures now (the newest capture frame: module docstring)."""
        p, rate = self.plant, self.params.mocap.rate_hz
        d = p.data
        k = 0
        if self.j > 0:  # frames up to the newest stored sample, time (j - 1) * sim_dt
            k = len(mocap.sample_times((self.j - 1) * self.sim_dt, rate)) - 1
        if self._frame is None or self._frame[0] != k:
            self._frame = (k, self._capture_frame(k))
        return TickObservation(
            tick=self.n_ticks,
            t=self.n_ticks * self.dt,
            q=d.qpos[p.qadr].copy(),
            qd=d.qvel[p.dadr].copy(),
            markers=self._frame[1].copy(),
            t_marker=k / rate,
            fault=self.fault,
        )

    def _capture_frame(self, k: int) -> np.ndarray:
        """Capture frame ``k`` (11, 3) [m] as the record will hold it (module docstring)."""
        p, mp = self.plant, self.params.mocap
        t_k = np.array([k / mp.rate_hz])  # the frame's time as mocap.sample_times gives it
        if self.j == 0:  # before the first step: the reset state, at t = 0
            verts = p.rope.vertex_positions(p.model, p.data)[None]
            t_hist = np.zeros(1)
        else:  # the stored samples around t_k (the pair the whole history would interpolate)
            j0 = math.floor(t_k[0] / self.sim_dt)
            lo, hi = max(0, j0 - 2), min(self.j, j0 + 3)
            verts = self._vert[lo:hi]
            t_hist = self.sim_dt * np.arange(lo, hi)
        true = mocap.resample_markers(t_hist, p.rope.markers_from_vertices(verts), t_k)
        noisy = true + self._noise_rows(k + 1, true.shape[1:])[k] if mp.noise_std > 0 else true
        rng = self._obs_rng if mp.loss_mode == "random" else self.rng  # the latter: no draw
        return mocap.apply_tracking_loss(t_k, noisy, self.first_contact, mp, rng)[0]

    def _noise_rows(self, n: int, shape: tuple[int, ...]) -> np.ndarray:
        """The capture noise of frames 0 .. n - 1, shape (n, *shape) [m], drawn in frame
        order from the trial's generator (a draw in pieces equals one draw of the whole)."""
        have = len(self._noise)
        if n > have:
            std = self.params.mocap.noise_std
            more = self.rng.normal(0.0, std, size=(n - have, *shape))
            self._noise = more if have == 0 else np.concatenate([self._noise, more])
        return self._noise[:n]

    # ------------------------------------------------------------------------------------
    def finish(self) -> TrialRecord:
        """Hold the last target until the settle rule ends (after a fault: brake for
        ``brake_s``), judge the knot and return the trial's record.

        Raises:
            CommandError: No target was sent, or the trial is finished already.
        """
        if self._finished:
            raise CommandError("the trial is finished already")
        if self.n_sent == 0:
            raise CommandError("no target was sent; tick() at least once before finish()")
        self._finished = True
        p = self.plant
        m, d, bound = p.model, p.data, p.rope
        params, tick, sim_dt = self.params, self.dt, self.sim_dt
        rule = params.settle_rule
        n_cmd = self.plan.n if self.plan is not None else self.n_sent
        if self._stream is not None and self.fault is None:
            fault = self._stream.close()  # the last sample's derivatives: hold after it
            if fault is not None:
                self.fault, self._brake_at = fault, self.n_ticks
        # The settle starts when the last command sample has been sent and held one tick.
        monitor = SettleMonitor(
            rule, t_end=self.pre_steps * sim_dt + n_cmd * tick, diameter=p.rope_params.diameter
        )
        if self.fault is not None:
            n_total = self._brake_at + round(params.brake_s / tick) + 1
            while self.n_ticks < n_total:
                self._advance(self._last_target)
        else:
            end_dof = bound.vert_dof[-1]
            n_max = n_cmd + math.ceil(rule.max_s / tick - 1e-9)

            def verdict() -> str:
                axis = d.site_xmat[p.tip_site].reshape(3, 3)[:, 2]
                return tube_knot(d.qpos[bound.vert_qpos] + bound.body_pos0, axis)

            def knot_region() -> tuple[tuple[int, int] | None, np.ndarray]:
                return bound.self_contact_span(m, d), d.qpos[bound.vert_qpos] + bound.body_pos0

            def settled() -> bool:
                speed = float(np.linalg.norm(d.qvel[end_dof]))
                touching = bound.self_contact(m, d)
                return monitor.observe(self.j * sim_dt, speed, verdict, touching, knot_region)

            done = settled()
            while not done and self.n_ticks < n_max:
                self._advance(self._last_target)
                done = settled()
        return self._record(monitor)

    def _record(self, monitor: SettleMonitor) -> TrialRecord:
        p = self.plant
        m, d, bound = p.model, p.data, p.rope
        params, sim_dt, rule, fault = self.params, self.sim_dt, self.params.settle_rule, self.fault
        n_ticks = self.n_ticks
        n_steps = self.j
        q_meas, tip_pos, tip_quat, q_sent = (
            np.array(a).reshape(n_ticks, -1)
            for a in (self._q_meas, self._tip_pos, self._tip_quat, self._q_sent)
        )
        vert_hist = self._vert[: n_steps + 1]
        t_hist = sim_dt * np.arange(n_steps + 1)
        mujoco.mj_kinematics(m, d)
        vert_hist[n_steps] = bound.vertex_positions(m, d)
        if self._bar is not None:
            self._bar.n = self._bar.total
            self._bar.close()
        # Joints are stamped on the robot's clock (0 at the first command sample); markers
        # and contact times on the motion-capture clock (0 at the nominal start). The two
        # differ by the unknown start delay, as unsynchronised lab clocks do.
        t_joint = np.arange(n_ticks) * self.dt
        t_mocap, markers = self._captured(t_hist, vert_hist)
        verdict = None
        settle_meta = None
        if fault is None:
            judge = with_rope_diameter(p.rope_params.diameter)
            verdict = judge_centreline(vert_hist[n_steps], tube_axis_of(tip_quat[-1]), judge)
            settle_meta = monitor.outcome.as_metadata(rule)
        truth = _truth(
            t_hist,
            vert_hist,
            bound,
            params.truth_rate_hz,
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
            base_pose=p.base_pose,
            fault=None if fault is None else fault.reason,
            fault_time=None if fault is None else float(t_joint[fault.tick]),
            first_contact_time=self.first_contact,
            knot=None if verdict is None else verdict.knot,
            verdict=verdict,
            metadata=self._metadata(float(t_hist[-1]), settle_meta),
            truth=truth,
        )

    def _captured(self, t_hist: np.ndarray, vert_hist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The motion capture of the whole trial: its frame times (k,) [s] and markers
        (k, 11, 3) [m] from the rope's vertices at every step, as :func:`mocap.emulate`
        makes them, with the frames' noise drawn in frame order as observed."""
        mp = self.params.mocap
        markers_true = self.plant.rope.markers_from_vertices(vert_hist)
        t_mocap = mocap.sample_times(t_hist[-1], mp.rate_hz)
        true = mocap.resample_markers(t_hist, markers_true, t_mocap)
        noisy = (
            true + self._noise_rows(len(t_mocap), true.shape[1:])
            if mp.noise_std > 0
            else true.copy()
        )
        return t_mocap, mocap.apply_tracking_loss(t_mocap, noisy, self.first_contact, mp, self.rng)

    def _metadata(self, sim_duration: float, settle_meta: dict | None) -> dict:
        """The record's metadata: the cell, the rope, the trial's seed and index, the lab's
        variation and the start delay it drew, durations and step, the settle's outcome, the
        drag and the versions."""
        params = self.params
        n_cmd = self.plan.n if self.plan is not None else self.n_sent
        duration = self.plan.duration if self.plan is not None else (n_cmd - 1) * self.dt
        return {
            "cell": "sim",
            **rope_record(self.plant.rope_params, params.ropes),
            "seed": params.seed,
            "trial_index": self.trial_index,
            "variation": asdict(params.variation),
            "start_delay_s": self.delay,
            "command_duration_s": duration,
            "sim_duration_s": sim_duration,
            "sim_timestep_s": self.sim_dt,
            "settle": settle_meta,
            "aero": params.aero.enabled,
            "versions": {
                "flyknot": __version__,
                "mujoco": mujoco.__version__,
                "python": platform.python_version(),
            },
        }


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

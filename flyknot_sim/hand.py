"""The hand lab: a free 6-DoF hand that holds rope by its end, for synthetic demonstrations.

Scene (built with ``mujoco.MjSpec``): a floor and a ``hand`` body at ``home`` on six joints,
slides along world x, y, z, then hinges about y (angle b), x (a) and z (c), so the hand's
orientation is R = Ry(b) Rx(a) Rz(c). The rope (:func:`flyknot_sim.rope.add_rope`) hangs from
the hand's origin along the hand's -z axis; a ``fingertip`` site there has its z axis along the
rope's exit (R_tip = R Rx(pi)), the convention of the robot's fingertip site, so a
demonstration's hand pose is directly a fingertip target for the learner. The lab's settings,
its trial variation and the hand's orientation convention are :mod:`flyknot_sim.hand_params`;
the flying-knot motion family is :mod:`flyknot_sim.hand_motion`, replaying a stored
demonstration :mod:`flyknot_sim.hand_replay`.

Servos: each joint has a position servo (kp = I w^2), a velocity servo fed with the target's
rate (kv = 2 I w, critically damped) and a force actuator fed with the target's acceleration
times the joint's inertia I (feed-forward): a hand that knows the motion it makes. The hand
body is gravity-compensated, so only the rope pulls it off its target.

A trial (:meth:`HandLab.run`), like the robot lab's:

1. seeded variation: servo gains x (1 + N(0, servo_gain_rel^2)) each, the rope's initial
   tilt |N(0, sway_deg^2)| towards a uniform azimuth, a start delay uniform in
   [0, start_delay_max_s) and a tempo factor 1 + N(0, tempo_rel^2) on the motion's duration;
2. hand at the motion's first pose, rope hanging at rest; ``hang_s`` still, then the motion
   (targets evaluated at every step's end), then ``settle_s`` holding its last pose;
3. the knot is judged on the settled centreline; ``knot_any`` and the fraction of knotted
   settling frames are judged on frames every 1 / ``judge_rate_hz`` seconds (for search
   shaping: knots often form and then slide off the free end).

Everything is recorded at every simulation step (hand pose, joint targets and positions, rope
vertices, the first rope self-contact); :func:`trial_demonstration` turns a trial into what the
motion capture of a human demonstration gives (200 Hz, marker noise and tracking loss by
:func:`flyknot_sim.mocap.emulate`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from flyknot.demo import Demonstration
from flyknot.errors import ConfigError
from flyknot.geometry import quat_sign_continuous
from flyknot.knot import TREFOIL
from flyknot.rest import SettleMonitor, start_with_sway
from flyknot.verdict import Verdict, judge_centreline, tube_knot
from flyknot_sim import mocap
from flyknot_sim.aero import DRAG_HOLD_S, RopeDrag
from flyknot_sim.bend_friction import RopeBendFriction
from flyknot_sim.hand_params import HandParams, JointTrajectory
from flyknot_sim.rope import add_rope, configure_options
from flyknot_sim.rope_handle import BoundRope

__all__ = [
    "FINGERTIP_SITE",
    "HAND_BODY",
    "HAND_JOINTS",
    "HandLab",
    "HandTrial",
    "build_hand_scene",
    "judged_frames",
    "trial_demonstration",
]

HAND_BODY = "hand"
FINGERTIP_SITE = "fingertip"
HAND_JOINTS = ("hand_x", "hand_y", "hand_z", "hand_b", "hand_a", "hand_c")
"""Slides along world x, y, z; hinges about y (b), x (a), z (c): R = Ry(b) Rx(a) Rz(c)."""
_JOINT_AXES = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 1, 0), (1, 0, 0), (0, 0, 1))
_FINGERTIP_QUAT = (0.0, 1.0, 0.0, 0.0)  # Rx(pi): site z along the rope's exit (hand -z)
N_HAND_DOF = 6


# ----------------------------------------------------------------------------------------
# scene
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HandScene:
    """A compiled hand scene.

    Attributes:
        model: The compiled model.
        rope: The rope bound to ``model``.
        qpos: qpos addresses of the hand joints, shape (6,).
        dof: dof addresses of the hand joints, shape (6,).
        act_pos: Position-servo actuator ids, shape (6,).
        act_vel: Velocity-servo actuator ids, shape (6,).
        act_ff: Feed-forward force actuator ids, shape (6,).
        fingertip: Fingertip site id.
    """

    model: mujoco.MjModel
    rope: BoundRope
    qpos: np.ndarray
    dof: np.ndarray
    act_pos: np.ndarray
    act_vel: np.ndarray
    act_ff: np.ndarray
    fingertip: int


def build_hand_scene(params: HandParams) -> HandScene:
    """Compile floor + hand + rope ``params.rope`` (see the module docstring)."""
    rope_params = params.rope_params
    spec = mujoco.MjSpec()
    spec.modelname = "flyknot_hand"
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[3.0, 3.0, 0.1],
        contype=1,
        conaffinity=1,
    )
    hand = spec.worldbody.add_body(name=HAND_BODY, pos=list(params.home), gravcomp=1.0)
    hand.explicitinertial = True
    hand.ipos = [0.0, 0.0, 0.0]
    hand.iquat = [1.0, 0.0, 0.0, 0.0]
    hand.mass = params.hand_mass
    hand.inertia = [params.hand_inertia] * 3
    hand.add_geom(
        name="palm",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[0.012, 0, 0],
        pos=[0, 0, 0.015],
        contype=0,
        conaffinity=0,
        mass=0.0,
        rgba=[0.85, 0.65, 0.55, 1],
    )
    hand.add_site(name=FINGERTIP_SITE, quat=list(_FINGERTIP_QUAT))
    kp, kv = params.servo_gains()
    for i, (name, axis) in enumerate(zip(HAND_JOINTS, _JOINT_AXES, strict=True)):
        slide = i < 3
        hand.add_joint(
            name=name,
            axis=list(axis),
            type=mujoco.mjtJoint.mjJNT_SLIDE if slide else mujoco.mjtJoint.mjJNT_HINGE,
            armature=0.0 if slide else params.hinge_armature,
        )
        a = spec.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        a.set_to_position(kp=float(kp[i]))
        v = spec.add_actuator(name=f"{name}_vel", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        v.set_to_velocity(kv=float(kv[i]))
        f = spec.add_actuator(name=f"{name}_ff", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        f.set_to_motor()
    handle = add_rope(
        spec,
        rope_params,
        anchor_body=HAND_BODY,
        axis=(0.0, 0.0, -1.0),
        prefix="rope",
        settings=params.settings,
        twist=params.twist,
    )
    configure_options(spec, [rope_params], params.settings)
    model = spec.compile()
    jid = [model.joint(n).id for n in HAND_JOINTS]
    return HandScene(
        model=model,
        rope=handle.bind(model),
        qpos=model.jnt_qposadr[jid].astype(int),
        dof=model.jnt_dofadr[jid].astype(int),
        act_pos=np.array([model.actuator(f"{n}_pos").id for n in HAND_JOINTS]),
        act_vel=np.array([model.actuator(f"{n}_vel").id for n in HAND_JOINTS]),
        act_ff=np.array([model.actuator(f"{n}_ff").id for n in HAND_JOINTS]),
        fingertip=model.site(FINGERTIP_SITE).id,
    )


# ----------------------------------------------------------------------------------------
# trial
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HandTrial:
    """What one hand trial produced (sim-only data; a demonstration is made from it).

    Attributes:
        t: Times of the saved states, shape (N + 1,) [s], 0 = trial start.
        hand_pos: Fingertip position, shape (N + 1, 3) [m].
        hand_quat: Fingertip orientation (w, x, y, z), sign-continuous, shape (N + 1, 4).
        q: Hand joint positions, shape (N + 1, 6) [m, rad] (slides relative to ``home``).
        q_target: Hand joint targets, shape (N + 1, 6) [m, rad].
        vertices: Rope centreline vertices, shape (N + 1, n + 1, 3) [m].
        first_contact: Time of the rope's first self-contact [s], or None.
        motion_start: Time the motion starts (``hang_s`` + start delay) [s].
        motion_end: Time the motion ends [s].
        knot: Knot type of the settled rope (``unknot``, ``trefoil``, ...), None if the
            simulation diverged.
        verdict: The settled rope's verdict with its evidence (:mod:`flyknot.verdict`), None
            if not judged.
        knot_any: A trefoil in any judged frame from the motion's start on.
        settle_fraction: Fraction of the judged frames in the settling phase that are
            trefoils (the last frame included).
        judged: Indices into ``t`` of the judged frames, shape (J,) (empty if not judged).
        diverged: MuJoCo reset the state (NaN) during the trial.
        variation: The drawn variation (gain factors, sway, azimuth, delay, tempo).
        wall_s: Wall time of the trial [s].
        settle: How the settle ended (:meth:`flyknot.rest.SettleOutcome.as_metadata`), None
            when not judged.
    """

    t: np.ndarray
    hand_pos: np.ndarray
    hand_quat: np.ndarray
    q: np.ndarray
    q_target: np.ndarray
    vertices: np.ndarray
    first_contact: float | None
    motion_start: float
    motion_end: float
    knot: str | None
    verdict: Verdict | None
    knot_any: bool
    settle_fraction: float
    judged: np.ndarray
    diverged: bool
    variation: Mapping[str, Any]
    wall_s: float
    settle: Mapping[str, Any] | None = None

    @property
    def tied(self) -> bool:
        """The settled rope holds an overhand knot in the hanging rope (verdict ``knot``)."""
        return self.verdict is not None and self.verdict.success

    def tracking_error(self) -> tuple[float, float]:
        """Largest servo tracking errors max_t |p - p_target| [m] and
        max_t max_j |angle_j - target_j| [rad] over the trial."""
        e = self.q - self.q_target
        return float(np.max(np.linalg.norm(e[:, :3], axis=1))), float(np.max(np.abs(e[:, 3:])))


class HandLab:
    """The hand lab: compiles the scene once and plays hand motions on it."""

    def __init__(self, params: HandParams | None = None):
        self.params = HandParams() if params is None else params
        self.scene = build_hand_scene(self.params)
        self.model = self.scene.model
        self.data = mujoco.MjData(self.model)
        self._kp0 = self.model.actuator_gainprm[self.scene.act_pos, 0].copy()
        self._bias0 = self.model.actuator_biasprm[self.scene.act_pos, :3].copy()
        self._kv0 = self.model.actuator_gainprm[self.scene.act_vel, 0].copy()
        self._vbias0 = self.model.actuator_biasprm[self.scene.act_vel, :3].copy()
        self._inertia = self.params.joint_inertia()
        aero = self.params.aero
        cd = self.params.rope_params.cd
        if cd is not None:  # the rope's own drag coefficient
            aero = dataclasses.replace(aero, cd=cd)
        self._drag = RopeDrag(self.scene.rope, aero)
        self._bend = RopeBendFriction(
            self.scene.rope, self.params.bend_friction.moment_for(self.params.rope_params)
        )

    @staticmethod
    def nominal_variation() -> dict[str, Any]:
        """The variation of a nominal trial: unit gain factors, no sway, delay or tempo
        change."""
        return _nominal_variation()

    @property
    def rope(self) -> BoundRope:
        """The rope bound to the model."""
        return self.scene.rope

    def draw_variation(self, rng: np.random.Generator) -> dict[str, Any]:
        """Draw one trial's variation (see :class:`HandVariation`).

        Returns:
            ``kp_factor`` (6,), ``kv_factor`` (6,), ``sway`` [rad], ``azimuth`` [rad],
            ``sway_rate`` [rad/s], ``delay`` [s], ``tempo`` [-].
        """
        if not isinstance(rng, np.random.Generator):
            raise ConfigError("rng", f"must be a numpy.random.Generator, got {type(rng).__name__}")
        v = self.params.variation
        kp = 1.0 + v.servo_gain_rel * rng.standard_normal(N_HAND_DOF)
        kv = 1.0 + v.servo_gain_rel * rng.standard_normal(N_HAND_DOF)
        sway = math.radians(v.sway_deg) * abs(float(rng.standard_normal()))
        azimuth = float(rng.uniform(0.0, 2.0 * math.pi))
        delay = float(rng.uniform(0.0, v.start_delay_max_s)) if v.start_delay_max_s else 0.0
        tempo = 1.0 + v.tempo_rel * float(rng.standard_normal())
        rate = 0.0
        if v.rest_start:
            p = self.params
            sway, azimuth, rate = start_with_sway(
                rng, p.settle.rest, p.rope_params.length, sway, azimuth, v.rest_scale
            )
        return {
            "kp_factor": np.clip(kp, 0.5, 1.5).tolist(),
            "kv_factor": np.clip(kv, 0.5, 1.5).tolist(),
            "sway": min(sway, math.radians(30.0)),
            "azimuth": azimuth,
            "sway_rate": rate,
            "delay": delay,
            "tempo": tempo,
        }

    def _apply_gains(self, kp_factor: np.ndarray, kv_factor: np.ndarray) -> None:
        m, s = self.model, self.scene
        m.actuator_gainprm[s.act_pos, 0] = self._kp0 * kp_factor
        m.actuator_biasprm[s.act_pos, :3] = self._bias0 * kp_factor[:, None]
        m.actuator_gainprm[s.act_vel, 0] = self._kv0 * kv_factor
        m.actuator_biasprm[s.act_vel, :3] = self._vbias0 * kv_factor[:, None]

    def run(
        self,
        motion: JointTrajectory,
        rng: np.random.Generator | None = None,
        *,
        variation: Mapping[str, Any] | None = None,
        judge: bool = True,
    ) -> HandTrial:
        """Play ``motion`` once from rest (see the module docstring).

        Args:
            motion: Hand joint targets over time.
            rng: Source of the variation (ignored if ``variation`` is given); None draws
                nothing and plays the nominal trial.
            variation: A variation as returned by :meth:`draw_variation` (to replay one).
            judge: Judge the knot (False skips knot classification: ``knot`` is None).

        Returns:
            The trial.
        """
        if variation is None:
            variation = self.draw_variation(rng) if rng is not None else _nominal_variation()
        tic = time.perf_counter()
        p, rule = self.params, self.params.settle_rule
        wait = rule.max_s if judge else rule.min_s  # unjudged trials need no rest
        plan = _Plan.of(motion, variation, p.hang_s, wait, self.model.opt.timestep, self._inertia)
        self._start(plan.q[0], variation)
        monitor = SettleMonitor(rule, t_end=plan.motion_end, diameter=p.rope_params.diameter)
        played = self._play(plan, monitor if judge else None)
        t, verts = played.t, played.vertices
        knot: str | None = None
        final: Verdict | None = None
        knot_any = False
        settle_fraction = 0.0
        judged = np.zeros(0, dtype=int)
        settle_meta = None
        if judge and not played.diverged:
            judged = judged_frames(t, plan.motion_start, p.judge_rate_hz)
            knot, knot_any, settle_fraction = _judge(t, verts, judged, plan.motion_end)
            if monitor.observe(float(t[-1]), float("nan"), self._verdict):  # the cap reached
                settle_meta = monitor.outcome.as_metadata(rule)
            final = judge_centreline(verts[-1], params=p.judge_params)
            knot = final.knot
        return HandTrial(
            t=t,
            hand_pos=played.pos,
            hand_quat=quat_sign_continuous(played.quat),
            q=played.q,
            q_target=plan.q[: len(t)],
            vertices=verts,
            first_contact=played.first_contact,
            motion_start=plan.motion_start,
            motion_end=plan.motion_end,
            knot=knot,
            verdict=final,
            knot_any=knot_any,
            settle_fraction=settle_fraction,
            judged=judged,
            diverged=played.diverged,
            variation=dict(variation),
            wall_s=time.perf_counter() - tic,
            settle=settle_meta,
        )

    def _start(self, q0: np.ndarray, variation: Mapping[str, Any]) -> None:
        """Reset to the hand at ``q0`` (6,) with the variation's servo gains and the rope
        hanging at rest, tilted by its sway."""
        m, d, s = self.model, self.data, self.scene
        mujoco.mj_resetData(m, d)
        self._apply_gains(np.asarray(variation["kp_factor"]), np.asarray(variation["kv_factor"]))
        d.qpos[s.qpos] = q0
        mujoco.mj_kinematics(m, d)
        s.rope.set_hanging(
            m,
            d,
            float(variation["sway"]),
            float(variation["azimuth"]),
            float(variation.get("sway_rate", 0.0)),
        )

    def _verdict(self) -> str:
        """The knot type of the rope as it is now."""
        rope = self.scene.rope
        return tube_knot(self.data.qpos[rope.vert_qpos] + rope.body_pos0)

    def _knot_region(self) -> tuple[tuple[int, int] | None, np.ndarray]:
        """The rope's self-contact span and its vertices now."""
        rope, d = self.scene.rope, self.data
        return rope.self_contact_span(self.model, d), d.qpos[rope.vert_qpos] + rope.body_pos0

    def _sample(self, out: _Played, k: int) -> None:
        """Store sample ``k``: the positions MuJoCo computed last (a step computes them
        before it integrates, so after k steps they are the state at t_k)."""
        d, s = self.data, self.scene
        out.vertices[k] = d.flexvert_xpos[s.rope.vert_adr : s.rope.vert_adr + s.rope.n_vert]
        out.q[k] = d.qpos[s.qpos]
        out.pos[k] = d.site_xpos[s.fingertip]
        mujoco.mju_mat2Quat(out.quat[k], d.site_xmat[s.fingertip])

    def _play(self, plan: _Plan, monitor: SettleMonitor | None) -> _Played:
        """Step through ``plan`` from the state :meth:`_start` set, recording every step,
        until its end, a settle end of ``monitor`` (None: no settle rule) or a divergence
        (MuJoCo resets a diverged state: the samples after it are NaN)."""
        m, d, s = self.model, self.data, self.scene
        rope, n_steps = s.rope, len(plan.t) - 1
        out = _Played.empty(plan.t, rope.n_vert)
        drag_every = max(1, round(DRAG_HOLD_S / m.opt.timestep))
        end_dof = rope.vert_dof[-1]
        for k in range(n_steps + 1):
            self._sample(out, k)
            if out.first_contact is None and k > 0 and rope.self_contact(m, d):
                out.first_contact = float(plan.t[k])
            if k == n_steps:
                break
            d.ctrl[s.act_pos] = plan.q[k + 1]
            d.ctrl[s.act_vel] = plan.qd[k + 1]
            d.ctrl[s.act_ff] = plan.ff[k + 1]
            before = d.time
            if k % drag_every == 0:
                self._drag.apply(d)
            self._bend.apply(d)
            mujoco.mj_step(m, d)
            if d.time < before:
                out.diverged = True
                for a in (out.vertices, out.q, out.pos, out.quat):
                    a[k + 1 :] = np.nan
                break
            t_next = float(plan.t[k + 1])
            if monitor is not None and t_next >= monitor.t_end - 1e-9:
                speed = float(np.linalg.norm(d.qvel[end_dof]))
                touching = rope.self_contact(m, d)
                if monitor.observe(t_next, speed, self._verdict, touching, self._knot_region):
                    # The state after this step is the last sample.
                    out.vertices[k + 1] = d.qpos[rope.vert_qpos] + rope.body_pos0
                    out.q[k + 1] = d.qpos[s.qpos]
                    mujoco.mj_kinematics(m, d)
                    out.pos[k + 1] = d.site_xpos[s.fingertip]
                    mujoco.mju_mat2Quat(out.quat[k + 1], d.site_xmat[s.fingertip])
                    return out.upto(k + 1)
        return out


@dataclass(frozen=True)
class _Plan:
    """A trial's clock and the hand's targets on it: every step's time t (n + 1,) [s] and the
    joint targets q, rates qd and inertial feed-forward ff (n + 1, 6), the motion played
    ``tempo`` times slower from ``motion_start``."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    ff: np.ndarray
    motion_start: float
    motion_end: float

    @staticmethod
    def of(
        motion: JointTrajectory,
        variation: Mapping[str, Any],
        hang_s: float,
        wait_s: float,
        dt: float,
        inertia: np.ndarray,
    ) -> _Plan:
        """The plan of ``motion`` under ``variation`` after ``hang_s`` still, waiting
        ``wait_s`` after it, on steps of ``dt`` [s]; ``inertia`` (6,) the joints' [kg, kg m^2]."""
        tempo = float(variation["tempo"])
        motion_start = hang_s + float(variation["delay"])
        motion_end = motion_start + float(motion.duration) * tempo
        n_steps = math.ceil((motion_end + wait_s) / dt - 1e-9)
        t = dt * np.arange(n_steps + 1)
        q, qd, qdd = motion.joint_targets((t - motion_start) / tempo)
        return _Plan(t, q, qd / tempo, qdd / tempo**2 * inertia, motion_start, motion_end)


@dataclass
class _Played:
    """What :meth:`HandLab._play` recorded, one row per step (module docstring)."""

    t: np.ndarray
    vertices: np.ndarray
    q: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    first_contact: float | None = None
    diverged: bool = False

    @staticmethod
    def empty(t: np.ndarray, n_vert: int) -> _Played:
        """Room for a sample at every time of ``t``."""
        n = len(t)
        return _Played(
            t,
            np.empty((n, n_vert, 3)),
            np.empty((n, N_HAND_DOF)),
            np.empty((n, 3)),
            np.empty((n, 4)),
        )

    def upto(self, k: int) -> _Played:
        """Samples 0 .. k."""
        a = (self.t, self.vertices, self.q, self.pos, self.quat)
        return _Played(*(x[: k + 1] for x in a), self.first_contact, self.diverged)


def _nominal_variation() -> dict[str, Any]:
    """The variation of a nominal trial (nothing varied)."""
    return {
        "kp_factor": [1.0] * N_HAND_DOF,
        "kv_factor": [1.0] * N_HAND_DOF,
        "sway": 0.0,
        "azimuth": 0.0,
        "sway_rate": 0.0,
        "delay": 0.0,
        "tempo": 1.0,
    }


def judged_frames(t: np.ndarray, start: float, rate_hz: float) -> np.ndarray:
    """Indices of the frames judged for knots: every round(1 / (rate_hz dt)) steps from the
    first step at or after ``start`` [s], plus the last frame; shape (J,)."""
    dt = float(t[1] - t[0])
    stride = max(1, round(1.0 / (rate_hz * dt)))
    k0 = min(math.ceil(start / dt - 1e-9), len(t) - 1)
    return np.array(sorted(set(range(k0, len(t) - 1, stride)) | {len(t) - 1}), dtype=int)


def _judge(
    t: np.ndarray, verts: np.ndarray, judged: np.ndarray, end: float
) -> tuple[str, bool, float]:
    """Knot at the last frame, a trefoil in any judged frame, and the trefoil fraction of
    the judged frames at or after ``end`` [s] (the settling phase)."""
    names = {int(k): tube_knot(verts[k]) for k in judged}
    end_knot = names[len(t) - 1]
    knot_any = any(n == TREFOIL for n in names.values())
    settle = [k for k in names if t[k] >= end - 1e-9]
    fraction = sum(names[k] == TREFOIL for k in settle) / len(settle)
    return end_knot, knot_any, float(fraction)


def trial_demonstration(
    trial: HandTrial,
    rope: BoundRope,
    mocap_params: mocap.MocapParams,
    rng: np.random.Generator,
    *,
    rope_id: int,
    metadata: Mapping[str, Any] | None = None,
) -> Demonstration:
    """A demonstration as the motion capture would record the trial.

    The capture runs at ``mocap_params.rate_hz`` from t = 0 (the trial start) to the trial's
    end. Hand pose: the fingertip's, interpolated linearly (quaternions renormalised) from the
    simulation steps, without noise. Markers: the 11 rope markers through
    :func:`flyknot_sim.mocap.emulate` (noise, NaN from ``first_contact + loss_delay`` on).
    t_c = the first rope self-contact of the simulation.

    Args:
        trial: A trial with a self-contact.
        rope: The rope the trial was run with (for the marker arc lengths).
        mocap_params: Capture settings.
        rng: Source of the capture noise.
        rope_id: Rope id stored in the demonstration.
        metadata: Extra plain data.

    Returns:
        The demonstration.

    Raises:
        ConfigError: The trial diverged or the rope never touched itself (no t_c).
    """
    if trial.diverged:
        raise ConfigError("trial", "diverged; no demonstration can be made from it")
    if trial.first_contact is None:
        raise ConfigError("trial", "the rope never touched itself, so there is no t_c")
    t_mocap = mocap.sample_times(float(trial.t[-1]), mocap_params.rate_hz)
    markers_true = rope.markers_from_vertices(trial.vertices)
    markers = mocap.emulate(trial.t, markers_true, t_mocap, trial.first_contact, mocap_params, rng)
    pos = np.column_stack([np.interp(t_mocap, trial.t, trial.hand_pos[:, i]) for i in range(3)])
    quat = np.column_stack([np.interp(t_mocap, trial.t, trial.hand_quat[:, i]) for i in range(4)])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return Demonstration(
        t=t_mocap,
        hand_pos=pos,
        hand_quat=quat,
        markers=markers,
        t_c=float(trial.first_contact),
        rope=rope_id,
        metadata=dict(metadata or {}),
    )

"""A fake real lab: the simulated lab's whole scene behind a fake xArm controller, in real time.

What the real lab's software talks to, on loopback, and nothing else:

* **The arm and the rope** (:class:`LabScene`): a :class:`flyknot_sim.lab.SimLab`'s MuJoCo
  model and data (xArm 7 with its servos, the rope with air drag and, if configured, bending
  friction) stepped by a thread in chunks of 2 ms, always behind the wall clock (a servo
  target can only act once it has arrived): the target in force at each 1 ms step is the one
  the controller held at that instant of ``time.perf_counter``. The scene thus replays the
  wall clock exactly, a few milliseconds late (the lag is measured; so is the real-time
  factor, simulated seconds per second of computing: about 2 for rope 1 on this 2-core box,
  3.6 flat out; the child process hands the GIL over every 0.1 ms and freezes its start-up
  objects out of the garbage collector, or the physics stalls for tens of milliseconds).
  The report's time stamps are those of the states, so the host's clock mapping (the least
  arrival delay) sees them about one chunk's computing late: the clock offset a trial
  recovers is ~1 ms late (0.6-1.1 ms measured).
* **The controller** (:class:`FakeLabXArm`): :class:`fakes.fake_xarm.FakeXArm` with that scene as
  its arm. It logs every change of its joint target (servo target, position-mode plan, stop)
  with its time, which the scene reads; the 30000 report stamps each frame with the time of
  the state it carries.
* **The motion-capture software** (``fakes.fake_capture.FakeCapture``): 200 Hz frames on its
  own clock (``t_mocap = perf_counter - epoch_s``), the 11 rope markers and a 3-marker cluster
  centred on the fingertip (labels ``fingertip1..3``), 1 mm noise on the rope (0.3 mm on the
  cluster), 1 % random dropouts and a few gaps of several frames, an occasional stray point,
  the rope markers' order shuffled in every frame (their labels mean nothing), every rope
  marker lost from 20 ms after the rope first touches itself (as the simulated lab's
  emulation does). It records from 0.5 s before the controller enters servo mode (a
  pre-trigger buffer) to 0.5 s after it leaves it (or stops), and writes one C3D file (mm)
  per trial, ``trial_YYYYmmdd-HHMMSS.c3d`` stamped with the capture's start (local time),
  into its directory: the file a lab file's ``file = "captures/trial_*.c3d"`` matches by time.
* **The operator's hands and eyes** (:meth:`FakeLab.steady`, :meth:`FakeLab.settle_after`):
  before a throw the rope is re-hung from the fingertip in a state drawn within the rest
  criterion; ``start = "sim"`` (default) does it at the step the stream's first target acts,
  exactly as the simulated lab starts a trial (the capture sees the rope from then on: the
  operator's hands hid it), ``start = "relaxed"`` does it at once and lets the rope relax to
  rest, as a real rope hangs (the simulated lab's start is not at rest: left alone, its free
  end swings by ~5 cm within a second). After the throw the operator waits until the rope
  rests by the simulated lab's rule (:class:`flyknot.rest.SettleMonitor`: free end at rest
  and the knot verdict stable, capped) and reads the knot from the simulated centreline
  (:func:`flyknot.verdict.tube_knot` while settling, :func:`flyknot.verdict.judge_centreline`
  at the end: the class an operator would answer).

:class:`FakeLabProcess` runs a :class:`FakeLab` in a child process (the controller is another
computer; the learner's solver in the test's process must not hold up the physics) and
forwards calls to it.
"""

from __future__ import annotations

import bisect
import contextlib
import gc
import math
import multiprocessing
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from fakes.fake_capture import RATE_HZ, FakeCapture
from fakes.fake_xarm import HOME, FakeXArm
from flyknot.rest import SettleMonitor, SettleParams, start_with_sway
from flyknot.verdict import judge_centreline, tube_knot
from flyknot_sim.aero import DRAG_HOLD_S
from flyknot_sim.lab import LabParams, SimLab
from flyknot_sim.robot import FINGERTIP_BODY, FINGERTIP_SITE, load_robot_model
from flyknot_sim.scene import ROBOT_PREFIX

CHUNK_S = 0.002  # [s] physics chunk (the report's timestamps lag by about one chunk's compute)
SERVO_S = 0.004  # [s] servo period
CLUSTER = 0.03 * np.array([[1.0, 0, 0], [-0.5, 0.866, 0], [-0.5, -0.866, 0]])  # [m] site frame


class LabScene:
    """The simulated lab's scene stepped in real time on a thread (module docstring).

    The controller reads it like its own arm (``q``, ``qd``, ``tau``, ``stamp``, ``advance``,
    ``tcp_pose``); :meth:`steady` re-hangs the rope; frames for the capture and a history for
    the settle check are kept.

    Args:
        rope: The simulated lab's rope id.
        seed: Seed of the servo gains, the rope's settled starts.
        q0: Initial joints (7,) [rad].
        epoch_s: The capture clock's origin on ``perf_counter`` [s].
    """

    def __init__(self, rope: int = 1, seed: int = 0, q0=HOME, epoch_s: float = 0.0):
        self.lab = SimLab(LabParams(rope=rope, seed=seed))
        m, d = self.lab.model, self.lab.data
        self.m, self.d, self.rope = m, d, self.lab.plant.rope
        self.dt = float(m.opt.timestep)
        self.chunk = max(1, round(CHUNK_S / self.dt))
        self.rng = np.random.default_rng([seed, 12345])
        self.lab.reset(np.asarray(q0, dtype=float), self.rng)
        plant = self.lab.plant
        self.qadr, self.dadr, self.act = plant.qadr, plant.dadr, plant.act
        self.site = self.lab.plant.tip_site
        self.end_dof = self.rope.vert_dof[-1]
        self.drag_every = max(1, round(DRAG_HOLD_S / self.dt))
        self.epoch_s = float(epoch_s)
        self.ctrl_at = lambda t: np.asarray(q0, dtype=float)
        self._lock = threading.Lock()
        self._kin = threading.Lock()
        self._robot = load_robot_model()
        self._robot_data = mujoco.MjData(self._robot)
        self._flange = self._robot.body(FINGERTIP_BODY).id
        self._snap = self._snapshot(time.perf_counter())
        self.frames: deque = deque(maxlen=int(RATE_HZ * 120))  # (k, t_wall, rope, cluster)
        # per chunk: (t, free-end speed, self-contact, centreline)
        self.history: deque = deque(maxlen=int(30.0 / CHUNK_S))
        self.contacts: list[float] = []  # wall times at which self-contact began
        self._steady = threading.Event()
        self._relax_s, self._armed = 0.0, False
        self.steadied_at: list[float] = []  # wall times at which the rope was re-hung
        self.stream_start = lambda: None  # when the current servo stream's first target acts
        self._steadied = threading.Event()
        self._run = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = {"sim_s": 0.0, "busy_s": 0.0, "lag": []}

    # --- what the controller reads -----------------------------------------------------
    def _snapshot(self, t: float) -> dict[str, Any]:
        d = self.d
        return {"t": t, "q": d.qpos[self.qadr].copy(), "qd": d.qvel[self.dadr].copy(),
                "tau": d.actuator_force[self.act].copy()}  # fmt: skip

    @property
    def q(self) -> np.ndarray:
        """Joints [rad] at :meth:`stamp`."""
        return self._snap["q"].copy()

    @property
    def qd(self) -> np.ndarray:
        """Joint speeds [rad/s]."""
        return self._snap["qd"].copy()

    @property
    def tau(self) -> np.ndarray:
        """Actuator torques [N m]."""
        return self._snap["tau"].copy()

    def stamp(self, now: float) -> float:
        """Time of the reported state on ``perf_counter`` [s] (a few ms before ``now``)."""
        return self._snap["t"]

    def advance(self, now: float, ctrl_at) -> None:
        """Nothing: the thread steps the scene (the controller's targets come through its
        target log, :attr:`ctrl_at`)."""

    def tcp_pose(self) -> np.ndarray:
        """Flange pose (x, y, z [mm], roll, pitch, yaw [rad]), base frame."""
        with self._kin:
            self._robot_data.qpos[:7] = self.q
            mujoco.mj_kinematics(self._robot, self._robot_data)
            p = self._robot_data.xpos[self._flange] * 1000.0
            r = self._robot_data.xmat[self._flange].reshape(3, 3)
        rpy = [math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1, min(1, r[2, 0]))),
               math.atan2(r[1, 0], r[0, 0])]  # fmt: skip
        return np.concatenate([p, rpy])

    # --- the thread ----------------------------------------------------------------------
    def start(self) -> LabScene:
        """Start stepping (sim time 0 = now)."""
        self._t0 = time.perf_counter()
        self._j = 0
        self._prev: tuple | None = None
        self._k = math.ceil((self._t0 - self.epoch_s) * RATE_HZ)
        self._touching = False
        self._run.set()
        self._thread = threading.Thread(target=self._loop, name="fake-lab-physics", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop stepping."""
        self._run.clear()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def steady(self, relax_s: float = 0.0, timeout: float = 10.0) -> None:
        """Re-hang the rope from the fingertip now, in a state drawn within the rest criterion
        (as the simulated lab starts a trial); with ``relax_s``, then let it relax that long
        [s] with its swing damped critically (outside time: the arm holds), so that it hangs
        at rest in its own shape. Waits until done."""
        self._relax_s = float(relax_s)
        self._steadied.clear()
        self._steady.set()
        if not self._steadied.wait(timeout):
            raise TimeoutError("the physics thread did not steady the rope")

    def steady_at_throw(self) -> None:
        """Re-hang the rope (as :meth:`steady`) at the step the next servo stream's first
        target takes effect: the simulated lab's start, a rope placed 0-4 ms before the
        command (which is not at rest: within a second its free end swings by ~5 cm)."""
        self._armed = True

    def _do_steady(self, t: float, relax_s: float = 0.0) -> None:
        m, d, lab = self.m, self.d, self.lab
        sway, azimuth, rate = start_with_sway(
            self.rng, lab.params.settle.rest, lab.rope_params.length, 0.0, 0.0
        )
        mujoco.mj_kinematics(m, d)
        self.rope.set_hanging(m, d, sway_angle=sway, sway_azimuth=azimuth, sway_rate=rate)
        if relax_s > 0:
            dof = self.rope.vert_dof.ravel()
            keep = m.dof_damping[dof].copy()
            mass = m.body_mass[self.rope.vert_body].repeat(3)
            m.dof_damping[dof] = 2.0 * mass * 3.6  # critical for the first swing mode
            mujoco.mj_step(m, d, round(relax_s / self.dt))
            m.dof_damping[dof] = keep
            d.qvel[dof] = 0.0
            mujoco.mj_forward(m, d)
        self.steadied_at.append(t)
        self._steady.clear()
        self._steadied.set()

    def _loop(self) -> None:
        m, d, rope, dt = self.m, self.d, self.rope, self.dt
        drag, bend = self.lab.plant.drag, self.lab.plant.bend
        adr, nv = rope.vert_adr, rope.n_vert
        while self._run.is_set():
            now = time.perf_counter()
            t_state = self._t0 + self._j * dt
            behind = now - t_state
            if behind < self.chunk * dt:
                time.sleep(self.chunk * dt - behind)
                continue
            self.stats["lag"].append((now, behind))
            busy = time.perf_counter()
            if self._steady.is_set():
                self._do_steady(t_state, self._relax_s)
            for _ in range(self.chunk):
                t_step = self._t0 + self._j * dt
                if self._armed and (self.stream_start() or math.inf) <= t_step:
                    self._armed = False
                    self._do_steady(t_step)
                d.ctrl[self.act] = self.ctrl_at(t_step)
                if self._j % self.drag_every == 0:
                    drag.apply(d)
                bend.apply(d)
                mujoco.mj_step(m, d)
                self._j += 1
                # positions after a step are those before it (MuJoCo's forward pass)
                self._sample(t_step, d.flexvert_xpos[adr : adr + nv], d)
            t_new = self._t0 + self._j * dt
            touching = rope.self_contact(m, d)
            if touching and not self._touching:
                self.contacts.append(t_new)
            self._touching = touching
            line = d.qpos[rope.vert_qpos] + rope.body_pos0
            speed = float(np.linalg.norm(d.qvel[self.end_dof]))
            snap = self._snapshot(t_new)
            with self._lock:
                self._snap = snap
                self.history.append((t_new, speed, self._touching, line))
            self.stats["sim_s"] += self.chunk * dt
            self.stats["busy_s"] += time.perf_counter() - busy

    def _sample(self, t: float, verts: np.ndarray, d) -> None:
        """Capture frames at ``epoch_s + k / 200 Hz`` between the last state and this one
        (linear interpolation over 1 ms)."""
        cur = (t, verts.copy(), d.site_xpos[self.site].copy(), d.site_xmat[self.site].copy())
        prev, self._prev = self._prev, cur
        if prev is None:
            return
        while True:
            w = self.epoch_s + self._k / RATE_HZ
            if w > t:
                return
            a = (w - prev[0]) / (t - prev[0]) if t > prev[0] else 1.0
            v, p, r = ((1 - a) * x + a * y for x, y in zip(prev[1:], cur[1:], strict=True))
            rope = self.rope.markers_from_vertices(v)
            cluster = p[None, :] + CLUSTER @ r.reshape(3, 3).T
            self.frames.append((self._k, w, rope, cluster))
            self._k += 1

    def measured(self, windows: list[tuple[float, float]] | None = None) -> dict[str, Any]:
        """Real-time factor (simulated s per s of computing) and lag of the state behind the
        wall clock [ms]: overall, and within ``windows`` (perf_counter spans) if given."""
        lag = np.asarray(self.stats["lag"], dtype=float).reshape(-1, 2)
        busy = self.stats["busy_s"]

        def summary(x: np.ndarray) -> dict[str, float | None]:
            x = 1e3 * x
            if not x.size:
                return {"mean": None, "p99": None, "max": None}
            return {"mean": round(float(x.mean()), 2),
                    "p99": round(float(np.percentile(x, 99)), 2),
                    "max": round(float(x.max()), 2)}  # fmt: skip

        inside = np.zeros(lag.shape[0], dtype=bool)
        for a, b in windows or []:
            inside |= (lag[:, 0] >= a) & (lag[:, 0] <= b)
        return {
            "sim_s": round(self.stats["sim_s"], 3),
            "realtime_factor": round(self.stats["sim_s"] / busy, 2) if busy else None,
            "lag_ms": summary(lag[:, 1]),
            "lag_in_windows_ms": summary(lag[inside, 1]),
        }


class FakeLabXArm(FakeXArm):
    """The fake controller with :class:`LabScene` as its arm, logging its joint target.

    Every assignment of the controller's target or plan is logged with its time; the scene
    asks :meth:`_ctrl_at` for the target in force at each of its steps.
    """

    def __init__(self, scene: LabScene, **kw):
        self.__dict__["_log_lock"] = threading.Lock()
        self.__dict__["_log_t"] = []
        self.__dict__["_log_v"] = []
        self.__dict__["_tgt"] = scene.q
        self.__dict__["_pln"] = None
        self.stream_start: float | None = None  # first applied target of the servo stream
        super().__init__(arm=scene, q0=scene.q, **kw)
        scene.ctrl_at = self._ctrl_at
        scene.stream_start = lambda: self.stream_start

    def _r12(self, p: bytes, now: float) -> None:
        super()._r12(p, now)
        if self.mode == 1 and p[0] == 0:
            self.stream_start = None

    def _r29(self, p: bytes, now: float) -> None:
        super()._r29(p, now)
        if self.stream_start is None and self.servo and self.servo[-1].applied:
            self.stream_start = now

    def _log(self) -> None:
        with self._log_lock:
            self._log_t.append(time.perf_counter())
            self._log_v.append((self.__dict__["_pln"], self.__dict__["_tgt"]))

    @property
    def _target(self) -> np.ndarray:
        return self.__dict__["_tgt"]

    @_target.setter
    def _target(self, value: np.ndarray) -> None:
        self.__dict__["_tgt"] = np.array(value, dtype=float)
        self._log()

    @property
    def _plan(self):
        return self.__dict__["_pln"]

    @_plan.setter
    def _plan(self, value) -> None:
        self.__dict__["_pln"] = value
        self._log()

    def _ctrl_at(self, t: float) -> np.ndarray:
        with self._log_lock:
            i = bisect.bisect_right(self._log_t, t) - 1
            plan, target = self._log_v[i] if i >= 0 else self._log_v[0]
        if plan is None:
            return target
        t0, qa, qb, dur = plan
        s = min(max((t - t0) / dur, 0.0), 1.0)
        return qa + (qb - qa) * s**3 * (10 - 15 * s + 6 * s * s)


class FakeLab:
    """The scene, the controller on loopback and the capture software, together.

    Args:
        captures: Directory of the C3D files.
        rope: The rope's id.
        seed: Seed of the lab's variation.
        epoch_offset_s: The capture clock's origin, before the lab starts [s] (an arbitrary,
            non-integer number of milliseconds: the clocks are not synchronised).
    """

    def __init__(
        self,
        captures: str | Path,
        rope: int = 1,
        seed: int = 0,
        epoch_offset_s: float = 123.4567,
        start: str = "sim",
    ):
        if start not in ("sim", "relaxed"):
            raise ValueError(f"start must be 'sim' or 'relaxed', got {start!r}")
        self.start_kind = start
        self.epoch_s = time.perf_counter() - epoch_offset_s
        self.scene = LabScene(rope=rope, seed=seed, epoch_s=self.epoch_s)
        self.xarm = FakeLabXArm(self.scene)
        self.capture = FakeCapture(self.scene, self.xarm, Path(captures), seed=seed)
        self.outcomes: list[dict[str, Any]] = []

    def start(self) -> FakeLab:
        """Start the physics, the controller's ports and the capture."""
        self.scene.start()
        self.xarm.start()
        self.capture.start()
        return self

    def stop(self) -> None:
        """Stop everything."""
        self.capture.stop()
        self.xarm.stop()
        self.scene.stop()

    def info(self) -> dict[str, Any]:
        """Where the controller listens, the capture clock's origin, the base pose."""
        return {
            "host": self.xarm.host,
            "ports": dict(self.xarm.ports),
            "sdk_port_overrides": self.xarm.sdk_port_overrides(),
            "epoch_s": self.epoch_s,
            "base_pose": self.scene.lab.base_pose.tolist(),
            "robot_prefix": ROBOT_PREFIX,
            "fingertip_site": FINGERTIP_SITE,
        }

    def steady(self, step_back_s: float = 0.6) -> None:
        """The operator steadies the rope before a throw. ``start = "sim"``: it hangs as in
        the simulated lab when the throw begins (:meth:`LabScene.steady_at_throw`; the
        capture sees the rope from then on). ``"relaxed"``: it is re-hung and relaxed to rest
        now (:meth:`LabScene.steady`), and the operator steps back (out of the capture's
        pre-trigger buffer) for ``step_back_s`` [s]."""
        if self.start_kind == "sim":
            self.scene.steady_at_throw()
            return
        self.scene.steady(relax_s=2.0)
        time.sleep(step_back_s)

    def settle_after(self, params: SettleParams | None = None, timeout: float = 60.0) -> dict:
        """After a throw: wait until the rope rests by the simulated lab's rule, from one
        servo period after the last servo target, and judge its knot (module docstring)."""
        params = params or self.scene.lab.params.settle
        applied = [e.t for e in self.xarm.servo if e.applied]
        t_end = (applied[-1] if applied else time.perf_counter()) + SERVO_S
        mon = SettleMonitor(params, t_end)
        last, end = t_end - 1e-9, time.perf_counter() + timeout
        while time.perf_counter() < end:
            with self.scene._lock:
                new = [h for h in self.scene.history if h[0] > last]
            for t, speed, contact, line in new:
                last = t
                if mon.observe(t, speed, lambda line=line: tube_knot(line), contact):
                    out = mon.outcome
                    klass = judge_centreline(line).klass
                    res = {"verdict": klass, **out.as_metadata(params), "t_end": t_end}
                    self.outcomes.append(res)
                    return res
            time.sleep(0.05)
        raise TimeoutError("the rope's settle did not end")

    def stream_windows(self, after_s: float = 0.5) -> list[tuple[float, float]]:
        """perf_counter spans of every servo stream: first to last applied target, plus
        ``after_s`` [s] (what the measured joints and the capture's throw depend on)."""
        t = [e.t for e in self.xarm.servo if e.applied]
        out: list[list[float]] = []
        for x in t:
            if out and x - out[-1][1] < 0.5:
                out[-1][1] = x
            else:
                out.append([x, x])
        return [(a, b + after_s) for a, b in out]

    def last_verdict(self) -> str | None:
        """The verdict class the last settle ended with (``knot``, ``wrapped_at_grip``, ...)."""
        return self.outcomes[-1]["verdict"] if self.outcomes else None

    def rope_truth(self, t_start: float, t_stop: float) -> tuple[np.ndarray, np.ndarray]:
        """The rope markers the capture sampled between two perf_counter times, before its
        noise, dropouts and shuffling: wall times (n,) [s] and markers (n, 11, 3) [m], world
        frame, marker 0 at the grip."""
        frames = [f for f in list(self.scene.frames) if t_start <= f[1] <= t_stop]
        t = np.array([f[1] for f in frames], dtype=float)
        return t, np.stack([f[2] for f in frames]) if frames else np.zeros((0, 11, 3))

    def report(self) -> dict[str, Any]:
        """What the test checks: captures written, outcomes, real time measurements."""
        return {
            "captures": list(self.capture.captures),
            "outcomes": [
                {k: o[k] for k in ("verdict", "settle_s", "settled")} for o in self.outcomes
            ],
            "physics": self.scene.measured(self.stream_windows()),
            "servo_targets": len(self.xarm.servo),
            "unknown_registers": sorted(set(self.xarm.unknown)),
        }


def _serve(conn, kwargs: dict[str, Any]) -> None:
    # Hand the GIL over often: the physics thread takes it between MuJoCo steps, and must
    # not wait out the default 5 ms while the capture writes a file or a knot is classified.
    sys.setswitchinterval(1e-4)
    lab = FakeLab(**kwargs)
    gc.collect()
    gc.freeze()  # what exists now is never collected: no long collection stalls the physics
    lab.start()
    conn.send(("ok", lab.info()))
    while True:
        try:
            name, kw = conn.recv()
        except EOFError:
            break
        try:
            conn.send(("ok", getattr(lab, name)(**kw)))
        except Exception as e:  # reported to the caller
            conn.send(("error", f"{type(e).__name__}: {e}"))
        if name == "stop":
            break
    with contextlib.suppress(Exception):
        lab.stop()


class FakeLabProcess:
    """A :class:`FakeLab` in a child process; ``proxy.call(name, **kw)`` runs its method.

    ``info`` holds :meth:`FakeLab.info`. Use as a context manager.
    """

    def __init__(self, captures: str | Path, **kwargs):
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._lock = threading.Lock()
        kw = {"captures": str(captures), **kwargs}
        self.proc = ctx.Process(target=_serve, args=(child, kw), name="fake-lab", daemon=True)
        self.info: dict[str, Any] = {}

    def start(self, timeout: float = 60.0) -> FakeLabProcess:
        """Start the child and wait until its controller listens."""
        self.proc.start()
        if not self._conn.poll(timeout):
            self.proc.kill()
            raise TimeoutError("the fake lab did not start")
        self.info = self._result(self._conn.recv())
        return self

    @staticmethod
    def _result(reply: tuple[str, Any]) -> Any:
        status, value = reply
        if status != "ok":
            raise RuntimeError(f"fake lab: {value}")
        return value

    def call(self, name: str, timeout: float = 120.0, **kw) -> Any:
        """Run ``FakeLab.name(**kw)`` in the child and return its result."""
        with self._lock:
            self._conn.send((name, kw))
            if not self._conn.poll(timeout):
                raise TimeoutError(f"fake lab: no reply to {name} within {timeout} s")
            return self._result(self._conn.recv())

    def stop(self) -> None:
        """Stop the fake lab and its process."""
        if self.proc.is_alive():
            with contextlib.suppress(Exception):
                self.call("stop", timeout=10.0)
            self.proc.join(timeout=10.0)
        if self.proc.is_alive():
            self.proc.kill()

    def __enter__(self) -> FakeLabProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

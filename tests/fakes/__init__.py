"""Test doubles of the real lab's devices (loopback only), and what the application injects.

``fake_xarm.FakeXArm`` is the controller, ``fake_lab.FakeLab`` the whole simulated lab behind
it (arm, rope, motion-capture software); here: the fingertip kinematics of the simulated lab's
arm (:class:`SimFingertip`), a stand-in motion capture (:class:`StandInMocap`) and a lab file
pointing at a fake (:func:`lab_doc`).
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from flyknot_hw.mocap import BodyTrack, RawStream, apply_pose, hanging_markers
from flyknot_sim.robot import FINGERTIP_SITE, load_robot_model

if TYPE_CHECKING:
    from fakes.fake_xarm import FakeXArm


class SimFingertip:
    """Fingertip kinematics of the simulated lab's xArm 7 (base frame), as the application
    injects them: q (k, 7) [rad] -> positions (k, 3) [m], quaternions (k, 4)."""

    def __init__(self) -> None:
        self.model = load_robot_model()
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site(FINGERTIP_SITE).id

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        pos, quat = np.empty((len(q), 3)), np.empty((len(q), 4))
        for i, row in enumerate(q):
            self.data.qpos[:7] = row
            mujoco.mj_kinematics(self.model, self.data)
            pos[i] = self.data.site_xpos[self.site]
            mujoco.mju_mat2Quat(quat[i], self.data.site_xmat[self.site])
        return pos, quat


class StandInMocap:
    """A stand-in motion capture (a :class:`flyknot_hw.mocap.stream.MocapSource`), stamped on
    ``time.perf_counter`` between :meth:`start` and :meth:`stop`.

    With a ``fake`` controller: 200 Hz frames of a rope hanging straight down from the fake
    arm's fingertip (read from the fake while recording; ``base_pose`` maps it to the mocap
    frame) and the fingertip itself as the body ``fingertip``. Without: a rope hanging still
    from a fixed point (nothing a trial's clock can be aligned on).
    """

    host_clock = True

    def __init__(self, fake: FakeXArm | None = None, base_pose=(0.1, -0.2, 0.8, 1, 0, 0, 0)):
        self.fake, self.base_pose = fake, np.asarray(base_pose, dtype=float)
        self.started = self.stopped = 0
        self._t0 = 0.0
        self._rows: list[tuple[float, np.ndarray]] = []
        self._thread: threading.Thread | None = None
        self._run = threading.Event()

    @property
    def recording(self) -> bool:
        return self._thread is not None or self._t0 > 0

    def start(self) -> None:
        self.started += 1
        self._t0 = time.perf_counter()
        self._rows = []
        if self.fake is not None:
            self._run.set()
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()

    def _sample(self) -> None:
        nxt = time.perf_counter()
        while self._run.is_set():
            self._rows.append((time.perf_counter(), self.fake.q))
            nxt += 1 / 200.0
            time.sleep(max(0.0, nxt - time.perf_counter()))

    def stop(self) -> RawStream:
        self.stopped += 1
        self._run.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        t0, self._t0 = self._t0, 0.0
        if self.fake is None:
            t = np.arange(t0, time.perf_counter(), 1 / 200.0)
            pts = np.tile(hanging_markers(np.array([0.0, 0.0, 2.0]))[None], (t.size, 1, 1))
            return RawStream(t, pts, source="stand-in")
        t = np.array([r[0] for r in self._rows])
        tip = apply_pose(self.base_pose, SimFingertip()(np.array([r[1] for r in self._rows]))[0])
        pts = tip[:, None, :] + hanging_markers(np.zeros(3))[None]
        body = BodyTrack.positions_only(tip)
        return RawStream(t, pts, {"fingertip": body}, source="stand-in")


def fake_factory(monkeypatch, cls=None):
    """Body of a ``make_fake`` fixture: yields ``make(**kw)``, which starts a ``cls`` (default
    :class:`~fakes.fake_xarm.FakeXArm`) on its own loopback alias 127.x.y.z and patches the
    SDK's command port only when the fake could not bind 502; stops every fake afterwards."""
    from xarm.core.config.x_config import XCONF

    from fakes.fake_xarm import FakeXArm

    cls = FakeXArm if cls is None else cls
    fakes = []

    def make(**kw):
        fk = cls(**kw).start()
        fakes.append(fk)
        assert fk.host.startswith("127."), fk.host
        for name, port in fk.sdk_port_overrides().items():
            monkeypatch.setattr(XCONF.SocketConf, name, port)
        return fk

    yield make
    for fk in fakes:
        fk.stop()


def lab_doc(fake: FakeXArm, **sections: dict) -> dict:
    """A lab-file mapping pointing at ``fake``; ``sections`` update its tables."""
    doc = {
        "robot": {
            "address": fake.host,
            "port": fake.ports[502],
            "report_port": fake.ports[30000],
            "start_speed": 1.0,
            "start_acc": 10.0,
            # The fakes share a loaded 2-core box with the rest of the suite: a tick sent up
            # to 0.1 s late is recorded, not fatal (the abort has its own test).
            "max_late_s": 0.1,
        },
        "mocap": {"kind": "file", "system": "c3d", "file": "captures/trial_*.c3d"},
        "rope": {"id": 1},
        "base": {"pose": [0.1, -0.2, 0.8, 1.0, 0.0, 0.0, 0.0]},
        # tip_speed_max: our fake controller does not model C60 (servo-mode TCP speed), so the
        # learned throws (~2.6 m/s at the fingertip) may be streamed to it.
        "safety": {
            "margin": 0.05,
            "workspace": {"min": [-1, -1, -0.5], "max": [1, 1, 1.5]},
            "tip_speed_max": 4.0,
        },
        "settle": {"mode": "seconds", "before_s": 0.02, "after_s": 0.1},
    }
    for name, table in sections.items():
        doc[name] = {**doc.get(name, {}), **table}
    return doc

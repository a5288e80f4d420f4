"""Test doubles of the real lab's devices (loopback only), and what the application injects.

``fake_xarm.FakeXArm`` is the controller; here: the fingertip kinematics of the simulated lab's
arm (:class:`SimFingertip`), a trivial motion capture (:class:`StandInMocap`) and a lab file
pointing at a fake (:func:`lab_doc`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import mujoco
import numpy as np

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
    """A trivial motion capture: 200 Hz frames of a rope hanging 1 m below a fixed point,
    stamped on ``time.perf_counter`` between :meth:`start` and :meth:`stop`."""

    def __init__(self) -> None:
        self.started = self.stopped = 0
        self._t0 = 0.0

    def start(self) -> None:
        self.started += 1
        self._t0 = time.perf_counter()

    def stop(self) -> tuple[np.ndarray, np.ndarray]:
        self.stopped += 1
        t = np.arange(self._t0, time.perf_counter(), 1 / 200.0)
        markers = np.zeros((t.size, 11, 3))
        markers[:, :, 2] = 2.0 - 0.1 * np.arange(1, 12)
        return t, markers


def lab_doc(fake: FakeXArm, **sections: dict) -> dict:
    """A lab-file mapping pointing at ``fake``; ``sections`` update its tables."""
    doc = {
        "robot": {
            "address": fake.host,
            "port": fake.ports[502],
            "report_port": fake.ports[30000],
            "start_speed": 1.0,
            "start_acc": 10.0,
        },
        "mocap": {"kind": "file", "system": "c3d", "file": "captures/trial_*.c3d"},
        "rope": {"id": 1},
        "base": {"pose": [0.1, -0.2, 0.8, 1.0, 0.0, 0.0, 0.0]},
        "safety": {"margin": 0.05, "workspace": {"min": [-1, -1, -0.5], "max": [1, 1, 1.5]}},
        "settle": {"mode": "seconds", "before_s": 0.02, "after_s": 0.1},
    }
    for name, table in sections.items():
        doc[name] = {**doc.get(name, {}), **table}
    return doc

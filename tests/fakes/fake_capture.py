"""The fake lab's motion-capture software: one C3D file per servo-mode session.

See ``fakes.fake_lab`` (module docstring) for what it records and how the files are named.
It reads the frames a ``fakes.fake_lab.LabScene`` samples (``frames``: (k, wall time, rope
markers (11, 3), fingertip cluster (3, 3)); ``contacts``, ``steadied_at``) and watches a
``fakes.fake_xarm.FakeXArm``'s mode and state.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from flyknot_hw.mocap import RawStream, write_c3d

RATE_HZ = 200.0  # [Hz] capture rate


LOSS_DELAY_S = 0.02
"""Every rope marker is lost this long after the rope first touches itself [s]."""


class FakeCapture:
    """The motion-capture software (module docstring): one C3D file per servo-mode session.

    Args:
        scene: Where the frames come from.
        xarm: The controller whose servo mode triggers a capture.
        directory: Where the files go.
        seed: Seed of the noise, dropouts and shuffles.
    """

    def __init__(self, scene, xarm, directory: Path, seed: int = 0):
        self.scene, self.xarm, self.directory = scene, xarm, Path(directory)
        self.rng = np.random.default_rng([seed, 777])
        self.pre_s, self.post_s, self.loss_delay_s = 0.5, 0.5, LOSS_DELAY_S
        self.noise_m, self.cluster_noise_m, self.dropout = 1e-3, 3e-4, 0.01
        self.captures: list[dict[str, Any]] = []
        self._run = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> FakeCapture:
        """Watch the controller (100 Hz)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        self._run.set()
        self._thread = threading.Thread(target=self._watch, name="fake-capture", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop watching."""
        self._run.clear()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _watch(self) -> None:
        start: float | None = None
        while self._run.is_set():
            x = self.xarm
            servo = x.mode == 1 and x.state in (1, 2)
            now = time.perf_counter()
            if start is None and servo:
                start = now - self.pre_s
            elif start is not None and not servo:
                self._write(start, now + self.post_s)
                start = None
            time.sleep(0.01)

    def _write(self, t_start: float, t_stop: float) -> None:
        while self.scene._snap["t"] < t_stop + 0.01 and self._run.is_set():
            time.sleep(0.01)
        frames = [f for f in list(self.scene.frames) if t_start <= f[1] <= t_stop]
        if len(frames) < 2:
            return
        k = np.array([f[0] for f in frames])
        t_wall = np.array([f[1] for f in frames])
        rope = np.stack([f[2] for f in frames]) + self.rng.normal(0, self.noise_m, (len(k), 11, 3))
        cluster = np.stack([f[3] for f in frames])
        cluster = cluster + self.rng.normal(0, self.cluster_noise_m, cluster.shape)
        lost = self.rng.random((len(k), 11)) < self.dropout
        for _ in range(4):  # gaps of a marker over several frames
            j, f0, n = self.rng.integers(11), self.rng.integers(len(k)), self.rng.integers(3, 12)
            lost[f0 : f0 + n, j] = True
        hung = [h for h in self.scene.steadied_at if t_start <= h <= t_stop]
        if hung:  # the operator's hands hid the rope until they let go
            lost[t_wall < hung[-1]] = True
        touch = [c for c in self.scene.contacts if t_start <= c <= t_stop]
        if touch:
            lost[t_wall >= touch[0] + self.loss_delay_s] = True
        rope[lost] = np.nan
        for f in range(len(k)):  # the capture's own labels mean nothing: shuffle them
            rope[f] = rope[f][self.rng.permutation(11)]
        stray = np.full((len(k), 1, 3), np.nan)
        hit = self.rng.random(len(k)) < 0.02
        stray[hit, 0] = self.rng.uniform([-1.5, -1.5, 0.0], [1.5, 1.5, 0.3], (int(hit.sum()), 3))
        points = np.concatenate([rope, stray, cluster], axis=1)
        labels = [f"p{i}" for i in range(12)] + ["fingertip1", "fingertip2", "fingertip3"]
        wall = time.time() - (time.perf_counter() - t_start)
        name = time.strftime("trial_%Y%m%d-%H%M%S", time.localtime(wall)) + ".c3d"
        tmp = self.directory / (name + ".part")
        write_c3d(tmp, RawStream(k / RATE_HZ, points), rate_hz=RATE_HZ, labels=labels)
        os.replace(tmp, self.directory / name)
        self.captures.append(
            {"file": name, "t_start": t_start, "t_stop": t_stop, "frames": len(k),
             "first_contact": touch[0] if touch else None, "let_go": hung[-1] if hung else None,
             "lost_fraction": float(lost.mean())}
        )  # fmt: skip

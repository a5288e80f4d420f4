"""Fakes for the driven calibration: a live motion-capture system that sees the fake arm's
fingertip in a known (mocap) frame, and a controller that faults during a joint move.

:class:`FakeMocapSystem` stands in for what ``motioncapture.connect(kind, config)`` returns
(``waitForNextFrame()``, ``rigidBodies``), so the real
:class:`~flyknot_hw.mocap.live.MotioncaptureSource` reads it: 200 Hz frames of one rigid body
``fingertip`` at the fake arm's fingertip (the simulated lab's MuJoCo site), mapped by
``base_pose`` into the mocap frame, with Gaussian noise per frame and random dropouts (the
body missing from a frame). ``hide(q)`` / ``misread(q, offset)`` make the body vanish or jump
while the arm is near a joint pose. Nothing touches a network.

:class:`MoveFaultXArm` is :class:`~fakes.fake_xarm.FakeXArm` with one more scripted trouble:
an error (or warning) raised a given time into the n-th joint move (register 23), as a
collision during a slow move would.
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np

from fakes import SimFingertip
from fakes.fake_xarm import FakeXArm
from flyknot_hw.mocap import apply_pose

RATE_HZ = 200.0


class _Body:
    """A rigid body as the ``motioncapture`` binding gives it."""

    def __init__(self, position: np.ndarray) -> None:
        self.position = np.asarray(position, dtype=np.float32)
        self.rotation = SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0)


class FakeMocapSystem:
    """A live system seeing the fake arm's fingertip (module docstring).

    Args:
        fake: The controller whose arm is watched.
        base_pose: The robot base in the mocap frame (x, y, z, qw, qx, qy, qz): the truth a
            calibration should recover.
        noise_m: Standard deviation of the per-frame noise on each coordinate [m].
        dropout: Fraction of frames without the body.
        seed: Seed of the noise and dropouts.
    """

    def __init__(self, fake: FakeXArm, base_pose, noise_m=3e-4, dropout=0.05, seed=0):
        self.fake, self.base_pose = fake, np.asarray(base_pose, dtype=float)
        self.noise_m, self.dropout = noise_m, dropout
        self.rng = np.random.default_rng([seed, 13])
        self.fk = SimFingertip()
        self.rigidBodies: dict[str, _Body] = {}
        self.frames = 0
        self.connects: list[tuple[str, dict]] = []
        self._hidden: list[np.ndarray] = []
        self._misread: list[tuple[np.ndarray, np.ndarray]] = []
        self._next = time.perf_counter()
        self._lock = threading.Lock()

    def connect(self, kind: str, config: dict) -> FakeMocapSystem:
        """What ``motioncapture.connect`` would return."""
        self.connects.append((kind, dict(config)))
        return self

    def module(self) -> SimpleNamespace:
        """A stand-in for the ``motioncapture`` module (its ``connect``)."""
        return SimpleNamespace(connect=self.connect, __version__="fake")

    def hide(self, q: np.ndarray) -> None:
        """No fingertip body while the arm is within 0.02 rad of ``q``."""
        self._hidden.append(np.asarray(q, dtype=float))

    def misread(self, q: np.ndarray, offset) -> None:
        """The body shifted by ``offset`` [m] (mocap frame) while the arm is near ``q``."""
        self._misread.append((np.asarray(q, dtype=float), np.asarray(offset, dtype=float)))

    def waitForNextFrame(self) -> None:
        """Sleep until the next 200 Hz frame, then take it."""
        self._next = max(self._next + 1.0 / RATE_HZ, time.perf_counter() - 0.05)
        time.sleep(max(0.0, self._next - time.perf_counter()))
        q = self.fake.q
        with self._lock:
            self.frames += 1
            near = [np.max(np.abs(q - h)) < 0.02 for h in self._hidden]
            if any(near) or self.rng.random() < self.dropout:
                self.rigidBodies = {}
                return
            tip = apply_pose(self.base_pose, self.fk(q[None])[0][0])
            for qm, off in self._misread:
                if np.max(np.abs(q - qm)) < 0.02:
                    tip = tip + off
            tip = tip + self.rng.normal(0.0, self.noise_m, 3)
            self.rigidBodies = {"fingertip": _Body(tip), "wand": _Body(np.zeros(3))}


class MoveFaultXArm(FakeXArm):
    """A fake controller that can fault during a joint move (module docstring)."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.moves = 0
        self._move_fault: tuple[int, float, str, int] | None = None
        self._fault_at: tuple[float, str, int] | None = None

    def inject_during_move(self, code: int, move: int, after_s: float, *, warn=False) -> None:
        """Raise controller error (or warning) ``code`` ``after_s`` into the ``move``-th joint
        move (1-based)."""
        self._move_fault = (move, after_s, "warn" if warn else "error", code)

    def _r23(self, p: bytes, now: float) -> None:
        super()._r23(p, now)
        self.moves += 1
        if self._move_fault is not None and self._move_fault[0] == self.moves:
            _, after_s, kind, code = self._move_fault
            self._fault_at = (now + after_s, kind, code)

    def _advance(self) -> None:
        super()._advance()
        if self._fault_at is not None and time.perf_counter() >= self._fault_at[0]:
            _, kind, code = self._fault_at
            self._fault_at = None
            if kind == "warn":
                self.warn_code = code
                self.events.append((time.perf_counter(), "warn", code))
            else:
                self._fault(code)

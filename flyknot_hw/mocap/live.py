"""Live motion capture through the ``motioncapture`` package (libmotioncapture's Python binding).

``pip install 'flyknot[mocap]'`` installs it; it is imported only when a live source starts.

What ``motioncapture`` 1.1 (the PyPI wheel) offers, as inspected:

* ``motioncapture.connect(kind, config)`` with ``kind`` one of ``"vicon"``, ``"optitrack"``,
  ``"qualisys"``, ``"vrpn"`` (the backends compiled into the wheel) and ``"mock"``; other
  names raise "Unknown motion capture type!". ``config`` is a dict of strings: e.g.
  ``{"hostname": "192.168.0.10"}`` (vicon, optitrack, qualisys, vrpn), ``"port"``
  (qualisys), ``"interface_ip"`` / ``"port_command"`` (optitrack).
* The ``"mock"`` backend needs no network: ``{"rigid_bodies": "name(x,y,z,qw,qx,qy,qz);...",
  "pointcloud": "x,y,z;x,y,z", "frequency": "100"}`` gives fixed bodies at ``frequency`` Hz
  (``waitForNextFrame`` sleeps 1 / frequency). The tests use it.
* The connected object has ``waitForNextFrame()`` (blocks until the next frame, without the
  GIL) and ``rigidBodies`` (dict name -> ``RigidBody`` with ``position`` (3,) float32 [m],
  ``rotation`` quaternion ``w, x, y, z``). In 1.1 it has **no** ``pointCloud`` (the C++
  library has one, the binding does not expose it) and no frame time stamps or latency.

Consequences here:

* Unlabelled points are read from a ``pointCloud`` attribute (an (P, 3) array [m]) when the
  installed binding has one (later builds do); with 1.1 a source that needs the rope's points
  (``require_points=True``, the default) refuses to start, with an explanation. Record the
  rope through the capture software's files instead (:mod:`flyknot_hw.mocap.files`), or use
  a build that exposes the point cloud. Rigid bodies (the hand's marker cluster) work.
* Frames are stamped with the host's clock (``time.perf_counter``) when
  ``waitForNextFrame`` returns: network latency and jitter are in the stamps. The constant
  part is absorbed by the clock offset (:mod:`flyknot_hw.mocap.clock`); the jitter (typically
  well under a millisecond on a wired network) is not corrected.
* A body missing from a frame's ``rigidBodies`` (or with non-finite values) is NaN there.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from flyknot.errors import ConfigError, HardwareError, check_choice, check_positive
from flyknot_hw.mocap.stream import BodyTrack, RawStream

__all__ = ["LIVE_KINDS", "MotioncaptureSource", "import_motioncapture"]

LIVE_KINDS = ("vicon", "optitrack", "qualisys", "vrpn", "mock")
"""Systems the ``motioncapture`` 1.1 wheel connects to (``mock``: no hardware, for tests)."""


def import_motioncapture() -> Any:
    """The ``motioncapture`` module, or a :class:`HardwareError` naming the extra to install."""
    try:
        import motioncapture  # optional dependency (the mocap extra), imported when used
    except ImportError as e:
        raise HardwareError(
            "live motion capture needs the 'motioncapture' package (>= 1.1): "
            "pip install 'flyknot[mocap]'"
        ) from e
    return motioncapture


class MotioncaptureSource:
    """A :class:`~flyknot_hw.mocap.stream.MocapSource` reading a live system.

    A background thread calls ``waitForNextFrame`` and copies each frame (bodies, and points
    when the binding has them) from :meth:`start` to :meth:`stop`.

    Args:
        kind: One of :data:`LIVE_KINDS`.
        config: The backend's string settings (module docstring), e.g. ``{"hostname": ...}``.
        require_points: Refuse to start when the binding cannot deliver unlabelled points.
        frame_timeout_s: :meth:`stop` fails if no frame arrived for this long [s].
        connect_timeout_s: :meth:`start` fails if the system does not answer in this time [s].
        clock: Time stamp of a frame [s] (host clock), injectable for tests.
        connect: Stand-in for ``motioncapture.connect(kind, config)`` (tests).
    """

    def __init__(
        self,
        kind: str,
        config: Mapping[str, str] | None = None,
        *,
        require_points: bool = True,
        frame_timeout_s: float = 1.0,
        connect_timeout_s: float = 5.0,
        clock: Callable[[], float] = time.perf_counter,
        connect: Callable[[str, dict[str, str]], Any] | None = None,
    ):
        check_choice("mocap kind", kind, LIVE_KINDS)
        cfg = dict(config or {})
        bad = [k for k, v in cfg.items() if not isinstance(k, str) or not isinstance(v, str)]
        if bad:
            raise ConfigError("mocap config", f"keys and values must be text; not: {bad}")
        check_positive("frame_timeout_s", frame_timeout_s)
        check_positive("connect_timeout_s", connect_timeout_s)
        self.kind = kind
        self.config = cfg
        self.require_points = bool(require_points)
        self.frame_timeout_s = frame_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self._clock = clock
        self._connect = connect
        self._mc: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._frames: list[tuple[float, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]] = []
        self._error: BaseException | None = None

    @property
    def source(self) -> str:
        """``kind@hostname`` (for messages and the stream's ``source``)."""
        return f"{self.kind}@{self.config.get('hostname', 'localhost')}"

    def _open(self) -> Any:
        """Connect, in a helper thread: some backends block without a server (optitrack
        waits for the NatNet version reply), and a blocked C++ call cannot be interrupted."""
        if self._mc is not None:
            return self._mc
        connect = self._connect or import_motioncapture().connect
        box: dict[str, Any] = {}

        def run() -> None:
            try:
                box["mc"] = connect(self.kind, self.config)
            except Exception as e:  # the binding raises RuntimeError with the SDK's text
                box["error"] = e

        helper = threading.Thread(target=run, name="mocap-connect", daemon=True)
        helper.start()
        helper.join(timeout=self.connect_timeout_s)
        if helper.is_alive():
            raise HardwareError(
                f"cannot connect to {self.source}: no answer within {self.connect_timeout_s} s"
            )
        if "error" in box:
            raise HardwareError(f"cannot connect to {self.source}: {box['error']}") from box[
                "error"
            ]
        self._mc = box["mc"]
        return self._mc

    def start(self) -> None:
        """Connect (first time) and begin recording frames in a background thread."""
        if self._thread is not None:
            raise HardwareError(f"{self.source}: start() while already recording")
        self.ready()
        self._frames = []
        self._error = None
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mocap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        mc = self._mc
        try:
            while not self._stop.is_set():
                mc.waitForNextFrame()
                stamp = self._clock()
                bodies = {}
                for name, rb in dict(mc.rigidBodies).items():
                    pos = np.asarray(rb.position, dtype=float).reshape(3)
                    rot = rb.rotation
                    quat = np.array([rot.w, rot.x, rot.y, rot.z], dtype=float)
                    bodies[str(name)] = (pos, quat)
                cloud = getattr(mc, "pointCloud", None)
                pts = np.zeros((0, 3)) if cloud is None else np.asarray(cloud, dtype=float)
                with self._lock:
                    self._frames.append((stamp, pts.reshape(-1, 3), bodies))
        except BaseException as e:  # reported by stop()
            self._error = e

    @property
    def host_clock(self) -> bool:
        """Whether frames are stamped with this host's ``time.perf_counter`` (the default)."""
        return self._clock is time.perf_counter

    def ready(self) -> None:
        """Connect (first time) and check that the rope's points can be read, before a trial
        moves the arm (raises :class:`HardwareError` otherwise)."""
        mc = self._open()
        if self.require_points and not hasattr(mc, "pointCloud"):
            version = getattr(sys.modules.get("motioncapture"), "__version__", "unknown")
            raise HardwareError(
                f"{self.source}: this motioncapture build (version {version}) exposes no "
                "pointCloud, so the rope's unlabelled markers cannot be read live; record them "
                "with the capture software (RecordedFileSource), or pass require_points=False "
                "to record rigid bodies only"
            )

    @property
    def recording(self) -> bool:
        """Whether :meth:`start` has begun a recording that :meth:`stop` has not ended."""
        return self._thread is not None

    def recent(self, seconds: float) -> RawStream | None:
        """The frames of the last ``seconds`` [s] of the running recording (None: no frame
        yet), without stopping it: what a settle check watches.

        Raises:
            HardwareError: Not recording, or the reader thread failed.
        """
        check_positive("seconds", seconds)
        if self._thread is None:
            raise HardwareError(f"{self.source}: recent() needs a running recording (start())")
        if self._error is not None:
            raise HardwareError(f"{self.source}: reading frames failed: {self._error}")
        with self._lock:
            if not self._frames:
                return None
            t_last = self._frames[-1][0]
            k = len(self._frames)
            while k > 0 and self._frames[k - 1][0] >= t_last - seconds:
                k -= 1
            frames = self._frames[k:]
        return frames_to_stream(frames, self.source)

    def stop(self) -> RawStream:
        """Stop recording and return the frames since :meth:`start`."""
        thread = self._thread
        if thread is None:
            raise HardwareError(f"{self.source}: stop() called before start()")
        self._stop.set()
        thread.join(timeout=self.frame_timeout_s)
        self._thread = None
        if thread.is_alive():
            raise HardwareError(
                f"{self.source}: no frame for {self.frame_timeout_s} s; the stream stalled"
            )
        if self._error is not None:
            raise HardwareError(f"{self.source}: reading frames failed: {self._error}")
        with self._lock:
            frames = list(self._frames)
        if not frames:
            raise HardwareError(f"{self.source}: no frames were received")
        return frames_to_stream(frames, self.source)


def frames_to_stream(
    frames: list[tuple[float, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]],
    source: str = "",
) -> RawStream:
    """Per-frame (time [s], points (P_f, 3) [m], {body: (position (3,), quat (4,))}) -> stream.

    Frames with a time not after the previous one are dropped (a stalled clock).
    """
    keep, last = [], -np.inf
    for fr in frames:
        if fr[0] > last:
            keep.append(fr)
            last = fr[0]
    m = len(keep)
    width = max((fr[1].shape[0] for fr in keep), default=0)
    points = np.full((m, width, 3), np.nan)
    names = sorted({n for fr in keep for n in fr[2]})
    pos = {n: np.full((m, 3), np.nan) for n in names}
    quat = {n: np.full((m, 4), np.nan) for n in names}
    for k, (_, pts, bodies) in enumerate(keep):
        points[k, : pts.shape[0]] = pts
        for n, (p, q) in bodies.items():
            if np.all(np.isfinite(p)) and np.all(np.isfinite(q)):
                pos[n][k], quat[n][k] = p, q
    times = np.array([fr[0] for fr in keep], dtype=float)
    return RawStream(times, points, {n: BodyTrack(pos[n], quat[n]) for n in names}, source)

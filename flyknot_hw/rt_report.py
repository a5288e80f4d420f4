"""The controller's real-time report (TCP 30000): timestamped joints at 200 Hz.

Firmware >= 2.1 streams, on its own TCP port, frames of a big-endian u32 size followed by
a u64 timestamp [us] (its epoch is the controller's, unrelated to ours), state and mode,
target and actual joint positions, velocities, currents and estimated torques (UFACTORY
ufactory_docs ``firmware/report/ReadMe_en.md``). The SDK does not open this port; we do, and
parse each frame with the SDK's own ``xarm.x3.report.ReportDataStructure.create(30000)``.

Clock alignment: each frame is stamped on arrival with ``time.perf_counter``; the controller
timestamps are mapped onto that clock with the smallest observed arrival delay
(``offset = min(t_arrival - t_controller)``), so network jitter does not enter the joint
times.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np

from flyknot.errors import HardwareError

__all__ = ["RealtimeFrames", "RealtimeReport"]


@dataclass(frozen=True)
class RealtimeFrames:
    """Frames received, in arrival order.

    Attributes:
        t: Controller timestamps mapped onto ``time.perf_counter`` (k,) [s].
        t_arrival: Arrival times (k,) [s].
        state: Controller state (k,) (1 moving, 2 idle, 3 paused, 4 stopped).
        mode: Controller mode (k,) (0 position, 1 servo).
        q_target: Target joints (k, 7) [rad].
        q: Actual joints (k, 7) [rad].
        qd: Actual joint velocities (k, 7) [rad/s].
        tau: Estimated joint torques (k, 7) [N m].
    """

    t: np.ndarray
    t_arrival: np.ndarray
    state: np.ndarray
    mode: np.ndarray
    q_target: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray

    @property
    def k(self) -> int:
        """Number of frames."""
        return int(self.t.shape[0])


class RealtimeReport:
    """A reader thread on the controller's port 30000.

    Args:
        address: Controller address.
        port: Report port (30000).
        timeout: Connect and read timeout [s].
    """

    def __init__(self, address: str, port: int, timeout: float = 1.0):
        self.address, self.port, self.timeout = address, port, timeout
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._alive = False
        self._lock = threading.Lock()
        self._rows: list[tuple] = []
        self.error: str | None = None

    def open(self) -> None:
        """Connect and start reading.

        Raises:
            HardwareError: If the port refuses (firmware < 2.1) or does not answer.
        """
        from xarm.x3.report import ReportDataStructure

        try:
            sock = socket.create_connection((self.address, self.port), timeout=self.timeout)
        except OSError as e:
            raise HardwareError(
                f"robot.report_port: cannot connect to {self.address}:{self.port} ({e}); "
                "the real-time report needs firmware >= 2.1"
            ) from e
        sock.settimeout(self.timeout)
        self._sock, self._alive = sock, True
        self._parser = ReportDataStructure.create(30000, is_radian=True)
        self._thread = threading.Thread(target=self._read, name="xarm-rt-report", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop reading and close the socket."""
        self._alive = False
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock = self._thread = None

    def _recv(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self._sock.recv(n - len(buf))  # type: ignore[union-attr]
            if not chunk:
                raise ConnectionError("closed by the controller")
            buf += chunk
        return buf

    def _read(self) -> None:
        p = self._parser
        try:
            while self._alive:
                head = self._recv(4)
                size = int.from_bytes(head, "big")
                if not 16 <= size <= 65536:
                    raise ConnectionError(f"bad frame size {size}")
                frame = head + self._recv(size - 4)
                t_arrival = time.perf_counter()
                p.update(frame)
                row = (
                    t_arrival,
                    p.timestamp * 1e-6,
                    p.state,
                    p.mode,
                    p.target_joint_angle,
                    p.actual_joint_angle,
                    p.actual_joint_velocity,
                    p.estimated_joint_torque,
                )
                with self._lock:
                    self._rows.append(row)
        except (OSError, ConnectionError) as e:
            if self._alive:
                self.error = str(e)
        self._alive = False

    @property
    def alive(self) -> bool:
        """True while frames are being read."""
        return self._alive

    def latest(self) -> tuple[int, int] | None:
        """(state, mode) of the newest frame, or None."""
        with self._lock:
            return None if not self._rows else (self._rows[-1][2], self._rows[-1][3])

    def latest_q(self) -> np.ndarray | None:
        """Measured joints (7,) [rad] of the newest frame, or None."""
        with self._lock:
            return None if not self._rows else np.array(self._rows[-1][5], dtype=float)

    def count(self) -> int:
        """Frames received so far."""
        with self._lock:
            return len(self._rows)

    def wait_for(self, predicate, timeout: float) -> bool:
        """Wait until ``predicate(state, mode)`` holds for a frame newer than the call."""
        n0 = self.count()
        end = time.perf_counter() + timeout
        while time.perf_counter() < end:
            with self._lock:
                rows = self._rows[n0:]
            if any(predicate(r[2], r[3]) for r in rows):
                return True
            time.sleep(0.002)
        return False

    def frames(self, since: float = -np.inf) -> RealtimeFrames:
        """Frames that arrived after ``since`` [s], on the ``perf_counter`` clock."""
        with self._lock:
            rows = list(self._rows)
        arrival = np.array([r[0] for r in rows], dtype=float)
        ctrl = np.array([r[1] for r in rows], dtype=float)
        offset = float(np.min(arrival - ctrl)) if rows else 0.0
        keep = arrival > since

        def col(i: int, width: int | None = None) -> np.ndarray:
            a = np.array([r[i] for r in rows], dtype=float)
            if width is not None:
                a = a.reshape(-1, width)
            return a[keep]

        return RealtimeFrames(
            t=(ctrl + offset)[keep],
            t_arrival=arrival[keep],
            state=col(2).astype(int),
            mode=col(3).astype(int),
            q_target=col(4, 7),
            q=col(5, 7),
            qd=col(6, 7),
            tau=col(7, 7),
        )

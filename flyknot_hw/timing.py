"""A steady 250 Hz clock for streaming, its jitter statistics, and a Ctrl-C latch.

The stream keeps absolute deadlines ``t0 + i / rate`` on :func:`time.perf_counter` (a late
tick does not delay the next ones); it sleeps until shortly before a deadline and spins the
rest, since ``time.sleep`` overshoots by tens of microseconds or more.

Ctrl-C: the xArm SDK reads its replies inside bare ``except:`` clauses, which swallow a
:class:`KeyboardInterrupt` raised while a request is waiting. :class:`SigintLatch` therefore
replaces the SIGINT handler while the arm moves with one that only sets a flag; the stream
checks it every tick, stops the arm and raises :class:`KeyboardInterrupt` itself. A second
Ctrl-C raises at once.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from flyknot.errors import check_nonnegative, check_positive

__all__ = ["DeadlineClock", "SigintLatch", "timing_stats"]


class DeadlineClock:
    """Absolute deadlines ``t0 + i * period`` on ``now()`` (default ``time.perf_counter``).

    Args:
        period: Tick period [s] (0.004 at 250 Hz).
        spin_s: Spin (busy-wait) this long before a deadline instead of sleeping [s].
        now: Clock [s].
        sleep: Sleep function [s].
    """

    def __init__(
        self,
        period: float,
        spin_s: float = 3e-4,
        now: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], Any] = time.sleep,
    ):
        check_positive("period", period)
        check_nonnegative("spin_s", spin_s)
        self.period, self.spin_s, self.now, self.sleep = period, spin_s, now, sleep
        self.t0 = 0.0

    def start(self, lead_s: float = 0.0) -> float:
        """Set tick 0 at ``now() + lead_s`` and return it [s]."""
        self.t0 = self.now() + lead_s
        return self.t0

    def deadline(self, i: int) -> float:
        """Deadline of tick ``i`` [s]."""
        return self.t0 + i * self.period

    def wait(self, i: int) -> float:
        """Wait until tick ``i``'s deadline; return the time it was reached [s] (late ticks
        return at once)."""
        target = self.deadline(i)
        remaining = target - self.now()
        if remaining > self.spin_s:
            self.sleep(remaining - self.spin_s)
        t = self.now()
        while t < target:
            t = self.now()
        return t


def _ms_summary(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"mean_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0}
    return {
        "mean_ms": round(float(np.mean(x)) * 1e3, 4),
        "p99_ms": round(float(np.percentile(x, 99)) * 1e3, 4),
        "max_ms": round(float(np.max(x)) * 1e3, 4),
    }


def timing_stats(
    deadlines: np.ndarray, sent: np.ndarray, replied: np.ndarray, period: float
) -> dict[str, Any]:
    """Jitter of a stream, for a trial record's metadata.

    Args:
        deadlines: Tick deadlines, shape (k,) [s].
        sent: When each target was handed to the SDK, shape (k,) [s].
        replied: When the controller's reply came back, shape (k,) [s].
        period: Nominal period [s].

    Returns:
        ``lateness`` (sent - deadline), ``period_error`` (|diff(sent) - period|) and
        ``round_trip`` (replied - sent), each as mean / p99 / max [ms]; ``late_ticks``
        (sent more than one period after the deadline) and ``ticks``.
    """
    deadlines, sent, replied = (np.asarray(a, dtype=float) for a in (deadlines, sent, replied))
    late = sent - deadlines
    return {
        "ticks": int(sent.size),
        "period_ms": round(period * 1e3, 6),
        "lateness": _ms_summary(late),
        "period_error": _ms_summary(np.abs(np.diff(sent) - period)),
        "round_trip": _ms_summary(replied - sent),
        "late_ticks": int(np.sum(late > period)),
    }


class SigintLatch:
    """Within ``with``: the first Ctrl-C sets :attr:`hit` instead of raising (main thread
    only; elsewhere the latch is inert and Ctrl-C raises as usual)."""

    def __init__(self) -> None:
        self.hit = False
        self._previous: Any = None
        self._installed = False

    def _handler(self, signum: int, frame: Any) -> None:
        if self.hit:
            raise KeyboardInterrupt
        self.hit = True

    def __enter__(self) -> SigintLatch:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
            self._installed = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False

    def check(self) -> None:
        """Raise :class:`KeyboardInterrupt` if Ctrl-C was pressed."""
        if self.hit:
            raise KeyboardInterrupt

"""The motion capture of the real lab, trial by trial, as the xArm cell uses it.

* :func:`open_source`: the lab file's ``[mocap]`` as a
  :class:`~flyknot_hw.mocap.stream.MocapSource`. ``kind = "live"``: a
  :class:`~flyknot_hw.mocap.live.MotioncaptureSource` of ``system`` at ``address``.
  ``kind = "file"``: a :class:`~flyknot_hw.mocap.files.RecordedFileSource` on the
  directory of ``file`` (relative to the lab file), taking the file whose name matches its
  last part (a glob such as ``trial_*.c3d``) that appeared during the trial, matched by time
  (:func:`~flyknot_hw.mocap.files.match_recording`).
* :func:`trial_capture`: one trial's :class:`~flyknot_hw.mocap.stream.RawStream` -> the record's
  ``t_marker`` (robot clock, 0 at the first command sample) and ``markers`` (mocap frame),
  through :func:`~flyknot_hw.mocap.pipeline.trial_markers` (labelling, clock alignment,
  200 Hz resampling), plus plain metadata (``record.metadata["mocap"]``): the alignment's
  offset and residual, what it aligned on, the labelling's counts. A recording the pipeline
  cannot use (no hanging rope at the start, no motion to align on, a fingertip body that
  does not follow the measured joints) gives no markers and the reason under ``"error"``:
  the arm's data are kept, and the learner repeats a trial without markers.
* :class:`MarkerSettle`: the ``settle.mode = "markers"`` check, from a live source.

Conventions:

* **The fingertip body** ``fingertip`` (:data:`TIP_BODY`): the hand's marker cluster, whose
  origin the lab puts at the fingertip: a live system's rigid body of that name, or, in a
  file, the points labelled ``fingertip1``, ``fingertip2``, ... (their mean;
  :func:`~flyknot_hw.mocap.files.cluster_labels`). When the recording has it, the clocks are
  aligned on it (sub-millisecond); without it on rope marker 0, which lags the hand (about
  15 ms off in a fast throw).
* **Gravity** in the mocap frame is minus the robot base's z axis (``base_pose``): the arm
  stands upright.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import MARKER_RATE_HZ, N_MARKERS, ROPE_LENGTH
from flyknot.errors import ConfigError, HardwareError, RecordError, check_choice, check_positive
from flyknot.geometry import quat_to_matrix, readonly
from flyknot.rest import RestCriterion, free_end_at_rest
from flyknot_hw.config import LabConfig
from flyknot_hw.mocap.files import RecordedFileSource
from flyknot_hw.mocap.live import LIVE_KINDS, MotioncaptureSource
from flyknot_hw.mocap.pipeline import trial_markers
from flyknot_hw.mocap.stream import MocapSource, RawStream

__all__ = [
    "TIP_BODY",
    "CapturedMarkers",
    "MarkerSettle",
    "free_end_track",
    "gravity_in_mocap",
    "open_source",
    "trial_capture",
]

TIP_BODY = "fingertip"
"""Name of the fingertip's rigid body (live) or marker cluster (files)."""
MAX_TIP_RESIDUAL_M = 0.01
"""An alignment on the fingertip body further off than this (rms) [m] is not used: a wrong
offset would hand the learner another instant's rope (good ones: under 1 mm)."""

Positions = Callable[[np.ndarray], np.ndarray]
"""Fingertip forward kinematics: q (n, 7) [rad] -> positions (n, 3) [m], robot base frame."""


def gravity_in_mocap(base_pose: np.ndarray) -> np.ndarray:
    """Unit gravity in the mocap frame, (3,): minus the base's z axis (the arm stands upright)."""
    return -quat_to_matrix(np.asarray(base_pose, dtype=float)[3:])[:, 2]


def _live_settings(system: str, address: str) -> dict[str, str]:
    host, _, port = address.partition(":")
    if system == "qualisys":
        return {"hostname": host, **({"port": port} if port else {})}
    if system == "optitrack":
        return {"hostname": host}
    return {"hostname": address}  # vicon and vrpn take "host:port"


def open_source(config: LabConfig, *, wait_s: float = 30.0) -> MocapSource:
    """The motion capture the lab file describes (module docstring).

    Args:
        config: The lab file.
        wait_s: How long a file source waits for the trial's recording [s].

    Raises:
        ConfigError: ``mocap.system`` is not a live system ``motioncapture`` knows, or
            ``mocap.file`` has a pattern in its directory part.
    """
    m = config.mocap
    if m.kind == "live":
        check_choice("mocap.system", m.system, LIVE_KINDS)
        return MotioncaptureSource(m.system, _live_settings(m.system, str(m.address)))
    path = Path(str(m.file)).expanduser()
    if not path.is_absolute() and config.source:
        path = Path(config.source).resolve().parent / path
    if any(c in str(path.parent) for c in "*?["):
        raise ConfigError("mocap.file", f"only the file name may be a pattern, got {str(m.file)!r}")
    return RecordedFileSource(
        path.parent, pattern=path.name, wait_s=wait_s, reader_kwargs={"clusters": (TIP_BODY,)}
    )


@dataclass(frozen=True)
class CapturedMarkers:
    """A trial's markers as the record holds them.

    Attributes:
        t_marker: Times on the robot clock (0 at the first command sample), k / 200 Hz,
            shape (m,) [s]; empty when the recording could not be used.
        markers: Rope markers in the mocap frame, shape (m, 11, 3) [m]; NaN where lost.
        metadata: Plain data for ``record.metadata["mocap"]`` (module docstring).
    """

    t_marker: np.ndarray
    markers: np.ndarray
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t, m = readonly(self.t_marker), readonly(self.markers)
        if t.ndim != 1 or m.shape != (t.shape[0], N_MARKERS, 3):
            raise ConfigError(
                "CapturedMarkers", f"need t (m,) and markers (m, 11, 3), got {t.shape}, {m.shape}"
            )
        object.__setattr__(self, "t_marker", t)
        object.__setattr__(self, "markers", m)
        object.__setattr__(self, "metadata", dict(self.metadata))

    @classmethod
    def empty(cls, metadata: Mapping[str, Any]) -> CapturedMarkers:
        """No markers (the reason in ``metadata``)."""
        return cls(np.zeros(0), np.zeros((0, N_MARKERS, 3)), metadata)


def _has_track(stream: RawStream, name: str) -> bool:
    body = stream.bodies.get(name)
    return body is not None and int(np.all(np.isfinite(body.position), axis=1).sum()) >= 3


def trial_capture(
    stream: RawStream,
    *,
    t_joint: np.ndarray,
    q_meas: np.ndarray,
    fk: Positions,
    base_pose: np.ndarray,
    coarse_offset_s: float | None = None,
    rate_hz: float = MARKER_RATE_HZ,
) -> CapturedMarkers:
    """One trial's recording -> the record's markers (module docstring).

    Args:
        stream: The recording (any clock).
        t_joint: Joint sample times, robot clock, shape (n,) [s].
        q_meas: Measured joints, shape (n, 7) [rad]; rows with NaN are left out.
        fk: Fingertip positions of joints (:data:`Positions`), robot base frame.
        base_pose: Robot base in the mocap frame (x, y, z, qw, qx, qy, qz).
        coarse_offset_s: ``t_robot - t_mocap`` when known (a stream stamped on this host's
            clock), else None (found from the start of the motion).
        rate_hz: Rate of the record's markers [Hz].
    """
    meta: dict[str, Any] = {"source": stream.source, "frames": stream.n_frames}
    q = np.asarray(q_meas, dtype=float)
    ok = np.all(np.isfinite(q), axis=1)
    tip_body = TIP_BODY if _has_track(stream, TIP_BODY) else None
    meta["aligned_on"] = "fingertip body" if tip_body else "rope marker 0"
    try:
        if ok.sum() < 3:
            raise HardwareError("fewer than 3 measured joint samples to align the clocks on")
        out = trial_markers(
            stream,
            t_joint=np.asarray(t_joint, dtype=float)[ok],
            q_meas=q[ok],
            fk=fk,
            base_pose=base_pose,
            tip_body=tip_body,
            gravity_dir=gravity_in_mocap(base_pose),
            rate_hz=rate_hz,
            coarse_offset_s=coarse_offset_s,
        )
    except (HardwareError, RecordError, ConfigError) as e:
        return CapturedMarkers.empty({**meta, "error": str(e)})
    al, lab = out.alignment, out.labels
    if tip_body is not None and al.residual_rms_m > MAX_TIP_RESIDUAL_M:
        return CapturedMarkers.empty(
            {**meta, "offset_s": al.offset_s, "residual_rms_m": al.residual_rms_m,
             "error": f"clock alignment failed: the fingertip body is {al.residual_rms_m:.3f} m "
             "(rms) from the measured joints' fingertip; check the base pose and the cluster"}
        )  # fmt: skip
    meta.update(
        offset_s=al.offset_s,
        coarse_offset_s=al.coarse_offset_s,
        correlation=al.correlation,
        residual_rms_m=al.residual_rms_m,
        residual_max_m=al.residual_max_m,
        residual_samples=al.n_samples,
        labelling={
            "init_frame": lab.init_frame,
            "n_ambiguous": lab.n_ambiguous,
            "n_reacquired": lab.n_reacquired,
            "tracked_fraction": [round(float(x), 4) for x in lab.tracked_fraction],
        },
    )
    return CapturedMarkers(out.t_marker, out.markers, meta)


def _lsq_speed(t: np.ndarray, p: np.ndarray, h: float) -> np.ndarray:
    """Speed [m/s] at each sample from a least-squares line through the samples of the
    preceding ``h`` seconds, shape (m,); NaN where that window holds fewer than 3 samples."""
    ok = np.all(np.isfinite(p), axis=1)
    w = (t[None, :] <= t[:, None]) & (t[None, :] > t[:, None] - h - 1e-9) & ok[None, :]
    n = w.sum(axis=1)
    pz = np.where(ok[:, None], p, 0.0)
    tm = (w * t[None, :]).sum(axis=1) / np.maximum(n, 1)
    pm = (w @ pz) / np.maximum(n, 1)[:, None]
    dt = np.where(w, t[None, :] - tm[:, None], 0.0)
    var = (dt * dt).sum(axis=1)
    cov = np.einsum("kj,kjc->kc", dt, pz[None, :, :] - pm[:, None, :])
    with np.errstate(invalid="ignore", divide="ignore"):
        v = cov / var[:, None]
    return np.where(n >= 3, np.linalg.norm(v, axis=1), np.nan)


def free_end_track(
    stream: RawStream, tip: np.ndarray, gravity_dir: np.ndarray, search_m: float = 0.15
) -> np.ndarray:
    """The rope's free end in each frame: of the points hanging below ``tip`` (deeper than
    0.2 m along gravity, within ``search_m`` of its vertical), the deepest; (m, 3) [m], NaN
    in a frame without one."""
    g = np.asarray(gravity_dir, dtype=float)
    g = g / np.linalg.norm(g)
    rel = stream.points - np.asarray(tip, dtype=float)[None, None, :]
    depth = rel @ g
    side = np.linalg.norm(rel - depth[..., None] * g, axis=2)
    cand = np.isfinite(depth) & (depth > 0.2) & (side <= search_m)
    depth = np.where(cand, depth, -np.inf)
    k = np.argmax(depth, axis=1)
    end = stream.points[np.arange(stream.n_frames), k]
    return np.where(cand.any(axis=1)[:, None], end, np.nan)


class MarkerSettle:
    """``settle.mode = "markers"``: wait until the rope's free end rests, seen live.

    Every ``poll_s`` the last ``criterion.window_s`` (plus ``speed_window_s``) of the live
    stream are looked at: the free end (:func:`free_end_track`) must be found in at least
    90 % of the frames, its speed (least-squares over ``speed_window_s``, which keeps 1 mm
    marker noise near 8 mm/s) must stay below ``criterion.speed_m_s`` and its distance from
    its mean position within the displacement bound (:func:`flyknot.rest.free_end_at_rest`;
    the mean stands in for the hanging position, which a rope leaving its tube at an angle
    does not take straight below the fingertip). A source not recording (before the throw)
    is started for the check and stopped after it.

    Args:
        source: A live source with ``recording``, ``recent(seconds)``, ``start``, ``stop``.
        fingertip: Returns the fingertip now, mocap frame (3,) [m].
        gravity_dir: Gravity in the mocap frame (3,).
        criterion: The core's rest criterion.
        length: Rope length [m] (the displacement bound's default).
        timeout_s: Longest wait [s] (``settle.timeout_s``).
        poll_s: Interval of the checks [s].
        speed_window_s: Window of the least-squares speed [s].
    """

    def __init__(
        self,
        source: Any,
        fingertip: Callable[[], np.ndarray],
        gravity_dir: np.ndarray,
        *,
        criterion: RestCriterion = RestCriterion(),  # noqa: B008 - frozen value
        length: float = ROPE_LENGTH,
        timeout_s: float = 60.0,
        poll_s: float = 0.1,
        speed_window_s: float = 0.1,
    ):
        for attr in ("recording", "recent", "start", "stop"):
            if not hasattr(source, attr):
                raise ConfigError(
                    "settle.mode",
                    '"markers" needs a live motion capture (mocap.kind = "live") that shows '
                    f"the rope while it hangs; {type(source).__name__} has no {attr!r}",
                )
        check_positive("settle.timeout_s", timeout_s)
        check_positive("poll_s", poll_s)
        check_positive("speed_window_s", speed_window_s)
        self.source, self.fingertip = source, fingertip
        self.gravity_dir = np.asarray(gravity_dir, dtype=float)
        self.criterion, self.length = criterion, float(length)
        self.timeout_s, self.poll_s, self.speed_window_s = timeout_s, poll_s, speed_window_s

    def check(self, stream: RawStream | None, tip: np.ndarray) -> tuple[bool, dict[str, Any]]:
        """Whether ``stream`` (the last window) shows the free end at rest, and the numbers."""
        c = self.criterion
        if stream is None or stream.n_frames < 3:
            return False, {"frames": 0 if stream is None else stream.n_frames}
        end = free_end_track(stream, tip, self.gravity_dir)
        t = stream.times
        speed = _lsq_speed(t, end, self.speed_window_s)
        inside = t >= t[-1] - c.window_s + 1e-9
        seen = np.all(np.isfinite(end[inside]), axis=1)
        covers = t[-1] - t[0] >= c.window_s + self.speed_window_s - 2.0 / MARKER_RATE_HZ
        found = float(seen.mean()) if seen.size else 0.0
        e = end[inside][seen]
        disp = np.linalg.norm(e - e.mean(axis=0), axis=1) if e.size else np.full(1, np.nan)
        v = speed[inside]
        info = {
            "free_end_found": round(found, 3),
            "free_end_speed_m_s": float(np.nanmax(v)) if np.any(np.isfinite(v)) else None,
            "free_end_displacement_m": float(np.nanmax(disp)) if e.size else None,
        }
        rest = covers and found >= 0.9 and not np.any(np.isnan(v[seen]))
        return bool(rest and free_end_at_rest(v, disp, c, self.length)), info

    def __call__(self, phase: str) -> dict[str, Any]:
        """Wait until the rope rests (``phase``: "before" or "after"); plain data for the
        record. Raises :class:`~flyknot.errors.HardwareError` after ``timeout_s``."""
        own = not self.source.recording
        if own:
            self.source.start()
        t_start = time.perf_counter()
        info: dict[str, Any] = {}
        try:
            while True:
                time.sleep(self.poll_s)
                window = self.criterion.window_s + self.speed_window_s
                rest, info = self.check(self.source.recent(window), self.fingertip())
                if rest:
                    return {"rest": info, "criterion": {"speed_m_s": self.criterion.speed_m_s,
                            "window_s": self.criterion.window_s}}  # fmt: skip
                if time.perf_counter() - t_start > self.timeout_s:
                    raise HardwareError(
                        f"settle.timeout_s: the rope did not come to rest {phase} the throw "
                        f"within {self.timeout_s:g} s (last window: {info}); steady it, or "
                        "raise settle.timeout_s"
                    )
        finally:
            if own:
                self.source.stop()

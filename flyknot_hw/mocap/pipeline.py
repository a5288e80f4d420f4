"""From a raw recording to a trial record's markers: label, align the clocks, resample.

:func:`trial_markers` chains the steps for one trial:

1. The fingertip in the mocap frame: a rigid body of the capture system (``tip_body``, the
   hand's marker cluster, whose origin the lab defines at the fingertip), or else forward
   kinematics of the first measured joint sample mapped by ``base_pose`` (the rope hangs
   still at the start, so that is where it hangs from).
2. Labelling (:func:`flyknot_hw.mocap.labelling.label_rope_markers`), started from the
   hanging pose below that fingertip.
3. Clock alignment (:func:`flyknot_hw.mocap.clock.align_clocks`) on the fingertip body
   (coarse offset from its departure from the start pose), or on rope marker 0 when there is
   none (from the start events; less exact: the rope lags the hand).
4. Resampling (:func:`flyknot_hw.mocap.resample.resample_uniform`) onto ``k / rate_hz`` of
   the robot clock, i.e. the record's ``t_marker``, covering the recording.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flyknot.constants import MARKER_RATE_HZ
from flyknot.geometry import readonly
from flyknot_hw.mocap.calibration import apply_pose
from flyknot_hw.mocap.clock import ClockAlignment, Fk, align_clocks
from flyknot_hw.mocap.labelling import LabelParams, LabelResult, label_rope_markers
from flyknot_hw.mocap.resample import DEFAULT_MAX_GAP_S, TIME_TOL, resample_uniform
from flyknot_hw.mocap.stream import RawStream

__all__ = ["TrialMarkers", "trial_markers"]


@dataclass(frozen=True)
class TrialMarkers:
    """A trial's rope markers on the robot clock, and how they were obtained.

    Attributes:
        t_marker: Times on the robot clock, k / rate_hz, shape (n,) [s].
        markers: Rope markers, shape (n, 11, 3) [m], mocap frame; NaN where lost.
        alignment: The clock alignment (offset, residual).
        labels: The labelling on the mocap clock (before resampling).
    """

    t_marker: np.ndarray
    markers: np.ndarray
    alignment: ClockAlignment
    labels: LabelResult

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_marker", readonly(self.t_marker))
        object.__setattr__(self, "markers", readonly(self.markers))


def trial_markers(
    stream: RawStream,
    *,
    t_joint: np.ndarray,
    q_meas: np.ndarray,
    fk: Fk,
    base_pose: np.ndarray,
    tip_body: str | None = None,
    label_params: LabelParams | None = None,
    gravity_dir: np.ndarray = (0.0, 0.0, -1.0),
    arclengths: np.ndarray | None = None,
    rate_hz: float = MARKER_RATE_HZ,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    coarse_offset_s: float | None = None,
) -> TrialMarkers:
    """Label, align and resample one trial's recording (steps in the module docstring).

    Args:
        stream: The recording.
        t_joint: Joint sample times, robot clock, shape (n,) [s].
        q_meas: Measured joints, shape (n, 7) [rad].
        fk: Fingertip forward kinematics, q (n, 7) -> (n, 3) [m], robot base frame.
        base_pose: Robot base in the mocap frame (x, y, z, qw, qx, qy, qz).
        tip_body: Name of the fingertip's rigid body in the stream, or None.
        label_params: Labeller settings; None: the defaults.
        gravity_dir: Gravity in the mocap frame, shape (3,).
        arclengths: Marker arclengths (11,) [m]; None: the paper's ropes.
        rate_hz: Output rate [Hz].
        max_gap_s: Longest gap bridged by interpolation [s].
        coarse_offset_s: Offset from a sync signal [s]; None: start events.
    """
    q = np.asarray(q_meas, dtype=float)
    if tip_body is not None:
        tip = stream.body(tip_body).position
    else:
        tip = apply_pose(base_pose, np.asarray(fk(q[:1]), dtype=float))[0]
    labels = label_rope_markers(
        stream.times,
        stream.points,
        tip,
        params=label_params or LabelParams(),
        gravity_dir=gravity_dir,
        arclengths=arclengths,
    )
    track = tip if tip_body is not None else labels.markers[:, 0]
    al = align_clocks(
        stream.times,
        track,
        t_joint,
        q,
        fk,
        base_pose=base_pose,
        coarse_offset_s=coarse_offset_s,
        departure=tip_body is not None,
    )
    k0 = math.ceil((stream.times[0] + al.offset_s) * rate_hz - TIME_TOL * rate_hz)
    t0 = k0 / rate_hz
    grid, out = resample_uniform(
        stream.times,
        labels.markers,
        rate_hz,
        max_gap_s=max_gap_s,
        t_start=t0 - al.offset_s,
        t_end=float(stream.times[-1]),
    )
    t_marker = t0 + np.arange(grid.shape[0]) / rate_hz
    return TrialMarkers(t_marker, out, al, labels)

"""Motion capture of the real lab: sources, rope-marker labelling, resampling, clocks, calibration.

* :mod:`~flyknot_hw.mocap.stream`: :class:`MocapSource` (start / stop), :class:`RawStream`.
* :mod:`~flyknot_hw.mocap.live`: live systems through ``motioncapture`` (optional extra).
* :mod:`~flyknot_hw.mocap.files`: C3D and CSV recordings, matched to trials.
* :mod:`~flyknot_hw.mocap.labelling`: unlabelled points -> the 11 rope markers.
* :mod:`~flyknot_hw.mocap.resample`: onto the 200 Hz record clock, never across long gaps.
* :mod:`~flyknot_hw.mocap.clock`: mocap clock -> robot clock (start event, cross-correlation).
* :mod:`~flyknot_hw.mocap.calibration`: robot base pose in the mocap frame.
* :mod:`~flyknot_hw.mocap.pipeline`: all of it for one trial.
* :mod:`~flyknot_hw.mocap.trial`: the lab file's source, a trial's markers for the record,
  the live markers' settle check (what the xArm cell uses).

Frames: mocap (world) frame [m]; times [s]. Forward kinematics of the fingertip is injected
by the application as ``fk(q (n, 7)) -> (n, 3)`` in the robot base frame [m].
"""

from flyknot_hw.mocap.calibration import (
    CalibrationResidual,
    apply_pose,
    calibrate_base,
    rigid_fit,
)
from flyknot_hw.mocap.clock import ClockAlignment, align_clocks, start_event_time
from flyknot_hw.mocap.files import (
    RecordedFileSource,
    cluster_labels,
    directory_snapshot,
    match_recording,
    read_c3d,
    read_csv,
    read_recording,
    write_c3d,
    write_csv,
)
from flyknot_hw.mocap.labelling import LabelParams, LabelResult, label_rope_markers
from flyknot_hw.mocap.live import LIVE_KINDS, MotioncaptureSource
from flyknot_hw.mocap.pipeline import TrialMarkers, trial_markers
from flyknot_hw.mocap.resample import DEFAULT_MAX_GAP_S, resample_uniform, uniform_grid
from flyknot_hw.mocap.stream import (
    BodyTrack,
    MocapSource,
    RawStream,
    hanging_markers,
    marker_arclengths,
)
from flyknot_hw.mocap.trial import (
    TIP_BODY,
    CapturedMarkers,
    MarkerSettle,
    free_end_track,
    gravity_in_mocap,
    open_source,
    trial_capture,
)

__all__ = [
    "DEFAULT_MAX_GAP_S",
    "LIVE_KINDS",
    "TIP_BODY",
    "BodyTrack",
    "CalibrationResidual",
    "CapturedMarkers",
    "ClockAlignment",
    "LabelParams",
    "LabelResult",
    "MarkerSettle",
    "MocapSource",
    "MotioncaptureSource",
    "RawStream",
    "RecordedFileSource",
    "TrialMarkers",
    "align_clocks",
    "apply_pose",
    "calibrate_base",
    "cluster_labels",
    "directory_snapshot",
    "free_end_track",
    "gravity_in_mocap",
    "hanging_markers",
    "label_rope_markers",
    "marker_arclengths",
    "match_recording",
    "open_source",
    "read_c3d",
    "read_csv",
    "read_recording",
    "resample_uniform",
    "rigid_fit",
    "start_event_time",
    "trial_capture",
    "trial_markers",
    "uniform_grid",
    "write_c3d",
    "write_csv",
]

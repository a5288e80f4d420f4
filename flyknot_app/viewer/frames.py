"""A trial's drawable state on one clock: the arm's links, the rope, the markers.

:func:`trial_frames` is what the viewer (:mod:`flyknot_app.viewer.server`) and the renders
(:mod:`flyknot_app.viewer.render`) draw.
"""

from __future__ import annotations

import mujoco
import numpy as np

from flyknot.constants import XARM7_XML
from flyknot.geometry import quat_to_matrix
from flyknot.record import TrialRecord

CHAIN = ("link_base", "link1", "link2", "link3", "link4", "link5", "link6", "link7")
RATE_HZ = 50.0
"""Frames per second of the viewer's clock (slider step, playback)."""


def trial_frames(record: TrialRecord, rate_hz: float = RATE_HZ) -> dict[str, np.ndarray]:
    """Everything the viewer draws, sampled on one clock.

    Returns:
        ``t`` (k,) [s]; ``robot`` (k, 9, 3): link origins then the fingertip, lab frame [m];
        ``markers`` (k, 11, 3) (NaN where lost); ``rope`` (k, n, 3) the simulated centreline
        or an empty (k, 0, 3) array without ground truth; ``tip_path`` (n_joint, 3).
    """
    t_end = max(record.t_joint[-1], record.t_marker[-1])
    t = np.arange(0.0, t_end + 1e-9, 1.0 / rate_hz)
    model = mujoco.MjModel.from_xml_path(str(XARM7_XML))
    data = mujoco.MjData(model)
    R_b = quat_to_matrix(record.base_pose[3:])
    p_b = record.base_pose[:3]
    ids = [model.body(n).id for n in CHAIN]
    tip = model.site("fingertip").id
    robot = np.empty((t.size, len(CHAIN) + 1, 3))
    for k, tk in enumerate(t):
        i = min(int(np.searchsorted(record.t_joint, tk)), record.t_joint.size - 1)
        data.qpos[:7] = record.q_meas[i]
        mujoco.mj_kinematics(model, data)
        pts = np.vstack([data.xpos[ids], data.site_xpos[tip]])
        robot[k] = pts @ R_b.T + p_b
    idx = np.clip(np.searchsorted(record.t_marker, t), 0, record.t_marker.size - 1)
    markers = record.markers[idx]
    if "centreline" in record.truth and "t_truth" in record.truth:
        j = np.clip(
            np.searchsorted(record.truth["t_truth"], t), 0, len(record.truth["t_truth"]) - 1
        )
        rope = record.truth["centreline"][j]
    else:
        rope = np.zeros((t.size, 0, 3))
    return {
        "t": t,
        "robot": robot,
        "markers": markers,
        "rope": rope,
        "tip_path": np.asarray(record.fingertip_pos),
    }

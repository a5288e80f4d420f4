"""A 3D viewer of trials in the browser (viser): robot, rope, markers, over time.

``flyknot view RECORD`` serves one trial record (from ``flyknot trial`` or a run
directory) on http://127.0.0.1:8080: the xArm 7 drawn as its link chain from the measured
joints, the rope's simulated centreline when the record carries ground truth, the 11
motion-capture markers (missing where tracking was lost), the fingertip's path, and a time
slider with play/pause.
"""

from __future__ import annotations

import time
from pathlib import Path

import mujoco
import numpy as np

from flyknot.constants import XARM7_XML
from flyknot.geometry import quat_to_matrix
from flyknot.record import TrialRecord

CHAIN = ("link_base", "link1", "link2", "link3", "link4", "link5", "link6", "link7")


def trial_frames(record: TrialRecord, rate_hz: float = 50.0) -> dict[str, np.ndarray]:
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


def _segments(points: np.ndarray) -> np.ndarray:
    """A polyline (n, 3) as line segments (n - 1, 2, 3)."""
    return np.stack([points[:-1], points[1:]], axis=1)


def build_scene(server, record: TrialRecord, frames: dict[str, np.ndarray]):
    """Add the trial to a viser server; returns a function drawing frame k."""
    server.scene.add_grid("/floor", width=3.0, height=3.0, cell_size=0.25)
    server.scene.add_line_segments(
        "/fingertip_path", _segments(frames["tip_path"]), (120, 120, 120), thickness=0.003
    )
    title = f"knot: {record.knot}" + (f" | fault: {record.fault}" if record.fault else "")
    server.gui.add_markdown(f"**{title}**")
    slider = server.gui.add_slider("t [s]", 0.0, float(frames["t"][-1]), 1.0 / 50.0, 0.0)
    play = server.gui.add_checkbox("play", False)
    handles: dict[str, object] = {}

    def draw(k: int) -> None:
        handles["robot"] = server.scene.add_line_segments(
            "/robot", _segments(frames["robot"][k]), (60, 90, 160), thickness=0.03
        )
        rope = frames["rope"][k]
        if rope.shape[0] > 1:
            handles["rope"] = server.scene.add_line_segments(
                "/rope", _segments(rope), (200, 140, 40), thickness=0.009
            )
        m = frames["markers"][k]
        ok = np.all(np.isfinite(m), axis=1)
        handles["markers"] = server.scene.add_point_cloud(
            "/markers", m[ok] if ok.any() else np.zeros((0, 3)), (30, 170, 60), point_size=0.02
        )

    @slider.on_update
    def _(_event) -> None:
        draw(round(slider.value * 50.0))

    draw(0)
    return draw, slider, play


def serve(
    path: str | Path, *, host: str = "127.0.0.1", port: int = 8080, duration_s: float | None = None
) -> None:
    """Serve a trial record until interrupted (or for ``duration_s``)."""
    import viser

    record = TrialRecord.load(path, with_truth=True)
    frames = trial_frames(record)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    _, slider, play = build_scene(server, record, frames)
    print(f"viewer on http://{host}:{port}  (Ctrl-C to stop)")
    t0 = time.monotonic()
    try:
        while duration_s is None or time.monotonic() - t0 < duration_s:
            if play.value:
                nxt = slider.value + 1.0 / 50.0
                slider.value = 0.0 if nxt > frames["t"][-1] else nxt
            time.sleep(1.0 / 50.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()

"""A 3D viewer of trials in the browser (viser): robot, rope, markers, target, over time.

``flyknot view PATH`` serves a trial record or a whole run directory (``flyknot run --out``)
on http://127.0.0.1:8080. Scene nodes:

* ``/robot``: the xArm 7 drawn as its link chain from the measured joints;
* ``/rope``: the rope's simulated centreline, when the record carries ground truth;
* ``/markers``: the 11 motion-capture markers (missing where tracking was lost);
* ``/fingertip_path``: the fingertip's whole path;
* ``/target_rope``: the demonstration's rope (its 11 markers) at the run's critical time
  t_c, placed in the lab as the trial's command placed it: the state the learner aims for;
* ``/critical``: the trial's measured markers at t_c, the critical point the learner compares
  with the target.

The GUI has a trial selector (every record under a run directory), a time slider with play
(t_c marked) and a button that moves the slider to t_c. Which trials, and their targets:
:mod:`flyknot_app.viewer.trials`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError
from flyknot.record import TrialRecord
from flyknot_app.viewer.frames import RATE_HZ, trial_frames
from flyknot_app.viewer.trials import TargetCache, ViewTrial, find_view_trials, markers_at

NODES = ("/robot", "/rope", "/markers", "/fingertip_path", "/target_rope", "/critical")
"""Scene nodes the viewer draws (besides the ``/floor`` grid)."""
COLOURS = {
    "robot": (60, 90, 160),
    "rope": (200, 140, 40),
    "markers": (30, 170, 60),
    "fingertip_path": (120, 120, 120),
    "target_rope": (210, 40, 40),
    "critical": (200, 0, 200),
}
"""RGB of each scene node."""


def _segments(points: np.ndarray) -> np.ndarray:
    """A polyline (n, 3) as line segments (n - 1, 2, 3)."""
    return np.stack([points[:-1], points[1:]], axis=1)


def _title(trial: ViewTrial, record: TrialRecord) -> str:
    """The GUI's description of a trial (markdown)."""
    v = record.verdict
    parts = [f"**{trial.name}**", f"verdict: {'not judged' if v is None else v.describe()}"]
    if record.fault:
        parts.append(f"fault: {record.fault}")
    parts.append("t_c: none (not in a run)" if trial.t_c is None else f"t_c = {trial.t_c:.3f} s")
    return "  \n".join(parts)


class RunViewer:
    """The scene and GUI of a set of trials on a viser server.

    Attributes:
        trials: The trials the selector offers.
        record: The trial shown now.
        frames: Its :func:`trial_frames`.
        target: The demonstration's markers at t_c in the lab (11, 3), or None.
        selector, slider, play, to_t_c: The GUI handles.
    """

    def __init__(self, server, trials: Sequence[ViewTrial], rate_hz: float = RATE_HZ):
        if not trials:
            raise ConfigError("trials", "the viewer needs at least one trial")
        self.server = server
        self.trials = tuple(trials)
        self.rate_hz = rate_hz
        self._targets = TargetCache()
        self._lock = threading.RLock()
        self._by_name = {t.name: i for i, t in enumerate(self.trials)}
        server.scene.set_up_direction("+z")
        server.scene.add_grid("/floor", width=3.0, height=3.0, cell_size=0.25)
        names = [t.name for t in self.trials]
        self.selector = server.gui.add_dropdown("trial", names, initial_value=names[0], order=0.0)
        self.info = server.gui.add_markdown("", order=0.5)
        self.slider = None
        self.play = server.gui.add_checkbox("play", False, order=2.0)
        self.to_t_c = server.gui.add_button("go to t_c", order=3.0)
        self.index = -1

        @self.selector.on_update
        def _(_event) -> None:
            self.show(self._by_name[self.selector.value])

        @self.to_t_c.on_click
        def _(_event) -> None:
            with self._lock:
                t_c = self.trials[self.index].t_c
                if t_c is not None:
                    self.play.value = False
                    self.slider.value = min(self.slider.max, round(t_c * rate_hz) / rate_hz)

        self.show(0)

    def _new_slider(self, t_end: float, t_c: float | None, value: float) -> None:
        """(Re)make the time slider for a trial: range [0, t_end], t_c marked."""
        if self.slider is not None:
            self.slider.remove()
        marks: list[tuple[float, str]] = [(0.0, "0"), (t_end, f"{t_end:.2f}")]
        if t_c is not None and 0.0 <= t_c <= t_end:
            marks.insert(1, (t_c, "t_c"))
        self.slider = self.server.gui.add_slider(
            "t [s]",
            0.0,
            t_end,
            1.0 / self.rate_hz,
            min(value, t_end),
            marks=tuple(marks),
            order=1.0,
        )

        @self.slider.on_update
        def _(_event) -> None:
            self.draw(self.frame_at(self.slider.value))

    def frame_at(self, t: float) -> int:
        """Index of the frame shown at time ``t`` [s]."""
        return int(np.clip(round(t * self.rate_hz), 0, self.frames["t"].size - 1))

    def show(self, index: int) -> None:
        """Load trial ``index`` and draw its static nodes and its frame at the slider's time."""
        with self._lock:
            trial = self.trials[index]
            self.record = TrialRecord.load(trial.path, with_truth=True)
            self.frames = trial_frames(self.record, self.rate_hz)
            self.target = self._targets.target_in_lab(trial, self.record)
            self.index = index
            scene = self.server.scene
            scene.add_line_segments(
                "/fingertip_path",
                _segments(self.frames["tip_path"]),
                COLOURS["fingertip_path"],
                thickness=0.003,
            )
            if self.target is not None:
                scene.add_line_segments(
                    "/target_rope", _segments(self.target), COLOURS["target_rope"], thickness=0.01
                )
            else:
                scene.remove_by_name("/target_rope")
            if trial.t_c is not None:
                scene.add_point_cloud(
                    "/critical",
                    markers_at(self.record, trial.t_c),
                    COLOURS["critical"],
                    point_size=0.035,
                    point_shape="diamond",
                    point_shading="flat",
                )
            else:
                scene.remove_by_name("/critical")
            self.info.content = _title(trial, self.record)
            self.to_t_c.disabled = trial.t_c is None
            value = 0.0 if self.slider is None else self.slider.value
            self._new_slider(float(self.frames["t"][-1]), trial.t_c, value)
            self.draw(self.frame_at(self.slider.value))

    def draw(self, k: int) -> None:
        """Draw the time-varying nodes (robot, rope, markers) at frame ``k``."""
        with self._lock:
            f = self.frames
            k = int(np.clip(k, 0, f["t"].size - 1))
            scene = self.server.scene
            scene.add_line_segments(
                "/robot", _segments(f["robot"][k]), COLOURS["robot"], thickness=0.03
            )
            rope = f["rope"][k]
            if rope.shape[0] > 1:
                scene.add_line_segments("/rope", _segments(rope), COLOURS["rope"], thickness=0.009)
            else:
                scene.remove_by_name("/rope")
            m = f["markers"][k]
            ok = np.all(np.isfinite(m), axis=1)
            scene.add_point_cloud(
                "/markers", m[ok], COLOURS["markers"], point_size=0.02, point_shading="flat"
            )

    def step(self) -> None:
        """Advance the slider by one frame while ``play`` is on (wrapping at the end)."""
        with self._lock:
            if self.play.value:
                nxt = self.slider.value + 1.0 / self.rate_hz
                self.slider.value = 0.0 if nxt > self.slider.max + 1e-9 else nxt


def frame_camera(viewer: RunViewer) -> tuple[np.ndarray, np.ndarray]:
    """A camera (look-at point, position) framing the shown trial's arm, rope and target."""
    f = viewer.frames
    pts = [f["robot"].reshape(-1, 3), f["rope"].reshape(-1, 3), f["markers"].reshape(-1, 3)]
    if viewer.target is not None:
        pts.append(viewer.target)
    pts = np.vstack(pts)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    look_at = 0.5 * (lo + hi)
    direction = np.array([1.0, -1.0, 0.5]) / 1.5
    return look_at, look_at + max(1.0, float(np.linalg.norm(hi - lo))) * direction


def start(
    path: str | Path, *, host: str = "127.0.0.1", port: int = 8080
) -> tuple[object, RunViewer]:
    """Start a viser server showing ``path`` (a record or a run directory).

    Returns:
        The server (stop it with ``server.stop()``) and the :class:`RunViewer`.

    Raises:
        ConfigError: ``path`` is neither a trial record nor a directory holding some.
    """
    import viser

    trials = find_view_trials(path)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        viewer = RunViewer(server, trials)
        look_at, position = frame_camera(viewer)
        server.initial_camera.look_at = look_at
        server.initial_camera.position = position
    except BaseException:
        server.stop()
        raise
    return server, viewer


def serve(
    path: str | Path, *, host: str = "127.0.0.1", port: int = 8080, duration_s: float | None = None
) -> None:
    """Serve a trial record or a run directory until interrupted (or for ``duration_s``)."""
    server, viewer = start(path, host=host, port=port)
    n = len(viewer.trials)
    print(f"viewer on http://{host}:{port}  ({n} trial{'s' * (n != 1)}; Ctrl-C to stop)")
    t0 = time.monotonic()
    try:
        while duration_s is None or time.monotonic() - t0 < duration_s:
            viewer.step()
            time.sleep(1.0 / viewer.rate_hz)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()

"""Offscreen renders of a trial for papers: ``flyknot render RECORD --out x.png|x.mp4``.

MuJoCo draws the lab's rigid scene (floor, pedestal, the xArm 7; :func:`flyknot_sim.scene.
scene_spec` with the record's base height) with the arm posed from the record's measured
joints. The rope is added to MuJoCo's scene as capsules along the simulated centreline when
the record carries ground truth, else along the finite motion-capture markers; the markers
are small spheres. The camera is fixed for the whole trial, framing every position of the arm
and the rope.

Rendering needs no display: the OpenGL context is EGL (``MUJOCO_GL=osmesa`` selects OSMesa,
``glfw``/``glx`` a window-system context). The context is made here, not chosen by the
``MUJOCO_GL`` that was set when MuJoCo was first imported (the CLI imports MuJoCo long before
a command runs), so ``flyknot render`` works headless whatever that was.

Parameter errors name the command-line flag (``--out``, ``--time``, ``--width``, ...).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from flyknot.errors import ConfigError, RenderError, check_int, check_positive
from flyknot.geometry import quat_to_matrix
from flyknot.record import TrialRecord

SUFFIXES = (".png", ".mp4")
"""Output types: one frame, or a video through the trial."""
ROPE_RGBA = np.array([0.85, 0.55, 0.15, 1.0], dtype=np.float32)
MARKER_RGBA = np.array([0.12, 0.67, 0.24, 1.0], dtype=np.float32)


@dataclass(frozen=True)
class RenderParams:
    """Image size, video rate and how the rope is drawn.

    Attributes:
        width: Image width [px].
        height: Image height [px].
        fps: Frames per second of a video (frames at 0, 1/fps, ... through the trial).
        rope_radius: Radius of the rope's capsules [m].
        marker_radius: Radius of the marker spheres [m].
        azimuth: Camera azimuth [deg] (MuJoCo's free camera).
        elevation: Camera elevation [deg] (negative: looking down).
        close_up: Frame the rope at the end of the trial and the fingertip only (for a
            person checking a verdict), not the arm and the rope over the whole trial.
        show_arm: Draw the arm (a hand-lab replay has none).
        focus: Vertices of the final rope the camera frames, (first, last), e.g. a verdict's
            knot core; None: as ``close_up`` says.
    """

    width: int = 640
    height: int = 480
    fps: float = 30.0
    rope_radius: float = 0.008
    marker_radius: float = 0.012
    azimuth: float = 125.0
    elevation: float = -12.0
    close_up: bool = False
    show_arm: bool = True
    focus: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        check_int("--width", self.width, 16)
        check_int("--height", self.height, 16)
        check_positive("--fps", self.fps)
        check_positive("rope_radius", self.rope_radius)
        check_positive("marker_radius", self.marker_radius)


def _gl_context(width: int, height: int):
    """An offscreen OpenGL context of the backend ``MUJOCO_GL`` asks for (default EGL).

    Mesa's software rasteriser (llvmpipe, what EGL gives without a GPU) draws on threads it
    starts with its first context; a process forked after that (a run pool's worker) inherits
    the rasteriser's state but not its threads and hangs in its first render. Unless the
    user has set ``LP_NUM_THREADS``, it is set to 0 here, before the first context: llvmpipe
    then draws in the calling thread (six pictures with their set-up 3.3-4.2 s against
    3.1-3.3 s on threads, 2-core machine; docs/performance.md), and pool workers can draw
    their runs' pictures."""
    os.environ.setdefault("LP_NUM_THREADS", "0")
    backend = os.environ.get("MUJOCO_GL", "").strip().lower() or "egl"
    try:
        if backend == "osmesa":
            from mujoco.osmesa import GLContext
        elif backend in ("glfw", "glx"):
            from mujoco.glfw import GLContext
        else:
            from mujoco.egl import GLContext
        return GLContext(width, height)
    except Exception as e:  # a missing library shows as any of several errors
        raise RenderError(
            f"no offscreen OpenGL context ({backend}: {type(e).__name__}: {e}); install "
            "Mesa's EGL (Debian: libegl1 libgl1-mesa-dri) or set MUJOCO_GL to a backend "
            "this machine has"
        ) from None


def rope_radius_of(record: TrialRecord) -> float | None:
    """The rope's radius [m] from the record's metadata (a paper rope's id, or a custom
    rope's parameters), or None when the record does not say."""
    meta = record.metadata
    custom = meta.get("rope_params")
    if isinstance(custom, dict) and isinstance(custom.get("diameter"), (int, float)):
        return 0.5 * float(custom["diameter"])
    rope = meta.get("rope")
    if isinstance(rope, int) and not isinstance(rope, bool):
        from flyknot.errors import ConfigError as _Unknown
        from flyknot_sim.rope_table import get_rope

        try:
            return 0.5 * get_rope(rope).diameter
        except _Unknown:
            return None
    return None


def check_output(out: str | Path) -> str:
    """The output type of ``out`` (``".png"`` or ``".mp4"``).

    Raises:
        ConfigError: ``--out`` has another suffix (the message lists the valid ones).
    """
    suffix = Path(out).suffix.lower()
    if suffix not in SUFFIXES:
        raise ConfigError("--out", f"unsupported file type of {str(out)!r}", SUFFIXES)
    return suffix


def trial_end(record: TrialRecord) -> float:
    """Time of the record's last joint or marker sample [s] (the end of the motion)."""
    return float(max(record.t_joint[-1], record.t_marker[-1]))


def frame_times(record: TrialRecord, fps: float) -> np.ndarray:
    """Times of a video's frames: 0, 1/fps, ... up to the end of the trial [s]."""
    check_positive("--fps", fps)
    return np.arange(0.0, trial_end(record) + 1e-9, 1.0 / fps)


def _nearest(t: np.ndarray, tk: float) -> int:
    return int(np.clip(np.searchsorted(t, tk), 0, t.size - 1))


def pedestal_height(record: TrialRecord) -> float:
    """The scene's pedestal height for ``record`` [m]: its base pose's height when that is a
    plausible one (0.05-5 m), else the scene's default."""
    from flyknot_sim.scene import SceneParams

    base = np.asarray(record.base_pose, dtype=float)
    return float(base[2]) if 0.05 < base[2] < 5.0 else SceneParams().pedestal_height


class TrialRenderer:
    """Draws one trial record's frames with MuJoCo (offscreen; close it when done).

    Lab (motion-capture) frame points are placed in the rendered scene by the record's base
    pose: p_scene = R_b^T (p - t_b) + (0, 0, h), h the pedestal height (the base's height
    above the mocap origin, so a simulated record's frame is the scene's).
    """

    def __init__(self, record: TrialRecord, params: RenderParams = RenderParams()):
        from flyknot_sim.scene import SceneParams, scene_spec

        self.pedestal = pedestal_height(record)
        self.size = (params.width, params.height)
        self.model = scene_spec(SceneParams(pedestal_height=self.pedestal)).compile()
        self.model.vis.global_.offwidth = max(params.width, self.model.vis.global_.offwidth)
        self.model.vis.global_.offheight = max(params.height, self.model.vis.global_.offheight)
        self.data = mujoco.MjData(self.model)
        self._qadr = [self.model.joint(f"xarm7/joint{i}").qposadr[0] for i in range(1, 8)]
        names = (self.model.body(b).name for b in range(self.model.nbody))
        arm = [b for b, name in enumerate(names) if name.startswith("xarm7/")]
        self._arm_geoms = np.isin(self.model.geom_bodyid, arm)
        self._arm_alpha = self.model.geom_rgba[self._arm_geoms, 3].copy()
        self._gl = _gl_context(params.width, params.height)
        self._gl.make_current()
        self._context = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self.scene = mujoco.MjvScene(self.model, maxgeom=2000)
        # The scene's light casts shadows onto a floor the pedestal stands on and the rope
        # hangs high above: the shadow-map and reflection passes drew no pixel differently in
        # whole-trial and close-up views (640x480), and without them a picture takes 0.19 s
        # against 0.41 s on Mesa's software rasteriser (docs/performance.md).
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            self.scene.flags[flag] = False
        self._option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, params.width, params.height)
        self.view(record, params)

    def fits(self, record: TrialRecord, params: RenderParams) -> bool:
        """Whether :meth:`view` can take ``record`` and ``params``: the same pedestal height
        (the compiled scene) and image size (the OpenGL buffer)."""
        return pedestal_height(record) == self.pedestal and (params.width, params.height) == (
            self.size
        )

    def view(self, record: TrialRecord, params: RenderParams) -> None:
        """Draw ``record`` with ``params`` from now on, on the same scene and OpenGL context
        (setting them up costs more than drawing a frame).

        Raises:
            ConfigError: ``record`` stands on another pedestal height, or ``params`` asks
                for another image size (:meth:`fits`).
        """
        if not self.fits(record, params):
            raise ConfigError(
                "record",
                f"needs a renderer for pedestal {pedestal_height(record):g} m and "
                f"{params.width}x{params.height} px; this one draws {self.pedestal:g} m and "
                f"{self.size[0]}x{self.size[1]} px",
            )
        self.record = record
        self.params = params
        base = np.asarray(record.base_pose, dtype=float)
        self._R_b = quat_to_matrix(base[3:])
        self._shift = np.array([0.0, 0.0, self.pedestal]) - base[:3] @ self._R_b
        alpha = self._arm_alpha if params.show_arm else 0.0
        self.model.geom_rgba[self._arm_geoms, 3] = alpha
        self.has_truth = "centreline" in record.truth and "t_truth" in record.truth
        self.camera = self._frame_camera()

    def to_scene(self, p: np.ndarray) -> np.ndarray:
        """Lab-frame points (..., 3) in the rendered scene's frame."""
        return np.asarray(p, dtype=float) @ self._R_b + self._shift

    def rope_at(self, t: float) -> np.ndarray:
        """The drawn rope at ``t`` (scene frame, (n, 3)): centreline, else finite markers."""
        r = self.record
        if self.has_truth:
            return self.to_scene(r.truth["centreline"][_nearest(r.truth["t_truth"], t)])
        return self.markers_at(t)

    def markers_at(self, t: float) -> np.ndarray:
        """The finite markers at the marker sample nearest ``t`` (scene frame, (n, 3))."""
        m = self.record.markers[_nearest(self.record.t_marker, t)]
        return self.to_scene(m[np.all(np.isfinite(m), axis=1)])

    def pose(self, t: float) -> None:
        """Set the arm to the measured joints nearest ``t`` and update its kinematics."""
        q = self.record.q_meas[_nearest(self.record.t_joint, t)]
        self.data.qpos[self._qadr] = q
        mujoco.mj_kinematics(self.model, self.data)

    def _frame_camera(self) -> mujoco.MjvCamera:
        """A free camera framing the arm and the rope over the whole trial."""
        from flyknot_app.viewer.frames import trial_frames

        if self.params.focus is not None:
            first, last = self.params.focus
            pts = self.rope_at(trial_end(self.record))[first : last + 1]
        elif self.params.close_up:
            end = trial_end(self.record)
            tip = self.record.fingertip_pos[_nearest(self.record.t_joint, end)]
            pts = np.vstack([self.rope_at(end), self.to_scene(tip)[None]])
        else:
            f = trial_frames(self.record, rate_hz=20.0)
            pts = [f["robot"], f["rope"], f["markers"]]
            pts = self.to_scene(np.vstack([p.reshape(-1, 3) for p in pts]))
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        radius = 0.5 * float(np.linalg.norm(hi - lo))
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = 0.5 * (lo + hi)
        # The narrower of the vertical and horizontal half-angles must hold the sphere.
        tan_half = np.tan(0.5 * np.radians(self.model.vis.global_.fovy))
        half = np.arctan(tan_half * min(1.0, self.params.width / self.params.height))
        cam.distance = 1.2 * radius / np.sin(half) if radius > 0 else 2.0
        cam.azimuth = self.params.azimuth
        cam.elevation = self.params.elevation
        return cam

    def _add(self, geom_type: int, size, pos, rgba: np.ndarray) -> mujoco.MjvGeom | None:
        if self.scene.ngeom >= self.scene.maxgeom:
            return None
        g = self.scene.geoms[self.scene.ngeom]
        mujoco.mjv_initGeom(
            g, geom_type, np.asarray(size, float), np.asarray(pos, float), np.eye(3).ravel(), rgba
        )
        self.scene.ngeom += 1
        return g

    def _draw_rope(self, t: float) -> None:
        rope = self.rope_at(t)
        r = self.params.rope_radius
        for a, b in itertools.pairwise(rope):
            g = self._add(mujoco.mjtGeom.mjGEOM_CAPSULE, (r, r, r), a, ROPE_RGBA)
            if g is not None:
                mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_CAPSULE, r, a, b)
        for p in self.markers_at(t):
            self._add(
                mujoco.mjtGeom.mjGEOM_SPHERE, (self.params.marker_radius,) * 3, p, MARKER_RGBA
            )

    def render(self, t: float, caption: str | None = None) -> np.ndarray:
        """The image at time ``t`` [s], (height, width, 3) uint8, with ``caption`` written
        at its top left."""
        self._gl.make_current()
        self.pose(t)
        mujoco.mjv_updateScene(
            self.model,
            self.data,
            self._option,
            None,
            self.camera,
            mujoco.mjtCatBit.mjCAT_ALL,
            self.scene,
        )
        self._draw_rope(t)
        mujoco.mjr_render(self._rect, self.scene, self._context)
        if caption:
            mujoco.mjr_overlay(
                mujoco.mjtFont.mjFONT_NORMAL,
                mujoco.mjtGridPos.mjGRID_TOPLEFT,
                self._rect,
                caption,
                "",
                self._context,
            )
        rgb = np.empty((self.params.height, self.params.width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(rgb, None, self._rect, self._context)
        return np.flipud(rgb)

    def frames(self, times: np.ndarray) -> Iterator[np.ndarray]:
        """The images at ``times``, one by one."""
        for t in times:
            yield self.render(float(t))

    def close(self) -> None:
        """Free the OpenGL resources."""
        if self._context is not None:
            self._gl.make_current()
            self._context.free()
            self._context = None
            self._gl.free()

    def __enter__(self) -> TrialRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RendererCache:
    """Open :class:`TrialRenderer` s, one per scene and image size, re-bound to each record
    asked for (:meth:`TrialRenderer.view`): many pictures pay the scene's and the OpenGL
    context's set-up once. Close it when done (or use it as a context manager)."""

    def __init__(self) -> None:
        self._open: list[TrialRenderer] = []

    def get(self, record: TrialRecord, params: RenderParams) -> TrialRenderer:
        """A renderer drawing ``record`` with ``params``."""
        for renderer in self._open:
            if renderer.fits(record, params):
                renderer.view(record, params)
                return renderer
        renderer = TrialRenderer(record, params)
        self._open.append(renderer)
        return renderer

    def close(self) -> None:
        """Close every renderer."""
        for renderer in self._open:
            renderer.close()
        self._open.clear()

    def __enter__(self) -> RendererCache:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_trial(
    record: str | Path | TrialRecord,
    out: str | Path,
    *,
    time: float | None = None,
    params: RenderParams = RenderParams(),
    caption: str | None = None,
) -> Path:
    """Render a trial to ``out``: a .png at ``time`` or an .mp4 through the trial.

    Args:
        record: The trial record (a loaded one, or its ``.json``/``.npz``/stem).
        out: Output file, ``.png`` (one frame) or ``.mp4`` (H.264 at ``params.fps``).
        time: Time of the .png [s]; default the end of the motion (the trial's last sample).
        params: Size, rate, drawing.
        caption: Text at the top left of a .png (e.g. the verdict).

    Returns:
        ``out``.

    Raises:
        ConfigError: An unsupported suffix, ``time`` outside the trial or given for a video,
            or an odd size for a video (H.264's 4:2:0 needs even sides).
    """
    kind = check_output(out)
    out = Path(out)
    if not isinstance(record, TrialRecord):
        record = TrialRecord.load(record, with_truth=True)
    end = trial_end(record)
    if kind == ".mp4":
        if time is not None:
            raise ConfigError("--time", "applies to a .png only; an .mp4 runs through the trial")
        for flag, v in (("--width", params.width), ("--height", params.height)):
            if v % 2:
                raise ConfigError(flag, f"must be even for an .mp4 (H.264), got {v}")
    else:
        time = end if time is None else time
        number = isinstance(time, (int, float)) and not isinstance(time, bool)
        if not (number and 0.0 <= time <= end):
            raise ConfigError("--time", f"must lie in the trial [0, {end:.3f}] s, got {time!r}")
    import imageio.v2 as imageio

    out.parent.mkdir(parents=True, exist_ok=True)
    with TrialRenderer(record, params) as renderer:
        if kind == ".png":
            imageio.imwrite(out, renderer.render(float(time), caption))
        else:
            with imageio.get_writer(
                out,
                format="FFMPEG",
                mode="I",
                fps=params.fps,
                codec="libx264",
                macro_block_size=2,
                ffmpeg_log_level="error",
            ) as writer:
                for frame in renderer.frames(frame_times(record, params.fps)):
                    writer.append_data(frame)
    return out


__all__ = [
    "SUFFIXES",
    "RenderParams",
    "TrialRenderer",
    "check_output",
    "frame_times",
    "render_trial",
    "rope_radius_of",
    "trial_end",
]

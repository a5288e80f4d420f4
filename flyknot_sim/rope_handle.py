"""Handles of a built rope: names (:class:`RopeHandle`), ids (:class:`BoundRope`), and the
pure geometry of a rope's vertices (markers at rest arc length, length, hanging shape).

:func:`flyknot_sim.rope.add_rope` builds the rope and returns its :class:`RopeHandle`. Arc
length, markers and :meth:`BoundRope.length` are measured from vertex 0 (the held end).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from flyknot.constants import MARKER_SPACING, N_MARKERS
from flyknot.errors import ConfigError
from flyknot_sim.rope_table import RopeParams

__all__ = [
    "BoundRope",
    "RopeHandle",
    "hanging_vertices",
    "marker_arclengths",
    "points_at_arclength",
    "polyline_length",
    "sway_direction",
]


# ----------------------------------------------------------------------------------------
# pure geometry kernels
# ----------------------------------------------------------------------------------------
def sway_direction(sway_angle: float, sway_azimuth: float) -> np.ndarray:
    """Unit vector tilted by ``sway_angle`` from straight down, toward ``sway_azimuth``.

    d = (sin(a) cos(phi), sin(a) sin(phi), -cos(a)) for tilt a [rad] and azimuth phi [rad]
    measured from world x about world z.

    Returns:
        Direction, shape (3,).
    """
    sa = math.sin(sway_angle)
    return np.array(
        [sa * math.cos(sway_azimuth), sa * math.sin(sway_azimuth), -math.cos(sway_angle)]
    )


def hanging_vertices(
    p0: np.ndarray, p1: np.ndarray, direction: np.ndarray, n_segments: int
) -> np.ndarray:
    """Vertices of a rope held at ``p0``, ``p1`` that continues straight along ``direction``.

    x_0 = p0, x_1 = p1, x_k = p1 + (k - 1) |p1 - p0| d for k = 2..n, d = direction / |direction|.

    Args:
        p0: Held end, shape (3,) [m].
        p1: Second vertex, shape (3,) [m]; |p1 - p0| is the segment length.
        direction: Direction of the rest of the rope, shape (3,).
        n_segments: Number of segments n.

    Returns:
        Vertices, shape (n + 1, 3) [m].
    """
    p0 = np.asarray(p0, dtype=float)
    p1 = np.asarray(p1, dtype=float)
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    seg = float(np.linalg.norm(p1 - p0))
    k = np.arange(n_segments - 1, dtype=float)[:, None]
    return np.vstack([p0, p1, p1 + (k + 1) * seg * d])


def polyline_length(vertices: np.ndarray) -> np.ndarray:
    """Length of polylines, sum_k |x_{k+1} - x_k|.

    Args:
        vertices: Shape (..., n + 1, 3) [m].

    Returns:
        Shape (...) [m].
    """
    v = np.asarray(vertices, dtype=float)
    return np.linalg.norm(np.diff(v, axis=-2), axis=-1).sum(axis=-1)


def points_at_arclength(vertices: np.ndarray, segment_length: float, s: np.ndarray) -> np.ndarray:
    """Material points of a rope at rest arc lengths ``s`` from vertex 0.

    With k = min(floor(s / l), n - 1) and f = s / l - k, the point is
    x_k + f (x_{k+1} - x_k): markers ride on the material, so a stretched rope carries them
    along.

    Args:
        vertices: Shape (..., n + 1, 3) [m].
        segment_length: Rest length l of one element [m].
        s: Arc lengths, shape (m,) [m], each in [0, n l].

    Returns:
        Shape (..., m, 3) [m].

    Raises:
        ConfigError: An arc length outside [0, n l].
    """
    v = np.asarray(vertices, dtype=float)
    s = np.asarray(s, dtype=float)
    n = v.shape[-2] - 1
    u = s / segment_length
    if np.any(u < -1e-9) or np.any(u > n + 1e-9):
        raise ConfigError("s", f"arc lengths must lie in [0, {n * segment_length:.6g}] m")
    k = np.clip(np.floor(u).astype(int), 0, n - 1)
    f = (u - k)[:, None]
    return v[..., k, :] * (1 - f) + v[..., k + 1, :] * f


def marker_arclengths(length: float) -> np.ndarray:
    """Marker rest arc lengths 0.10, 0.20, ..., the last one at the free end [m], shape (11,)."""
    s = MARKER_SPACING * np.arange(1, N_MARKERS + 1)
    s[-1] = length
    return s


# ----------------------------------------------------------------------------------------
# handles
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RopeHandle:
    """Names of everything :func:`flyknot_sim.rope.add_rope` put in the spec.

    Resolve it against a compiled model with :meth:`bind`; the methods taking
    ``(model, data)`` bind on the fly (cached for the last model).

    Attributes:
        params: The rope.
        prefix: Name prefix.
        flex: Flex name.
        vertex_bodies: Vertex body names, held end first, shape (n + 1,).
        twist_joints: The rod's per-edge twist hinge names (empty for a rope without
            elasticity).
        end_geom: The end-weight sphere geom.
        anchor_body: Body holding the rope.
        hold_sites: Sites on the anchor body where vertices 0 and 1 are held.
        hold_equalities: The two ``connect`` equalities.
        edge_equality: The flex edge-length equality.
    """

    params: RopeParams
    prefix: str
    flex: str
    vertex_bodies: tuple[str, ...]
    twist_joints: tuple[str, ...]
    end_geom: str
    anchor_body: str
    hold_sites: tuple[str, str]
    hold_equalities: tuple[str, str]
    edge_equality: str
    _cache: list = field(default_factory=list, compare=False, repr=False)

    def bind(self, model: mujoco.MjModel) -> BoundRope:
        """Resolve the names against ``model``.

        Raises:
            ConfigError: A name is missing from the model.
        """
        if self._cache and self._cache[0] is model:
            return self._cache[1]
        bound = BoundRope.from_names(self, model)
        self._cache[:] = [model, bound]
        return bound

    def vertex_positions(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """See :meth:`BoundRope.vertex_positions`."""
        return self.bind(model).vertex_positions(model, data)

    def centreline(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """See :meth:`BoundRope.centreline`."""
        return self.bind(model).centreline(model, data)

    def markers(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """See :meth:`BoundRope.markers`."""
        return self.bind(model).markers(model, data)

    def self_contact(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        """See :meth:`BoundRope.self_contact`."""
        return self.bind(model).self_contact(model, data)

    def self_contact_span(
        self, model: mujoco.MjModel, data: mujoco.MjData
    ) -> tuple[int, int] | None:
        """See :meth:`BoundRope.self_contact_span`."""
        return self.bind(model).self_contact_span(model, data)

    def length(self, model: mujoco.MjModel, data: mujoco.MjData) -> float:
        """See :meth:`BoundRope.length`."""
        return self.bind(model).length(model, data)

    def set_hanging(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        sway_angle: float = 0.0,
        sway_azimuth: float = 0.0,
        sway_rate: float = 0.0,
    ) -> None:
        """See :meth:`BoundRope.set_hanging`."""
        self.bind(model).set_hanging(model, data, sway_angle, sway_azimuth, sway_rate)


COMPILED = True
"""Scan the contacts for the rope's self-contacts with the compiled kernel
(:mod:`flyknot_sim.contact_kernel`); False: NumPy (:meth:`BoundRope.self_contact_elements`)."""


def _ids(model: mujoco.MjModel, obj: mujoco.mjtObj, names: Iterable[str], what: str) -> np.ndarray:
    out = []
    for name in names:
        i = mujoco.mj_name2id(model, obj, name)
        if i < 0:
            raise ConfigError(what, f"no {what} named {name!r} in the model")
        out.append(i)
    return np.array(out, dtype=int)


@dataclass(frozen=True, eq=False)
class BoundRope:
    """A rope resolved against one compiled model (ids and addresses).

    Methods take ``(model, data)`` for symmetry with :class:`RopeHandle`; ``model`` must be
    the model it was bound to.
    """

    handle: RopeHandle
    flex_id: int
    vert_adr: int
    n_vert: int
    vert_body: np.ndarray
    vert_qpos: np.ndarray
    vert_dof: np.ndarray
    twist_qpos: np.ndarray
    twist_dof: np.ndarray
    end_geom: int
    hold_sites: np.ndarray
    plastic: slice
    body_pos0: np.ndarray

    @classmethod
    def from_names(cls, handle: RopeHandle, model: mujoco.MjModel) -> BoundRope:
        """Resolve ``handle``'s names in ``model``."""
        fid = int(_ids(model, mujoco.mjtObj.mjOBJ_FLEX, [handle.flex], "flex")[0])
        vb = _ids(model, mujoco.mjtObj.mjOBJ_BODY, handle.vertex_bodies, "body")
        adr, num = int(model.flex_vertadr[fid]), int(model.flex_vertnum[fid])
        if num != len(vb) or not np.array_equal(model.flex_vertbodyid[adr : adr + num], vb):
            raise ConfigError("flex", f"flex {handle.flex!r} does not match its vertex bodies")
        qpos, dof = [], []
        for b in vb:
            j0, nj = int(model.body_jntadr[b]), int(model.body_jntnum[b])
            axes = model.jnt_axis[j0 : j0 + nj]
            if nj != 3 or model.body_parentid[b] != 0 or not np.allclose(axes, np.eye(3)):
                raise ConfigError("flex", "vertex bodies must hang from the world on x/y/z slides")
            qpos.append(model.jnt_qposadr[j0 : j0 + 3])
            dof.append(model.jnt_dofadr[j0 : j0 + 3])
        tj = _ids(model, mujoco.mjtObj.mjOBJ_JOINT, handle.twist_joints, "joint")
        start = int(model.flex_plasticadr[fid])
        later = [int(a) for a in model.flex_plasticadr if a > start]
        stop = min(later) if later else int(model.nplastic)
        return cls(
            handle=handle,
            flex_id=fid,
            vert_adr=adr,
            n_vert=num,
            vert_body=vb,
            vert_qpos=np.array(qpos, dtype=int),
            vert_dof=np.array(dof, dtype=int),
            twist_qpos=model.jnt_qposadr[tj].astype(int) if len(tj) else np.zeros(0, int),
            twist_dof=model.jnt_dofadr[tj].astype(int) if len(tj) else np.zeros(0, int),
            end_geom=int(_ids(model, mujoco.mjtObj.mjOBJ_GEOM, [handle.end_geom], "geom")[0]),
            hold_sites=_ids(model, mujoco.mjtObj.mjOBJ_SITE, handle.hold_sites, "site"),
            plastic=slice(start, stop),
            body_pos0=model.body_pos[vb].copy(),
        )

    @property
    def params(self) -> RopeParams:
        """The rope's parameters."""
        return self.handle.params

    @property
    def n_segments(self) -> int:
        """Number of elements n."""
        return self.n_vert - 1

    # -- state read-out ------------------------------------------------------------------
    def vertex_positions(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Vertex world positions, held end first, shape (n + 1, 3) [m] (a copy)."""
        return data.flexvert_xpos[self.vert_adr : self.vert_adr + self.n_vert].copy()

    def centreline(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Centreline from the held end to the free end, shape (n + 1, 3) [m]."""
        return self.vertex_positions(model, data)

    def length(self, model: mujoco.MjModel, data: mujoco.MjData) -> float:
        """Current centreline length sum_k |x_{k+1} - x_k| [m]."""
        return float(polyline_length(self.vertex_positions(model, data)))

    def markers(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """The 11 markers at rest arc length 0.1, ..., 1.1 m from the held end, (11, 3) [m]."""
        return self.markers_from_vertices(self.vertex_positions(model, data))

    def markers_from_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """Markers of stored vertex positions, (..., n + 1, 3) -> (..., 11, 3) [m]."""
        p = self.params
        return points_at_arclength(vertices, p.segment_length, marker_arclengths(p.length))

    def centrelines_from_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """Centrelines of stored vertex positions, (..., n + 1, 3) -> same shape [m]."""
        return np.array(vertices, dtype=float, copy=True)

    def self_contact_elements(self, data: mujoco.MjData) -> np.ndarray:
        """Element pairs of the rope's self-contacts, shape (k, 2): two elements i, j with
        |i - j| >= 2 (sharing no vertex), or the end weight (as element n) and an element
        j <= n - 2 (the readable reference of :mod:`flyknot_sim.contact_kernel`)."""
        ncon = data.ncon
        if ncon == 0:
            return np.zeros((0, 2), dtype=int)
        c = data.contact
        flex = c.flex[:ncon]
        elem = c.elem[:ncon]
        active = c.exclude[:ncon] == 0
        f = self.flex_id
        both = active & (flex[:, 0] == f) & (flex[:, 1] == f)
        pairs = [elem[both][np.abs(elem[both, 0] - elem[both, 1]) >= 2]]
        geom = c.geom[:ncon]
        n = self.n_segments
        for side in (0, 1):
            hit = active & (geom[:, side] == self.end_geom) & (flex[:, 1 - side] == f)
            other = elem[hit, 1 - side]
            other = other[other <= n - 2]
            pairs.append(np.stack([np.full(len(other), n), other], axis=1))
        return np.concatenate(pairs).astype(int)

    def self_contact(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        """Whether the rope touches itself: an active contact between two elements i, j with
        |i - j| >= 2 (sharing no vertex), or between the end weight and an element
        j <= n - 2 (counting the weight as element n).
        """
        return self._contact_span(data)[0] >= 0

    def self_contact_span(
        self, model: mujoco.MjModel, data: mujoco.MjData
    ) -> tuple[int, int] | None:
        """The first and last vertex of the elements in self-contact (element i joins
        vertices i and i + 1; the end weight is vertex n), or None if the rope touches
        nothing of itself."""
        lo, hi = self._contact_span(data)
        if lo < 0:
            return None
        return lo, min(hi + 1, self.n_segments)

    def _contact_span(self, data: mujoco.MjData) -> tuple[int, int]:
        """The lowest and highest element of :meth:`self_contact_elements` ((-1, -1): none),
        by the compiled scan (:data:`COMPILED`) or from the NumPy one."""
        ncon = data.ncon
        if ncon == 0:
            return -1, -1
        if COMPILED:
            from flyknot_sim.contact_kernel import self_contact_span  # numba: compiled on demand

            c = data.contact
            lo, hi = self_contact_span(
                c.flex, c.elem, c.geom, c.exclude, ncon, self.flex_id, self.end_geom,
                self.n_segments,
            )  # fmt: skip
            return int(lo), int(hi)
        pairs = self.self_contact_elements(data)
        if len(pairs) == 0:
            return -1, -1
        return int(pairs.min()), int(pairs.max())

    # -- state write ---------------------------------------------------------------------
    def set_hanging(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        sway_angle: float = 0.0,
        sway_azimuth: float = 0.0,
        sway_rate: float = 0.0,
    ) -> None:
        """Place the rope hanging from the anchor's current pose, at rest or swinging.

        Reads the hold sites' world positions from ``data`` (call ``mj_kinematics`` after
        moving the anchor first). Vertices 0 and 1 go to the hold sites; the rest continue
        straight, tilted by ``sway_angle`` from straight down toward ``sway_azimuth`` (see
        :func:`sway_direction`), and turn about vertex 1 at ``sway_rate``: vertex k >= 2 moves
        at v_k = (k - 1) l sway_rate dd/d(angle) [m/s]. Twist angles, the rod's transported
        reference frames (``mjData.plastic``) and the rope's warm start are zeroed; then
        ``mj_forward`` runs.

        Args:
            model: The model bound to.
            data: Its data.
            sway_angle: Tilt from vertical [rad], in [0, pi/2).
            sway_azimuth: Direction of the tilt about world z [rad].
            sway_rate: Rate of change of the tilt [rad/s] (0: at rest).

        Raises:
            ConfigError: ``sway_angle`` outside [0, pi/2) or a non-finite ``sway_rate``.
        """
        if not (0.0 <= sway_angle < math.pi / 2):
            raise ConfigError("sway_angle", f"must lie in [0, pi/2) rad, got {sway_angle!r}")
        if not math.isfinite(sway_rate):
            raise ConfigError("sway_rate", f"must be a finite number, got {sway_rate!r}")
        p0 = data.site_xpos[self.hold_sites[0]]
        p1 = data.site_xpos[self.hold_sites[1]]
        x = hanging_vertices(p0, p1, sway_direction(sway_angle, sway_azimuth), self.n_segments)
        self.set_vertices(model, data, x)
        if sway_rate:
            ca, sa = math.cos(sway_angle), math.sin(sway_angle)
            dd = np.array([ca * math.cos(sway_azimuth), ca * math.sin(sway_azimuth), sa])
            arm = np.linalg.norm(x[2:] - x[1], axis=1)
            v = np.zeros_like(x)
            v[2:] = sway_rate * arm[:, None] * dd
            data.qvel[self.vert_dof] = v
            mujoco.mj_forward(model, data)

    def vertex_velocities(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Vertex world velocities, held end first, shape (n + 1, 3) [m/s] (a copy)."""
        return data.qvel[self.vert_dof].copy()

    def set_vertices(self, model: mujoco.MjModel, data: mujoco.MjData, x: np.ndarray) -> None:
        """Put the rope's vertices at ``x`` at rest, then run ``mj_forward``.

        Zeroes the rope's velocities, twist angles, warm start and the rod's transported
        reference frames (``mjData.plastic``; MuJoCo re-derives them from the new shape). The
        hold equalities are not enforced here: vertices 0 and 1 should be at the hold sites.

        Args:
            model: The model bound to.
            data: Its data.
            x: Vertex positions, shape (n + 1, 3) [m], held end first.

        Raises:
            ConfigError: Wrong shape or non-finite values.
        """
        x = np.asarray(x, dtype=float)
        if x.shape != (self.n_vert, 3) or not np.all(np.isfinite(x)):
            raise ConfigError(
                "x", f"must be finite with shape ({self.n_vert}, 3), got shape {x.shape}"
            )
        data.qpos[self.vert_qpos] = x - self.body_pos0
        data.qvel[self.vert_dof] = 0.0
        data.qacc_warmstart[self.vert_dof] = 0.0
        if len(self.twist_qpos):
            data.qpos[self.twist_qpos] = 0.0
            data.qvel[self.twist_dof] = 0.0
            data.qacc_warmstart[self.twist_dof] = 0.0
        data.plastic[self.plastic] = 0.0
        mujoco.mj_forward(model, data)

"""Air drag on the rope: cylinder cross-flow and skin friction per segment, sphere on the end.

MuJoCo's fluid models act on bodies through their geoms or inertia boxes; the rope's vertex
bodies are point masses with no geoms (the flex draws the capsules), so neither model applies.
The drag is computed here, vectorised over the segments, and applied as a passive force on the
vertices' world-axis slides (``qfrc_applied``) before every step.

Per segment k (length l_k, diameter D, unit tangent t_k, velocity v_k = the mean of its two
vertices' velocities relative to still air):

* cross-flow:   F_n = -1/2 rho C_D(Re_n) D l_k |v_n| v_n,  v_n = v_k - (v_k . t_k) t_k,
  Re_n = |v_n| D / nu (independence principle for yawed cylinders: only the normal component
  of the flow makes pressure drag; Hoerner, "Fluid-Dynamic Drag", 1965, ch. 3);
* skin friction: F_t = -1/2 rho C_t pi D l_k |v_t| v_t,  v_t = (v_k . t_k) t_k;

each split equally onto the segment's two vertices. The end weight (a sphere of radius R):
F_s = -1/2 rho C_D,s(Re_s) pi R^2 |v| v.

Constants of air at 20 degC and 1 atm: rho = 1.204 kg/m^3, nu = 1.516e-5 m^2/s (engineering
tables, e.g. F. M. White, "Fluid Mechanics", 7th ed., 2011, table A.2).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from flyknot.errors import check_nonnegative, check_positive

__all__ = [
    "AIR_DENSITY",
    "AIR_KINEMATIC_VISCOSITY",
    "DRAG_HOLD_S",
    "AeroParams",
    "RopeDrag",
    "compiled_drag_matches",
    "cylinder_cd",
    "rope_drag_forces",
    "sphere_cd",
]

AIR_DENSITY = 1.204
"""Density of air at 20 degC, 101.325 kPa [kg/m^3] (White, "Fluid Mechanics", table A.2)."""

AIR_KINEMATIC_VISCOSITY = 1.516e-5
"""Kinematic viscosity of air at 20 degC [m^2/s] (White, "Fluid Mechanics", table A.2)."""

TANGENTIAL_CT = 0.01
"""Skin-friction coefficient of a rope in axial flow, on the wetted area pi D l [-].

Published values bracket 0.008-0.03: fly lines meet ~50x less axial than normal drag at equal
speed (C_t ~ 0.008); Hoerner ("Fluid-Dynamic Drag", 1965) gives ~0.01-0.02 for cables (not
re-checked here); mooring-line codes (MoorDyn's input docs) define C_t on the same area. The
term is small beside the cross-flow drag in a throw and in a swing."""

_RE_FLOOR = 1e-6  # keeps Re^(-2/3) finite for a vertex at rest (its force is ~0 anyway)


def cylinder_cd(re: np.ndarray) -> np.ndarray:
    """Drag coefficient of a smooth circular cylinder in cross-flow, C_D(Re).

    C_D = 1 + 10 Re^(-2/3), White's curve fit for 1 <= Re <= 2e5 (F. M. White, "Viscous Fluid
    Flow", 2nd ed., 1991, curve fits for the cylinder and the sphere; within ~10 % of the
    measured curve, and within ~10 % of White's longer fit quoted in Nellis & Klein,
    "Introduction to Engineering Heat Transfer", 2021, over Re 1-1e4). Below Re = 1 it is
    extended (Re here is clamped to >= 1e-6); a rope there carries a negligible force. The
    ropes meet Re ~ 9 (7 mm at 2 cm/s) to ~8300 (25 mm at 5 m/s).

    Args:
        re: Reynolds numbers based on the diameter, shape (...,) [-].

    Returns:
        C_D, same shape [-].
    """
    re = np.maximum(np.asarray(re, dtype=float), _RE_FLOOR)
    return 1.0 + 10.0 * re ** (-2.0 / 3.0)


def sphere_cd(re: np.ndarray) -> np.ndarray:
    """Drag coefficient of a sphere, C_D(Re) = 24/Re + 6/(1 + sqrt(Re)) + 0.4.

    White's curve fit for 0 <= Re <= 2e5 (F. M. White, "Viscous Fluid Flow", 2nd ed., 1991;
    within ~10 %).

    Args:
        re: Reynolds numbers based on the diameter, shape (...,) [-].

    Returns:
        C_D, same shape [-].
    """
    re = np.maximum(np.asarray(re, dtype=float), _RE_FLOOR)
    return 24.0 / re + 6.0 / (1.0 + np.sqrt(re)) + 0.4


@dataclass(frozen=True)
class AeroParams:
    """Air drag on a rope.

    Attributes:
        enabled: Apply drag at all.
        air_density: rho [kg/m^3].
        air_viscosity: Kinematic viscosity nu [m^2/s].
        tangential_ct: Skin-friction coefficient on the area pi D l [-].
        cd: Fixed cross-flow drag coefficient [-] replacing the C_D(Re) curve, or None.
    """

    enabled: bool = True
    air_density: float = AIR_DENSITY
    air_viscosity: float = AIR_KINEMATIC_VISCOSITY
    tangential_ct: float = TANGENTIAL_CT
    cd: float | None = None

    def __post_init__(self) -> None:
        check_positive("air_density", self.air_density)
        check_positive("air_viscosity", self.air_viscosity)
        check_nonnegative("tangential_ct", self.tangential_ct)
        if self.cd is not None:
            check_positive("cd", self.cd)


def rope_drag_forces(
    x: np.ndarray,
    v: np.ndarray,
    diameter: float,
    end_radius: float,
    params: AeroParams,
) -> np.ndarray:
    """Drag forces on the rope's vertices (module docstring for the formulas).

    Args:
        x: Vertex positions, held end first, shape (n + 1, 3) [m].
        v: Vertex velocities relative to still air, shape (n + 1, 3) [m/s].
        diameter: Rope diameter D [m].
        end_radius: Radius of the end-weight sphere on the last vertex [m] (0: none).
        params: Air and coefficients.

    Returns:
        Forces on the vertices, shape (n + 1, 3) [N].
    """
    rho = params.air_density
    seg = x[1:] - x[:-1]
    length = np.sqrt(np.einsum("ij,ij->i", seg, seg))
    t = seg / np.maximum(length, 1e-12)[:, None]
    vs = 0.5 * (v[1:] + v[:-1])
    vt_mag = np.einsum("ij,ij->i", vs, t)
    vt = vt_mag[:, None] * t
    vn = vs - vt
    vn_mag = np.sqrt(np.einsum("ij,ij->i", vn, vn))
    cd = _cross_flow_cd(vn_mag, diameter, params)
    kn = (0.5 * rho * diameter) * length * cd * vn_mag
    kt = (0.5 * rho * params.tangential_ct * math.pi * diameter) * length * np.abs(vt_mag)
    f_seg = -0.5 * (kn[:, None] * vn + kt[:, None] * vt)
    f = np.zeros_like(x)
    f[1:] += f_seg
    f[:-1] += f_seg
    if end_radius > 0:
        f[-1] -= _end_coef(v[-1], end_radius, params) * v[-1]
    return f


def _cross_flow_cd(vn_mag: np.ndarray, diameter: float, params: AeroParams):
    """C_D per segment: ``params.cd``, else cylinder_cd(Re_n) inlined (hot path)."""
    if params.cd is not None:
        return params.cd
    re = np.maximum(vn_mag * (diameter / params.air_viscosity), _RE_FLOOR)
    return 1.0 + 10.0 * re ** (-2.0 / 3.0)


def _end_coef(ve: np.ndarray, end_radius: float, params: AeroParams) -> float:
    """1/2 rho C_D,s(Re_s) pi R^2 |v| of the end sphere [kg/s] (sphere_cd inlined)."""
    speed = math.sqrt(float(ve @ ve))
    re_s = max(speed * 2 * end_radius / params.air_viscosity, _RE_FLOOR)
    cds = 24.0 / re_s + 6.0 / (1.0 + math.sqrt(re_s)) + 0.4
    return 0.5 * params.air_density * cds * math.pi * end_radius**2 * speed


DRAG_HOLD_S = 0.004
"""How long a computed drag force is held [s]: the robot's command tick. The drag's rate
constant is at most ~4 1/s (the lightest rope, 7 mm at 0.014 kg/m, at 5 m/s), so the force
changes by < 2 % within a hold; recomputing it every 1 ms step cost a third of the step."""


class RopeDrag:
    """Applies :func:`rope_drag_forces` to a bound rope.

    The vertices are bodies on world-axis slides, so a world force on a vertex is its three
    slide forces; they go to ``qfrc_applied`` (explicit: the drag's rate constant, at most ~4
    1/s, is far below 1 / dt) and stay there until the next :meth:`apply` (callers recompute
    every :data:`DRAG_HOLD_S`).
    """

    def __init__(self, rope, params: AeroParams, end_radius: float | None = None):
        """Bind to ``rope`` (a :class:`flyknot_sim.rope_handle.BoundRope`)."""
        self.rope = rope
        self.params = params
        self.diameter = rope.params.diameter
        self.end_radius = rope.params.end_radius if end_radius is None else end_radius

    def apply(self, data) -> None:
        """Write the drag of ``data``'s current state into ``data.qfrc_applied``: computed by
        the compiled kernel when it matches :func:`rope_drag_forces` bit for bit on this
        machine (:func:`compiled_drag_matches`), else by that function."""
        if not self.params.enabled:
            return
        r = self.rope
        x = data.qpos[r.vert_qpos] + r.body_pos0
        v = (data.qvel[r.vert_dof]).reshape(-1, 3)
        if COMPILED and compiled_drag_matches():
            f = np.empty_like(x)
            _drag_compiled(x, v, self.diameter, self.end_radius, self.params, f)
        else:
            f = rope_drag_forces(x, v, self.diameter, self.end_radius, self.params)
        data.qfrc_applied[r.vert_dof] = f


COMPILED = True
"""Use the compiled drag (:mod:`flyknot_sim.aero_kernel`) where it matches; False: NumPy."""


def _drag_compiled(x, v, diameter, end_radius, params: AeroParams, out: np.ndarray) -> None:
    """:func:`rope_drag_forces` by the compiled kernels, into ``out``; the power in C_D(Re)
    and the end weight's speed by NumPy, as there."""
    from flyknot_sim.aero_kernel import drag_into, segment_flow

    rho = params.air_density
    flow = np.empty((x.shape[0] - 1, 9))
    segment_flow(x, v, flow)
    cd = np.broadcast_to(_cross_flow_cd(flow[:, 1], diameter, params), flow.shape[:1])
    ve = v[-1]
    end_coef = _end_coef(ve, end_radius, params) if end_radius > 0 else 0.0
    c_n = 0.5 * rho * diameter
    c_t = 0.5 * rho * params.tangential_ct * math.pi * diameter
    drag_into(flow, cd, c_n, c_t, np.ascontiguousarray(ve), end_coef, out)


@functools.cache
def compiled_drag_matches(n_states: int = 300) -> bool:
    """Whether the compiled drag equals :func:`rope_drag_forces` bit for bit on ``n_states``
    random rope states (2-60 segments, speeds from rest to 5 m/s, with and without an end
    weight and a fixed C_D); checked once per process."""
    rng = np.random.default_rng(0)
    for k in range(n_states):
        n = int(rng.integers(2, 61))
        x = np.cumsum(0.03 * rng.standard_normal((n + 1, 3)), axis=0)
        v = rng.standard_normal((n + 1, 3)) * (0.0 if k % 10 == 0 else 5.0 * rng.random())
        params = AeroParams(cd=None if k % 3 else 1.2)
        end_radius = 0.01 * (k % 2)
        out = np.empty_like(x)
        _drag_compiled(x, v, 0.009, end_radius, params, out)
        ref = rope_drag_forces(x, v, 0.009, end_radius, params)
        if not np.array_equal(out.view(np.int64), ref.view(np.int64)):
            return False
    return True

"""The rope table of the simulated lab: the paper's ropes and the simulation options.

Rope ids, names, sizes and material data live in ``assets/ropes.toml`` (``[[rope]]`` entries
taking their material's values from ``[materials.<material>]``, see :func:`load_rope_table`);
simulation options in its ``[simulation]`` table (:func:`load_sim_settings`). A user's own
ropes and the one resolver of rope ids and names are in :mod:`flyknot_sim.rope_custom`; the
MuJoCo rope built from a :class:`RopeParams` in :mod:`flyknot_sim.rope`.
"""

from __future__ import annotations

import functools
import math
import tomllib as _toml
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from flyknot.constants import ROPE_TABLE
from flyknot.errors import ConfigError, check_choice, check_positive
from flyknot_sim.rope_fields import MATERIALS, REQUIRED, ROPE_FIELDS, ByMaterial, rope_dataclass

__all__ = [
    "CLEARANCE_EXTRA",
    "CONES",
    "INTEGRATORS",
    "MATERIALS",
    "SELFCOLLIDE_MODES",
    "SOLVERS",
    "STEEL_DENSITY",
    "STRETCH_IMPEDANCE",
    "RopeParams",
    "SimSettings",
    "get_rope",
    "load_rope_table",
    "load_sim_settings",
    "parse_rope_table",
]

STEEL_DENSITY = 7850.0
"""Density of carbon steel [kg/m^3] (e.g. ASM Handbook vol. 1), for the end-weight sphere."""

STRETCH_IMPEDANCE = 0.9
"""Impedance d of a stretching rope's edge equality (solimp d0 = d_width, MuJoCo's default d0):
constant, so the edge is linear. The edge's stiffness and damping do not depend on it (k scales
with 1 - d, :attr:`RopeParams.stretch_spring`; a hung tube's stretch and stretch mode are the
same at d 0.5, 0.9 and 0.99 within 3 %, docs/rope-model.md)."""

CLEARANCE_EXTRA = 1e-3
"""Gap between the anchor point and the first capsule's cap [m]; clearance = radius + this."""

SELFCOLLIDE_MODES = ("auto", "sap", "bvh", "narrow")
INTEGRATORS = ("discrete",)
SOLVERS = ("Newton", "CG")
CONES = ("pyramidal", "elliptic")


# ----------------------------------------------------------------------------------------
# parameters
# ----------------------------------------------------------------------------------------
@rope_dataclass
class RopeParams:
    """One rope of the paper's table plus the material and discretisation we chose for it, or
    a user's own rope (:func:`~flyknot_sim.rope_custom.load_custom_ropes`).

    Its fields, their units, valid values and defaults are declared once, in
    :data:`flyknot_sim.rope_fields.ROPE_FIELDS` (listed below); every field is checked on
    construction (:class:`ConfigError` naming the field and its valid values).
    """

    def __post_init__(self) -> None:
        if isinstance(self.id, str):
            if self.id != self.name:
                raise ConfigError(
                    "id", f"a custom rope's id is its name {self.name!r}, got {self.id!r}"
                )
        elif isinstance(self.id, bool) or not isinstance(self.id, int) or self.id < 1:
            raise ConfigError("id", f"must be an integer >= 1, got {self.id!r}")
        for f in ROPE_FIELDS:
            f.check(getattr(self, f.name))
        if self.stretch_spring > 1 / (2 * self.timestep * STRETCH_IMPEDANCE) ** 2:
            e_max = self.stretch_modulus / (
                self.stretch_spring * (2 * self.timestep * STRETCH_IMPEDANCE) ** 2
            )
            raise ConfigError(
                "stretch_modulus",
                f"{self.stretch_modulus:.4g} Pa makes an edge's spring faster than MuJoCo's soft "
                f"constraint follows at the rope's {self.timestep:.4g} s step (its time "
                f"constant under twice the step); use at most {e_max:.4g} Pa, or 0 for an "
                "inextensible rope",
            )
        if self.length / self.segments <= self.diameter:
            n_max = max(1, int(self.length // self.diameter))
            while n_max > 1 and self.length / n_max <= self.diameter:
                n_max -= 1
            raise ConfigError(
                "segments",
                f"segment length {self.length / self.segments:.4g} m must exceed the diameter "
                f"{self.diameter:.4g} m (elements sharing no vertex would touch at rest); "
                f"use at most {n_max} segments",
            )

    @property
    def friction_triple(self) -> list[float]:
        """MuJoCo's (sliding, torsional [m], rolling [m]) friction of the rope's contacts."""
        tors = self.torsional_friction
        if tors is None:
            tors = 2.0 / 3.0 * self.friction * self.radius
        return [self.friction, tors, 0.0001]

    @property
    def custom(self) -> bool:
        """A user's rope (from a ropes file; its id is its name), not one of the paper's."""
        return isinstance(self.id, str)

    def to_dict(self) -> dict[str, Any]:
        """The parameters as plain data; a field with a default only when it differs from it
        (``cd`` only when set), so that a record reads as before the field existed."""
        return {
            f.name: getattr(self, f.name)
            for f in ROPE_FIELDS
            if f.default is REQUIRED or getattr(self, f.name) != f.default
        }

    @property
    def n_segments(self) -> int:
        """Number of flex elements (alias of ``segments``)."""
        return self.segments

    @property
    def radius(self) -> float:
        """Capsule radius r = diameter / 2 [m]."""
        return self.diameter / 2

    @property
    def segment_length(self) -> float:
        """Rest length of one element, length / segments [m]."""
        return self.length / self.segments

    @property
    def mass(self) -> float:
        """Rope mass without the end weight, density * length [kg]."""
        return self.density * self.length

    @property
    def bending_stiffness(self) -> float:
        """EI = E pi r^4 / 4 [N m^2]."""
        return self.bend_modulus * math.pi * self.radius**4 / 4

    @property
    def axial_stiffness(self) -> float:
        """EA = E_s pi r^2 [N] (E_s the ``stretch_modulus``; 0: inextensible)."""
        return self.stretch_modulus * math.pi * self.radius**2

    @property
    def stretch_spring(self) -> float:
        """k [1/s^2] of the edge equality's direct solref (-k, -tau k) that makes every interior
        edge a spring of EA / l (0: inextensible; :func:`flyknot_sim.rope.stretch_solref`).

        At rest a soft equality row's force is f = k r / ((1 - d) A) for a stretch r (MuJoCo's
        R = (1 - d) / d A, measured on MuJoCo 4.0.0: ``tests/test_rope_stretch.py``), A = 2 /
        (rho l) for an edge between two vertices of mass rho l, d = :data:`STRETCH_IMPEDANCE`:

            k = (EA / l) (1 - d) 2 / (rho l).
        """
        ell = self.segment_length
        return self.axial_stiffness / ell * (1 - STRETCH_IMPEDANCE) * 2 / (self.density * ell)

    @property
    def frictional_couple(self) -> float:
        """Grosberg's frictional couple of bending M_0 = (HB / B) EI [N m]."""
        return self.bend_hysteresis * self.bending_stiffness

    @property
    def link_friction_arm(self) -> float:
        """The links' frictional couple per newton of tension, friction * r = mu r [m] (r the
        ``link_friction_radius``; 0: no link friction, the default)."""
        return self.friction * self.link_friction_radius

    @property
    def torsional_stiffness(self) -> float:
        """GJ = G pi r^4 / 2 [N m^2] (G = E / 2 when ``shear_modulus`` is 0)."""
        g = self.shear_modulus if self.shear_modulus > 0 else self.bend_modulus / 2
        return g * math.pi * self.radius**4 / 2

    @property
    def end_radius(self) -> float:
        """Radius of the end-weight sphere [m]: a steel sphere of ``end_mass``, at least r.

        r_end = max(r, (3 m_end / (4 pi rho_steel))^(1/3)).
        """
        r_steel = (3 * self.end_mass / (4 * math.pi * STEEL_DENSITY)) ** (1 / 3)
        return max(self.radius, r_steel)

    @property
    def clearance(self) -> float:
        """Distance from the anchor point to the held end (vertex 0) along the axis [m]."""
        return self.radius + CLEARANCE_EXTRA


_ROPE_FIELDS = tuple(f.name for f in ROPE_FIELDS)
_MATERIAL_FIELDS = tuple(f.name for f in ROPE_FIELDS if f.by_material is not ByMaterial.NO)


@dataclass(frozen=True)
class SimSettings:
    """Simulation options for scenes with ropes (the ``[simulation]`` table).

    Attributes:
        integrator: MuJoCo integrator; only ``discrete`` integrates rod elasticity implicitly.
        solver: Constraint solver, ``Newton`` or ``CG`` (PGS does not support flex).
        iterations: Maximum solver iterations.
        ls_iterations: Maximum line-search iterations per solver iteration.
        tolerance: Solver early-termination tolerance.
        edge_timeconst: solref time constant of the edge and hold equalities [s].
        contact_timeconst: solref time constant of rope contacts [s].
        contact_dampratio: solref damping ratio of rope contacts [-].
        contact_solimp: solimp (d0, d_width, width) of rope contacts: impedance at zero and at
            ``width`` [m] penetration.
        refsafe: MuJoCo's refsafe flag; under ``discrete`` it replaces contact rows stiffer than
            the step can resolve (time constant < timestep) by the stiffest resolvable one.
        selfcollide: Flex self-collision midphase, one of ``auto``, ``sap``, ``bvh``,
            ``narrow``.
        cone: MuJoCo's friction cone, ``pyramidal`` or ``elliptic``.
        impratio: MuJoCo's ratio of frictional to normal constraint impedance [-] (> 0).
    """

    integrator: str = "discrete"
    solver: str = "Newton"
    iterations: int = 100
    ls_iterations: int = 50
    tolerance: float = 1e-8
    edge_timeconst: float = 1e-4
    contact_timeconst: float = 0.001
    contact_dampratio: float = 1.0
    contact_solimp: tuple[float, float, float] = (0.9, 0.95, 0.001)
    refsafe: bool = True
    selfcollide: str = "auto"
    cone: str = "pyramidal"
    impratio: float = 1.0

    def __post_init__(self) -> None:
        check_choice("integrator", self.integrator, INTEGRATORS)
        check_choice("cone", self.cone, CONES)
        check_positive("impratio", self.impratio)
        check_choice("solver", self.solver, SOLVERS)
        check_choice("selfcollide", self.selfcollide, SELFCOLLIDE_MODES)
        for f in ("iterations", "ls_iterations"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f, f"must be an integer >= 1, got {v!r}")
        for f in ("tolerance", "edge_timeconst", "contact_timeconst", "contact_dampratio"):
            check_positive(f, getattr(self, f))
        imp = tuple(self.contact_solimp)
        if len(imp) != 3 or not all(isinstance(v, (int, float)) for v in imp):
            raise ConfigError("contact_solimp", f"must be 3 numbers, got {self.contact_solimp!r}")
        if not (0 < imp[0] < 1 and 0 < imp[1] < 1 and imp[2] > 0):
            raise ConfigError(
                "contact_solimp", f"need 0 < d0, d_width < 1 and width > 0, got {imp!r}"
            )
        object.__setattr__(self, "contact_solimp", tuple(float(v) for v in imp))
        if not isinstance(self.refsafe, bool):
            raise ConfigError("refsafe", f"must be true or false, got {self.refsafe!r}")

    def to_dict(self) -> dict[str, Any]:
        """The settings as plain data (``cone`` and ``impratio`` only when not MuJoCo's
        defaults, so that records of tables without them read as before they existed)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, default in (("cone", "pyramidal"), ("impratio", 1.0)):
            if d[k] == default:
                del d[k]
        return d


_SIM_FIELDS = tuple(f.name for f in fields(SimSettings))


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            return _toml.load(fh)
    except FileNotFoundError as exc:
        raise ConfigError("rope table", f"file not found: {path}") from exc
    except _toml.TOMLDecodeError as exc:
        raise ConfigError("rope table", f"{path}: {exc}") from exc


def _check_keys(where: str, table: Mapping[str, Any], allowed: Sequence[str]) -> None:
    for key in table:
        if key not in allowed:
            raise ConfigError(f"{where}.{key}", "unknown key", allowed)


def parse_rope_table(doc: Mapping[str, Any]) -> dict[int, RopeParams]:
    """Build the rope table from a parsed TOML document (see ``assets/ropes.toml``).

    Each ``[[rope]]`` entry gives the fields of :data:`~flyknot_sim.rope_fields.ROPE_FIELDS`
    (their units and valid values there): every field without a default, but those its
    material's ``[materials.<material>]`` gives (it may override them).

    Raises:
        ConfigError: Missing or unknown keys, bad values, duplicate ids.
    """
    materials = doc.get("materials", {})
    ropes = doc.get("rope")
    if not isinstance(ropes, list) or not ropes:
        raise ConfigError("rope", "the table needs at least one [[rope]] entry")
    out: dict[int, RopeParams] = {}
    for i, entry in enumerate(ropes):
        where = f"rope[{i}]"
        _check_keys(where, entry, _ROPE_FIELDS)
        material = entry.get("material")
        check_choice(f"{where}.material", material, MATERIALS)
        mat = materials.get(material, {})
        _check_keys(f"materials.{material}", mat, _MATERIAL_FIELDS)
        values = {**mat, **entry}
        missing = [f.name for f in ROPE_FIELDS if f.default is REQUIRED and f.name not in values]
        if missing:
            raise ConfigError(where, f"missing key(s) {', '.join(missing)}")
        p = RopeParams(**{f: values[f] for f in _ROPE_FIELDS if f in values})
        if p.custom:
            raise ConfigError(f"{where}.id", f"must be an integer >= 1, got {p.id!r}")
        if p.id in out:
            raise ConfigError(f"{where}.id", f"duplicate rope id {p.id}")
        out[p.id] = p
    return dict(sorted(out.items()))


def load_rope_table(path: str | Path = ROPE_TABLE) -> dict[int, RopeParams]:
    """Read the rope table (default ``assets/ropes.toml``): rope id -> :class:`RopeParams`."""
    return parse_rope_table(_read_toml(Path(path)))


def load_sim_settings(path: str | Path = ROPE_TABLE) -> SimSettings:
    """Read the ``[simulation]`` table of the rope file as :class:`SimSettings`."""
    sim = _read_toml(Path(path)).get("simulation", {})
    _check_keys("simulation", sim, _SIM_FIELDS)
    return SimSettings(**sim)


@functools.lru_cache(maxsize=1)
def _default_table() -> dict[int, RopeParams]:
    return load_rope_table(ROPE_TABLE)


def get_rope(rope_id: int) -> RopeParams:
    """The rope with this id from ``assets/ropes.toml``.

    Raises:
        ConfigError: Unknown id, listing the valid ids.
    """
    table = _default_table()
    if isinstance(rope_id, bool) or rope_id not in table:
        raise ConfigError("rope", f"unknown rope id {rope_id}", sorted(table))
    return table[rope_id]

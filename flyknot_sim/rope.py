"""The rope of the simulated lab: a MuJoCo 4 one-dimensional flex (discrete elastic rod).

Model (chosen by measurement, see ``docs/rope-model.md``):

* a ``dim=1`` flex of ``segments`` capsules built directly with ``MjSpec``: its vertices are
  point-mass bodies with three world-axis slide joints under the world body (MuJoCo's fast
  path for flex stiffness under Newton);
* stretching held by the flex edge equality (one constraint row per edge), bending by MuJoCo's
  discrete-elastic-rod elasticity (``young``, Rayleigh ``damping``), integrated implicitly by
  the ``discrete`` integrator. No per-edge twist hinges by default (bending is the same, the
  step ~40 % cheaper); ``add_rope(..., twist=True)`` builds MuJoCo's ``flexcomp`` with them;
* the held end: two ``connect`` equalities pin vertex 0 and vertex 1 to sites on the anchor
  body (a dynamic body moved by joints, e.g. the robot's ``link7``), so the first segment
  leaves along ``axis`` like a rope leaving a tube; the first segment may spin about its own
  axis (a held rope slips in its tube);
* the end weight: its mass is added to the last vertex body, plus a massless steel sphere there
  for contact;
* contact: flex self-collision (elements sharing a vertex never collide), with the floor and
  with every geom whose ``contype`` has bit 0 or bit 1 set (rope ``contype`` 1,
  ``conaffinity`` 3).

The held end (vertex 0) sits ``clearance = radius + 1 mm`` beyond the anchor point along the
axis, so the first capsule does not touch a tube that ends at the anchor (MuJoCo's body-pair
``exclude`` does not filter flex-geom contacts). Arc length, markers and :meth:`length` are
measured from vertex 0.

Rope ids, names, sizes and material data live in ``assets/ropes.toml`` (see
:func:`load_rope_table`); simulation options in its ``[simulation]`` table
(:func:`load_sim_settings`, :func:`configure_options`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from flyknot.constants import MARKER_SPACING, N_MARKERS, ROPE_TABLE
from flyknot.errors import ConfigError, check_choice, check_nonnegative, check_positive
from flyknot.geometry import quat_from_x_to

try:  # Python >= 3.11
    import tomllib as _toml
except ModuleNotFoundError:  # pragma: no cover - Python 3.10 needs the tomli backport
    import tomli as _toml  # type: ignore[no-redef]

__all__ = [
    "MATERIALS",
    "STEEL_DENSITY",
    "BoundRope",
    "RopeHandle",
    "RopeParams",
    "SimSettings",
    "add_rope",
    "configure_options",
    "get_rope",
    "hanging_vertices",
    "load_custom_ropes",
    "load_rope_table",
    "load_sim_settings",
    "marker_arclengths",
    "parse_custom_ropes",
    "parse_rope_table",
    "points_at_arclength",
    "polyline_length",
    "resolve_rope",
    "rope_choices",
    "rope_record",
    "sway_direction",
]

MATERIALS = ("cotton", "steel", "latex")
"""Materials of the paper's ropes."""

STEEL_DENSITY = 7850.0
"""Density of carbon steel [kg/m^3] (e.g. ASM Handbook vol. 1), for the end-weight sphere."""

CLEARANCE_EXTRA = 1e-3
"""Gap between the anchor point and the first capsule's cap [m]; clearance = radius + this."""

SELFCOLLIDE_MODES = ("auto", "sap", "bvh", "narrow")
INTEGRATORS = ("discrete",)
SOLVERS = ("Newton", "CG")

ROPE_CONTYPE = 1
"""Rope contype: bit 0, so geoms with conaffinity bit 0 (floor, robot links) touch it."""
ROPE_CONAFFINITY = 3
"""Rope conaffinity: bits 0 and 1, so geoms with contype 1 (floor) or 2 (robot) touch it."""

_RGBA = {
    "cotton": (0.92, 0.88, 0.78, 1.0),
    "steel": (0.55, 0.57, 0.6, 1.0),
    "latex": (0.93, 0.62, 0.25, 1.0),
}


# ----------------------------------------------------------------------------------------
# parameters
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RopeParams:
    """One rope of the paper's table plus the material and discretisation we chose for it, or
    a user's own rope (:func:`load_custom_ropes`).

    Attributes:
        id: Rope id of the paper (1..7), or, for a custom rope, its name (a string).
        name: Name in the paper's table (or the custom rope's name).
        material: One of :data:`MATERIALS`.
        diameter: Rope diameter [m]; the flex capsule radius is half of it.
        density: Linear density [kg/m].
        end_mass: Mass of the weight at the free end [kg] (separate from the rope's mass).
        length: Rope length [m].
        bend_modulus: Effective Young's modulus E of a solid circular section of the rope's
            diameter [Pa]; bending stiffness EI = E pi r^4 / 4 [N m^2].
        shear_modulus: Effective shear modulus G [Pa]; torsional stiffness GJ = G pi r^4 / 2.
            0 lets MuJoCo use E / (2 (1 + nu)) with nu = 0.
        damping: Rayleigh damping time of the bending/torsion stiffness [s].
        friction: Sliding friction coefficient of rope-rope and rope-geom contact [-].
        segments: Number of flex elements (capsules); length / segments > diameter.
        timestep: Largest simulation step this rope was validated at [s].
        cd: Fixed cross-flow drag coefficient [-] replacing the C_D(Re) curve of
            :mod:`flyknot_sim.aero` (the labs pass it on as ``AeroParams.cd``), or None.
        condim: Contact dimensionality of the rope's contacts: 3 (sliding friction, the
            default) or 4 (plus torsional friction about the contact normal).
        torsional_friction: MuJoCo's torsional friction coefficient [m] (the moment about the
            normal is this times the normal force) when ``condim`` is 4; None:
            (2/3) friction r, the moment of uniform pressure over a contact disc of radius a
            = r (K. L. Johnson, "Contact Mechanics", 1985, sec. 7.4; a soft cord flattens to
            a patch about its radius wide -- an upper bound, no measured value found).
    """

    id: int | str
    name: str
    material: str
    diameter: float
    density: float
    end_mass: float
    length: float
    bend_modulus: float
    shear_modulus: float
    damping: float
    friction: float
    segments: int
    timestep: float
    cd: float | None = None
    condim: int = 3
    torsional_friction: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.id, str):
            if self.id != self.name:
                raise ConfigError(
                    "id", f"a custom rope's id is its name {self.name!r}, got {self.id!r}"
                )
        elif isinstance(self.id, bool) or not isinstance(self.id, int) or self.id < 1:
            raise ConfigError("id", f"must be an integer >= 1, got {self.id!r}")
        if not isinstance(self.name, str) or not self.name.strip():
            raise ConfigError("name", f"must be a non-empty string, got {self.name!r}")
        check_choice("material", self.material, MATERIALS)
        for f in ("diameter", "density", "length", "friction", "timestep"):
            check_positive(f, getattr(self, f))
        for f in ("end_mass", "bend_modulus", "shear_modulus", "damping"):
            check_nonnegative(f, getattr(self, f))
        if isinstance(self.segments, bool) or not isinstance(self.segments, int):
            raise ConfigError("segments", f"must be an integer, got {self.segments!r}")
        if self.segments < 2:
            raise ConfigError("segments", f"must be >= 2, got {self.segments}")
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
        if self.cd is not None:
            check_positive("cd", self.cd)
        check_choice("condim", self.condim, (3, 4))
        if self.torsional_friction is not None:
            check_nonnegative("torsional_friction", self.torsional_friction)

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
        """The parameters as plain data (``cd`` only when set, so that the paper's ropes read
        as before it existed)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, default in (("cd", None), ("condim", 3), ("torsional_friction", None)):
            if d[k] == default:
                del d[k]
        return d

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


_ROPE_FIELDS = tuple(f.name for f in fields(RopeParams))
_OPTIONAL_ROPE_FIELDS = ("cd", "condim", "torsional_friction")
_MATERIAL_FIELDS = ("bend_modulus", "shear_modulus", "damping", "friction")


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

    def __post_init__(self) -> None:
        check_choice("integrator", self.integrator, INTEGRATORS)
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

    Each ``[[rope]]`` entry takes its material's values from ``[materials.<material>]`` and
    may override any of them.

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
        missing = [f for f in _ROPE_FIELDS if f not in values and f not in _OPTIONAL_ROPE_FIELDS]
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


# ----------------------------------------------------------------------------------------
# custom ropes: a user's own ropes file
# ----------------------------------------------------------------------------------------
CUSTOM_REQUIRED = ("name", "material", "diameter", "density", "length", "end_weight")
"""Keys every ``[[rope]]`` table of a custom ropes file must have."""
CUSTOM_OPTIONAL = (
    "bend_modulus",
    "shear_modulus",
    "damping",
    "friction",
    "cd",
    "condim",
    "torsional_friction",
    "segments",
    "timestep",
)
"""Keys a custom rope may give; missing ones come from its material (or the defaults below)."""
CUSTOM_KEYS = CUSTOM_REQUIRED + CUSTOM_OPTIONAL

REFERENCE_DIAMETER = {"cotton": 0.009}
"""Diameter [m] at which a material's stiffness in ``assets/ropes.toml`` holds; for these
materials a custom rope's default E and G scale as (D_ref / D)^2, as the table's cotton ropes
do (free-slip fibre-bundle scaling, see the comments there). Other materials are not scaled:
steel (chain) has no stiffness; latex's values are those of 3/8" surgical tubing."""
DEFAULT_SEGMENTS = 30
"""Flex elements of a custom rope unless it says, capped so that length / segments > D."""
DEFAULT_TIMESTEP = 0.001
"""Simulation step of a custom rope unless it says [s] (the thin ropes' validated step)."""
MAX_TIMESTEP = 0.004
"""Largest simulation step of a custom rope [s]: the robot's 4 ms command tick."""


def _is_number(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _max_segments(length: float, diameter: float) -> int:
    """The most elements n with length / n > diameter (at least 1)."""
    n = max(1, int(length // diameter))
    while n > 1 and length / n <= diameter:
        n -= 1
    return n


@functools.lru_cache(maxsize=1)
def _material_defaults() -> dict[str, dict[str, float]]:
    mats = _read_toml(ROPE_TABLE).get("materials", {})
    return {m: dict(mats.get(m, {})) for m in MATERIALS}


def _custom_rope(entry: Mapping[str, Any], where: str, paper: Mapping[str, int]) -> RopeParams:
    if not isinstance(entry, Mapping):
        raise ConfigError(where, f"must be a table ([[rope]]), got {entry!r}")
    _check_keys(where, entry, CUSTOM_KEYS)
    missing = [k for k in CUSTOM_REQUIRED if k not in entry]
    if missing:
        raise ConfigError(where, f"missing key(s) {', '.join(missing)}")
    name = entry["name"]
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(f"{where}.name", f"must be a non-empty string, got {name!r}")
    if name.strip().isdigit():
        raise ConfigError(
            f"{where}.name", f"must not be a number (1..7 are the paper's rope ids), got {name!r}"
        )
    if name in paper:
        raise ConfigError(
            f"{where}.name",
            f"{name!r} is the paper's rope {paper[name]}; give your rope another name",
        )
    material = entry["material"]
    check_choice(f"{where}.material", material, MATERIALS)
    for k in ("diameter", "density", "length"):
        check_positive(f"{where}.{k}", entry[k])
    check_nonnegative(f"{where}.end_weight", entry["end_weight"])
    diameter, length = float(entry["diameter"]), float(entry["length"])
    span = MARKER_SPACING * (N_MARKERS - 1)
    if length <= span:
        raise ConfigError(
            f"{where}.length",
            f"must exceed {span:g} m (the {N_MARKERS} markers sit every {MARKER_SPACING:g} m "
            f"from the held end, the last one at the free end), got {entry['length']!r}",
        )
    n_max = _max_segments(length, diameter)
    if n_max < 2:
        raise ConfigError(
            f"{where}.diameter",
            f"must be less than half the length ({length / 2:g} m), got {entry['diameter']!r}",
        )
    mat = _material_defaults()[material]
    scale = (REFERENCE_DIAMETER[material] / diameter) ** 2 if material in REFERENCE_DIAMETER else 1
    values: dict[str, Any] = {
        "bend_modulus": mat["bend_modulus"] * scale,
        "shear_modulus": mat["shear_modulus"] * scale,
        "damping": mat["damping"],
        "friction": mat["friction"],
        "cd": None,
        "condim": 3,
        "torsional_friction": None,
        "segments": min(DEFAULT_SEGMENTS, n_max),
        "timestep": DEFAULT_TIMESTEP,
    }
    for k in CUSTOM_OPTIONAL:
        if k in entry:
            values[k] = entry[k]
    if "timestep" in entry:
        t = entry["timestep"]
        if not (_is_number(t) and 0 < t <= MAX_TIMESTEP):
            raise ConfigError(
                f"{where}.timestep",
                f"must lie in (0, {MAX_TIMESTEP:g}] s (the robot's command tick), got {t!r}",
            )
    try:
        p = RopeParams(
            id=name,
            name=name,
            material=material,
            diameter=diameter,
            density=entry["density"],
            end_mass=entry["end_weight"],
            length=length,
            **values,
        )
    except ConfigError as e:  # name the rope's field (RopeParams' own names but end_mass)
        field_name = "end_weight" if e.field == "end_mass" else e.field
        raise ConfigError(f"{where}.{field_name}", e.problem, e.choices) from None
    floats = ("density", "end_mass", "bend_modulus", "shear_modulus", "damping", "friction")
    as_float = {k: float(getattr(p, k)) for k in (*floats, "timestep")}
    if p.cd is not None:
        as_float["cd"] = float(p.cd)
    return replace(p, **as_float)


def parse_custom_ropes(doc: Mapping[str, Any]) -> dict[str, RopeParams]:
    """A user's ropes from a parsed TOML document: name -> :class:`RopeParams`.

    The document holds ``[[rope]]`` tables with the keys :data:`CUSTOM_REQUIRED` (``name``,
    ``material`` of :data:`MATERIALS`, ``diameter`` [m], ``density`` [kg/m], ``length`` [m],
    ``end_weight`` [kg]) and optionally :data:`CUSTOM_OPTIONAL` (``bend_modulus``,
    ``shear_modulus`` [Pa], ``damping`` [s], ``friction`` [-], ``cd`` [-], ``segments``,
    ``timestep`` [s]). Missing optional values: the material's in ``assets/ropes.toml`` (E and
    G of cotton scaled by (9 mm / D)^2, see :data:`REFERENCE_DIAMETER`), ``cd`` None (the
    Re-dependent curve), ``segments`` 30 capped so that length / segments > D, ``timestep``
    1 ms. Each rope's id is its name.

    Raises:
        ConfigError: Unknown key, missing key, bad value, duplicate name, or a name that is
            a number or one of the paper's rope names (the message names the field, e.g.
            ``rope[0].diameter``).
    """
    for k in doc:
        if k != "rope":
            raise ConfigError(k, "unknown top-level key of a ropes file", ["rope"])
    ropes = doc.get("rope")
    if not isinstance(ropes, list) or not ropes:
        raise ConfigError("rope", "the ropes file needs at least one [[rope]] table")
    paper = {p.name: rid for rid, p in _default_table().items()}
    out: dict[str, RopeParams] = {}
    for i, entry in enumerate(ropes):
        p = _custom_rope(entry, f"rope[{i}]", paper)
        if p.name in out:
            raise ConfigError(f"rope[{i}].name", f"duplicate rope name {p.name!r}")
        out[p.name] = p
    return out


def _ropes_path(path: str | Path) -> Path:
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError("ropes", f"no ropes file {str(path)!r}")
    return p.resolve()


@functools.lru_cache(maxsize=16)
def _load_custom_cached(path: str, mtime_ns: int, size: int) -> dict[str, RopeParams]:
    try:
        with open(path, "rb") as fh:
            doc = _toml.load(fh)
    except _toml.TOMLDecodeError as exc:
        raise ConfigError("ropes", f"{path}: not valid TOML: {exc}") from None
    return parse_custom_ropes(doc)


def load_custom_ropes(path: str | Path) -> dict[str, RopeParams]:
    """Read a user's ropes file (format: :func:`parse_custom_ropes`; example:
    ``assets/ropes_example.toml``): name -> :class:`RopeParams`. Cached until the file
    changes.

    Raises:
        ConfigError: No such file, not TOML, or a bad rope (see :func:`parse_custom_ropes`).
    """
    p = _ropes_path(path)
    st = p.stat()
    return dict(_load_custom_cached(str(p), st.st_mtime_ns, st.st_size))


def rope_choices(ropes_file: str | Path | None = None) -> list[object]:
    """Every valid rope: the paper's ids 1..7, then the quoted names of the paper's ropes and
    of the ropes in ``ropes_file`` (for error messages)."""
    table = _default_table()
    names = [p.name for p in table.values()]
    if ropes_file is not None:
        names += list(load_custom_ropes(ropes_file))
    return [*sorted(table), *(repr(n) for n in names)]


def resolve_rope(rope: int | str | RopeParams, ropes_file: str | Path | None = None) -> RopeParams:
    """The one place a rope id becomes a rope.

    Args:
        rope: A paper rope id 1..7 (an int or a string of digits, e.g. from the command
            line), a rope's name (the paper's, e.g. ``"shoe lace"``, or one of
            ``ropes_file``'s), or a :class:`RopeParams` (returned as is).
        ropes_file: A user's ropes file (:func:`load_custom_ropes`), or None.

    Raises:
        ConfigError: Unknown id or name (listing the valid ids and names), or a bad ropes
            file.
    """
    if isinstance(rope, RopeParams):
        return rope
    custom = load_custom_ropes(ropes_file) if ropes_file is not None else {}
    if isinstance(rope, str) and rope.strip().isdigit():
        rope = int(rope)
    if isinstance(rope, int) and not isinstance(rope, bool):
        table = _default_table()
        if rope in table:
            return table[rope]
        if not custom:
            get_rope(rope)  # the paper's message: unknown rope id, valid ids
        raise ConfigError("rope", f"unknown rope id {rope}", rope_choices(ropes_file))
    if isinstance(rope, str):
        if rope in custom:
            return custom[rope]
        for p in _default_table().values():
            if p.name == rope:
                return p
        hint = "" if ropes_file is not None else ", and no ropes file was given"
        raise ConfigError("rope", f"unknown rope name {rope!r}{hint}", rope_choices(ropes_file))
    raise ConfigError("rope", f"must be a rope id or name, got {rope!r}", rope_choices(ropes_file))


def rope_record(params: RopeParams, ropes_file: str | Path | None = None) -> dict[str, Any]:
    """What a record says about its rope: ``rope`` (the id: 1..7, or a custom rope's name)
    and ``rope_name``; for a custom rope also ``rope_params`` (all its parameters) and
    ``ropes_file``, so that the record describes the rope without the file."""
    out: dict[str, Any] = {"rope": params.id, "rope_name": params.name}
    if params.custom:
        out["rope_params"] = params.to_dict()
        out["ropes_file"] = None if ropes_file is None else str(ropes_file)
    return out


def configure_options(
    spec: mujoco.MjSpec, ropes: Iterable[RopeParams], settings: SimSettings | None = None
) -> None:
    """Set the spec's simulation options for these ropes.

    The timestep is the smallest of the ropes' validated timesteps; integrator, solver,
    iterations, line-search iterations and tolerance come from ``settings`` (default: the
    ``[simulation]`` table of ``assets/ropes.toml``). Noslip stays off (flex rejects it).

    Raises:
        ConfigError: ``ropes`` is empty.
    """
    ropes = list(ropes)
    if not ropes:
        raise ConfigError("ropes", "need at least one rope")
    s = load_sim_settings() if settings is None else settings
    opt = spec.option
    opt.timestep = min(r.timestep for r in ropes)
    opt.integrator = mujoco.mjtIntegrator.mjINT_DISCRETE
    opt.solver = getattr(mujoco.mjtSolver, f"mjSOL_{s.solver.upper()}")
    opt.iterations = s.iterations
    opt.ls_iterations = s.ls_iterations
    opt.tolerance = s.tolerance
    opt.noslip_iterations = 0
    if s.refsafe:
        opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    else:
        opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)


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
# building
# ----------------------------------------------------------------------------------------
def _flexcomp_xml(
    params: RopeParams, settings: SimSettings, pos: np.ndarray, quat: np.ndarray, name: str
) -> str:
    n, seg = params.segments, params.segment_length
    f = _fmt
    rgba = " ".join(f(c) for c in _RGBA[params.material])
    return (
        "<mujoco><worldbody>"
        f'<flexcomp name="{name}" type="grid" dim="1" count="{n + 1} 1 1" '
        f'spacing="{f(seg)} {f(seg)} {f(seg)}" radius="{f(params.radius)}" '
        f'mass="{f(params.mass)}" pos="{" ".join(f(x) for x in pos)}" '
        f'quat="{" ".join(f(x) for x in quat)}" rgba="{rgba}">'
        f'<edge equality="true" solref="{f(settings.edge_timeconst)} 1"/>'
        f'<elasticity young="{f(params.bend_modulus)}" shear="{f(params.shear_modulus)}" '
        f'damping="{f(params.damping)}"/>'
        f'<contact selfcollide="{settings.selfcollide}" contype="{ROPE_CONTYPE}" '
        f'conaffinity="{ROPE_CONAFFINITY}" condim="{params.condim}" '
        f'friction="{" ".join(f(v) for v in params.friction_triple)}" '
        f'solref="{f(settings.contact_timeconst)} {f(settings.contact_dampratio)}" '
        f'solimp="{" ".join(f(v) for v in settings.contact_solimp)} 0.5 2"/>'
        "</flexcomp></worldbody></mujoco>"
    )


def _fmt(x: float) -> str:
    return repr(float(x))


def _add_raw_flex(
    spec: mujoco.MjSpec, params: RopeParams, settings: SimSettings, x0: np.ndarray, name: str
) -> None:
    """Vertex bodies ``<name>_<k>`` at ``x0`` (n + 1, 3) on x/y/z slides under the world, a
    ``dim=1`` flex through them with rod elasticity (bending only: no twist joints) and the
    flex edge-length equality (named by the caller)."""
    n = params.segments
    box = 0.005  # inertia box side [m] (point masses; rotational inertia unused)
    for k in range(n + 1):
        b = spec.worldbody.add_body(name=f"{name}_{k}", pos=x0[k])
        b.explicitinertial = True
        b.mass = 1.0  # set by add_rope
        b.inertia = [box * box / 6] * 3
        for i, ax in enumerate(np.eye(3)):
            b.add_joint(name=f"{name}_{k}_{'xyz'[i]}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=ax)
    f = spec.add_flex()
    f.name = name
    f.dim = 1
    f.radius = params.radius
    f.vertbody = [f"{name}_{k}" for k in range(n + 1)]
    f.vert = [0.0] * (3 * (n + 1))
    f.elem = [v for k in range(n) for v in (k, k + 1)]
    f.young = params.bend_modulus
    f.shear = params.shear_modulus
    f.damping = params.damping
    f.selfcollide = getattr(mujoco.mjtFlexSelf, f"mjFLEXSELF_{settings.selfcollide.upper()}")
    f.contype = ROPE_CONTYPE
    f.conaffinity = ROPE_CONAFFINITY
    f.condim = params.condim
    f.friction = params.friction_triple
    f.solref = [settings.contact_timeconst, settings.contact_dampratio]
    f.solimp = [*settings.contact_solimp, 0.5, 2.0]
    f.rgba = _RGBA[params.material]
    spec.add_equality(
        type=mujoco.mjtEq.mjEQ_FLEX, name1=name, solref=[settings.edge_timeconst, 1.0]
    )


def _anchor_world_pose(spec: mujoco.MjSpec, anchor_body: str) -> tuple[np.ndarray, np.ndarray]:
    """World position (3,) and rotation matrix (3, 3) of a body at qpos0 (compiles a copy)."""
    try:
        model = spec.copy().compile()
    except ValueError as exc:
        raise ConfigError("spec", f"does not compile before adding the rope: {exc}") from exc
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, anchor_body)
    return data.xpos[bid].copy(), data.xmat[bid].reshape(3, 3).copy()


def add_rope(
    spec: mujoco.MjSpec,
    params: RopeParams,
    *,
    anchor_body: str,
    anchor_pos: Sequence[float] = (0.0, 0.0, 0.0),
    axis: Sequence[float] = (0.0, 0.0, -1.0),
    prefix: str = "rope",
    settings: SimSettings | None = None,
    twist: bool = False,
) -> RopeHandle:
    """Add a rope to ``spec`` held by ``anchor_body``.

    The rope is built hanging straight along ``axis`` from the anchor's pose at ``qpos0``
    (a copy of the spec is compiled to find it), so a freshly reset model is consistent.
    Call :meth:`BoundRope.set_hanging` to place it at the anchor's current pose.

    Args:
        spec: Spec to edit; must compile without the rope.
        params: The rope.
        anchor_body: Name of a dynamic body (moved by joints, not mocap) holding the rope.
        anchor_pos: Anchor point in the anchor body's frame, shape (3,) [m].
        axis: Direction the rope leaves in, in the anchor body's frame, shape (3,).
        prefix: Name prefix of everything added (bodies ``<prefix>_flex_<k>``, ...).
        settings: Simulation settings (default: ``[simulation]`` of ``assets/ropes.toml``).
        twist: Build with MuJoCo's ``flexcomp``, which adds a twist hinge per edge (rod
            torsion); the default builds the flex directly without them (bending only, ~30 %
            faster; torsion is not driven anyway, since the held first edge may spin in its
            tube). See ``docs/rope-model.md``.

    Returns:
        The rope's handle (names); bind it to the compiled model with
        :meth:`RopeHandle.bind`.

    Raises:
        ConfigError: Unknown anchor body, mocap anchor, zero axis, bad vectors, name clash.
    """
    settings = load_sim_settings() if settings is None else settings
    body = spec.body(anchor_body)
    if body is None:
        names = [b.name for b in spec.bodies if b.name and b.name != "world"]
        raise ConfigError("anchor_body", f"no body named {anchor_body!r}", names)
    if body.mocap:
        raise ConfigError(
            "anchor_body",
            f"{anchor_body!r} is a mocap body; flex elasticity needs a body moved by joints",
        )
    pos = _vec3("anchor_pos", anchor_pos)
    ax = _vec3("axis", axis)
    if np.linalg.norm(ax) < 1e-9:
        raise ConfigError("axis", f"must be a non-zero vector, got {tuple(axis)}")
    ax = ax / np.linalg.norm(ax)
    if not isinstance(prefix, str) or not prefix:
        raise ConfigError("prefix", f"must be a non-empty string, got {prefix!r}")
    flex_name = f"{prefix}_flex"
    if spec.body(f"{flex_name}_0") is not None or spec.flex(flex_name) is not None:
        raise ConfigError("prefix", f"a rope with prefix {prefix!r} is already in the spec")

    n, seg, c = params.segments, params.segment_length, params.clearance
    xb, rb = _anchor_world_pose(spec, anchor_body)
    ax_w = rb @ ax
    p0 = xb + rb @ (pos + c * ax)
    if twist:
        centre = p0 + ax_w * params.length / 2
        child = mujoco.MjSpec.from_string(
            _flexcomp_xml(params, settings, centre, quat_from_x_to(ax_w), "flex")
        )
        frame = spec.worldbody.add_frame()
        spec.attach(child, frame=frame, prefix=f"{prefix}_")
    else:
        x0 = p0 + seg * np.arange(n + 1)[:, None] * ax_w
        _add_raw_flex(spec, params, settings, x0, flex_name)

    vbodies = tuple(f"{flex_name}_{k}" for k in range(n + 1))
    # Trapezoidal lumping of the rope's mass: l rho per interior vertex, l rho / 2 at the ends.
    for k, bname in enumerate(vbodies):
        b = spec.body(bname)
        b.mass = params.density * seg * (0.5 if k in (0, n) else 1.0)
    last = spec.body(vbodies[-1])
    last.mass = last.mass + params.end_mass
    end_geom = f"{prefix}_end_weight"
    last.add_geom(
        name=end_geom,
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[params.end_radius, 0, 0],
        mass=0.0,
        contype=ROPE_CONTYPE,
        conaffinity=ROPE_CONAFFINITY,
        condim=params.condim,
        friction=params.friction_triple,
        solref=[settings.contact_timeconst, settings.contact_dampratio],
        solimp=[*settings.contact_solimp, 0.5, 2.0],
        rgba=[0.3, 0.3, 0.32, 1.0],
    )
    sites = (f"{prefix}_hold0", f"{prefix}_hold1")
    body.add_site(name=sites[0], pos=pos + c * ax, group=5)
    body.add_site(name=sites[1], pos=pos + (c + seg) * ax, group=5)
    eqs = (f"{prefix}_hold0", f"{prefix}_hold1")
    for k in range(2):
        vsite = f"{prefix}_vertex{k}"
        spec.body(vbodies[k]).add_site(name=vsite, group=5)
        spec.add_equality(
            name=eqs[k],
            type=mujoco.mjtEq.mjEQ_CONNECT,
            objtype=mujoco.mjtObj.mjOBJ_SITE,
            name1=vsite,
            name2=sites[k],
            solref=[settings.edge_timeconst, 1.0],
        )
    edge_eq = f"{prefix}_edges"
    for e in spec.equalities:
        if e.type == mujoco.mjtEq.mjEQ_FLEX and e.name1 == flex_name:
            e.name = edge_eq
    twist = tuple(j.name for j in spec.joints if j.name.startswith(f"{flex_name}_twist"))
    return RopeHandle(
        params=params,
        prefix=prefix,
        flex=flex_name,
        vertex_bodies=vbodies,
        twist_joints=twist,
        end_geom=end_geom,
        anchor_body=anchor_body,
        hold_sites=sites,
        hold_equalities=eqs,
        edge_equality=edge_eq,
    )


def _vec3(name: str, v: Sequence[float]) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(name, f"must be 3 numbers, got {v!r}") from exc
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(name, f"must be 3 finite numbers, got {v!r}")
    return a


# ----------------------------------------------------------------------------------------
# handles
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RopeHandle:
    """Names of everything :func:`add_rope` put in the spec.

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

    def self_contact(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        """Whether the rope touches itself: an active contact between two elements i, j with
        |i - j| >= 2 (sharing no vertex), or between the end weight and an element
        j <= n - 2 (counting the weight as element n).
        """
        ncon = data.ncon
        if ncon == 0:
            return False
        c = data.contact
        flex = c.flex[:ncon]
        elem = c.elem[:ncon]
        active = c.exclude[:ncon] == 0
        f = self.flex_id
        both = active & (flex[:, 0] == f) & (flex[:, 1] == f)
        if np.any(np.abs(elem[both, 0] - elem[both, 1]) >= 2):
            return True
        geom = c.geom[:ncon]
        n = self.n_segments
        for side in (0, 1):
            hit = active & (geom[:, side] == self.end_geom) & (flex[:, 1 - side] == f)
            if np.any(elem[hit, 1 - side] <= n - 2):
                return True
        return False

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

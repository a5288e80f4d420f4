"""A user's own ropes (a ropes file of ``[[rope]]`` tables) and the one resolver of ropes.

:func:`resolve_rope` turns a paper rope id 1..7, a rope's name (the paper's or one of a ropes
file's) or a :class:`~flyknot_sim.rope_table.RopeParams` into the rope; :func:`rope_record`
says what a record stores about it. The paper's table is :mod:`flyknot_sim.rope_table`.
"""

from __future__ import annotations

import functools
import tomllib as _toml
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from flyknot.constants import MARKER_SPACING, N_MARKERS, ROPE_TABLE
from flyknot.errors import ConfigError
from flyknot.judge import ROPE_DIAMETER_KEY
from flyknot_sim.rope_fields import (
    DEFAULT_SEGMENTS,
    DEFAULT_TIMESTEP,
    FIELD,
    MATERIALS,
    MAX_TIMESTEP,
    REQUIRED,
    ROPE_FIELDS,
    SAME,
    ByMaterial,
)
from flyknot_sim.rope_table import (
    RopeParams,
    _check_keys,
    _default_table,
    _read_toml,
    get_rope,
)

__all__ = [
    "CUSTOM_KEYS",
    "CUSTOM_OPTIONAL",
    "CUSTOM_REQUIRED",
    "DEFAULT_SEGMENTS",
    "DEFAULT_TIMESTEP",
    "MAX_TIMESTEP",
    "REFERENCE_CORD",
    "load_custom_ropes",
    "parse_custom_ropes",
    "resolve_rope",
    "rope_choices",
    "rope_record",
]

# ----------------------------------------------------------------------------------------
# custom ropes: a user's own ropes file
# ----------------------------------------------------------------------------------------
_FILE_FIELDS = tuple(f for f in ROPE_FIELDS if f.in_file)
CUSTOM_REQUIRED = tuple(f.file_key for f in _FILE_FIELDS if f.file_required)
"""Keys every ``[[rope]]`` table of a custom ropes file must have."""
CUSTOM_OPTIONAL = tuple(f.file_key for f in _FILE_FIELDS if not f.file_required)
"""Keys a custom rope may give; missing ones come from its material (or the defaults)."""
CUSTOM_KEYS = CUSTOM_REQUIRED + CUSTOM_OPTIONAL

REFERENCE_CORD = {"cotton": (0.009, 0.040)}
"""Diameter [m] and linear density [kg/m] of the cord (rope 1) at which a material's stiffness in
``assets/ropes.toml`` holds. For these materials a custom rope's default E and G scale as
(rho / rho_ref) (D_ref / D)^4, so that EI grows with the linear density as the table's cotton
ropes' does (EI = b tex, free-slip fibre-bundle scaling, see the comments there). Other
materials are not scaled: steel (chain) has no stiffness; latex's values are those of 3/8"
surgical tubing."""


def _stiffness_scale(material: str, diameter: float, density: float) -> float:
    """E / E_ref of a custom rope: (rho / rho_ref) (D_ref / D)^4 (:data:`REFERENCE_CORD`)."""
    if material not in REFERENCE_CORD:
        return 1.0
    d_ref, rho_ref = REFERENCE_CORD[material]
    return (density / rho_ref) * (d_ref / diameter) ** 4


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
    """One ``[[rope]]`` table (``where`` names it in errors) as :class:`RopeParams`: the
    material's defaults scaled to its size, the table's own values over them."""
    if not isinstance(entry, Mapping):
        raise ConfigError(where, f"must be a table ([[rope]]), got {entry!r}")
    _check_keys(where, entry, CUSTOM_KEYS)
    missing = [k for k in CUSTOM_REQUIRED if k not in entry]
    if missing:
        raise ConfigError(where, f"missing key(s) {', '.join(missing)}")
    for f in _FILE_FIELDS:
        if f.file_key in entry:
            f.check(entry[f.file_key], f"{where}.{f.file_key}", in_file=True)
    name = _checked_name(entry["name"], where, paper)
    diameter, n_max = _checked_size(entry, where)
    values = _material_values(entry["material"], diameter, float(entry["density"]), n_max)
    values.update({f.name: entry[f.file_key] for f in _FILE_FIELDS if f.file_key in entry})
    try:
        p = RopeParams(id=name, **values)
    except ConfigError as e:  # name the rope's field as the file does (end_weight)
        key = FIELD[e.field].file_key if e.field in FIELD else e.field
        raise ConfigError(f"{where}.{key}", e.problem, e.choices) from None
    as_float = {
        f.name: float(getattr(p, f.name))
        for f in ROPE_FIELDS
        if f.type is float and getattr(p, f.name) is not None
    }
    return replace(p, **as_float)


def _checked_name(name: Any, where: str, paper: Mapping[str, int]) -> str:
    """A custom rope's name (a non-empty string already): not a number, not a paper rope's
    name."""
    if name.strip().isdigit():
        raise ConfigError(
            f"{where}.name", f"must not be a number (1..7 are the paper's rope ids), got {name!r}"
        )
    if name in paper:
        raise ConfigError(
            f"{where}.name",
            f"{name!r} is the paper's rope {paper[name]}; give your rope another name",
        )
    return name


def _checked_size(entry: Mapping[str, Any], where: str) -> tuple[float, int]:
    """The diameter [m] and the most segments the rope can have, the size checked (each value
    is in its range already): the length past the markers' span, the diameter under half the
    length."""
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
    return diameter, n_max


def _material_values(material: str, diameter: float, density: float, n_max: int) -> dict:
    """The defaults of a rope of this material and size for every field a ropes file may
    leave out: the material's values in the lab's table (moduli scaled by
    :func:`_stiffness_scale`), else the field's default; segments at most ``n_max``."""
    mat = _material_defaults()[material]
    scale = _stiffness_scale(material, diameter, density)
    out = {}
    for f in _FILE_FIELDS:
        if f.file_required:
            continue
        if f.by_material is ByMaterial.NO:
            out[f.name] = f.default if f.file_default is SAME else f.file_default
            continue
        value = mat.get(f.name, f.default)
        if value is REQUIRED:
            raise ConfigError(f"materials.{material}.{f.name}", f"missing from {ROPE_TABLE}")
        out[f.name] = value * scale if f.by_material is ByMaterial.SCALED else value
    out["segments"] = min(out["segments"], n_max)
    return out


def parse_custom_ropes(doc: Mapping[str, Any]) -> dict[str, RopeParams]:
    """A user's ropes from a parsed TOML document: name -> :class:`RopeParams`.

    The document holds ``[[rope]]`` tables with the keys :data:`CUSTOM_REQUIRED` and
    optionally :data:`CUSTOM_OPTIONAL`: the fields of
    :data:`~flyknot_sim.rope_fields.ROPE_FIELDS` (their units, valid values and defaults
    there) but the ``id`` (each rope's id is its name), ``end_mass`` given as ``end_weight``.
    Missing optional values: the material's in ``assets/ropes.toml`` (E and G of cotton
    scaled by (rho / 40 g/m) (9 mm / D)^4, see :data:`REFERENCE_CORD`), else the field's
    default (``segments`` 30 capped so that length / segments > D, ``timestep`` 1 ms).

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
    """What a record says about its rope: ``rope`` (the id: 1..7, or a custom rope's name),
    ``rope_name`` and ``rope_diameter_m`` (by which the judge tells a knot lying on the floor,
    :func:`flyknot.judge.judge_params_for`); for a custom rope also ``rope_params`` (all its
    parameters) and ``ropes_file``, so that the record describes the rope without the file."""
    out: dict[str, Any] = {
        "rope": params.id,
        "rope_name": params.name,
        ROPE_DIAMETER_KEY: params.diameter,
    }
    if params.custom:
        out["rope_params"] = params.to_dict()
        out["ropes_file"] = None if ropes_file is None else str(ropes_file)
    return out

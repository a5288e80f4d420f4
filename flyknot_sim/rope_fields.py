"""The rope's fields, each declared once: its type, unit, valid values and default.

Every parameter of a rope is one :class:`RopeField` of :data:`ROPE_FIELDS`. They are the fields
of :class:`~flyknot_sim.rope_table.RopeParams` (:func:`rope_dataclass`) and its checks; the
keys of a ropes table's ``[[rope]]`` entries and ``[materials.<material>]`` tables
(:func:`~flyknot_sim.rope_table.parse_rope_table`), of a user's ropes file and their defaults
(:func:`~flyknot_sim.rope_custom.parse_custom_ropes`), the fields ``flyknot-tools rope-validate
--set`` may change (:meth:`RopeField.from_text`), and every message about a bad value (it names
the field and its valid range or choices). Adding a rope field is adding one entry to
:data:`ROPE_FIELDS` and using it; one with a default leaves the records of ropes without it as
they were (:meth:`~flyknot_sim.rope_table.RopeParams.to_dict` leaves a default out).

The values of a material (cotton's E, G, damping, friction, HB / B) are data of a ropes table,
with their sources beside them (``assets/ropes.toml``, ``[materials.<material>]``); a field
declares whether a material gives it (:class:`ByMaterial`).
"""

from __future__ import annotations

import enum
import inspect
import math
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from flyknot.errors import ConfigError, check_choice

__all__ = [
    "DEFAULT_SEGMENTS",
    "DEFAULT_TIMESTEP",
    "FIELD",
    "MATERIALS",
    "MAX_TIMESTEP",
    "NONNEGATIVE",
    "POSITIVE",
    "REQUIRED",
    "ROPE_FIELDS",
    "SAME",
    "SETTABLE",
    "ByMaterial",
    "Choice",
    "Range",
    "RopeField",
    "Text",
    "rope_dataclass",
]

MATERIALS = ("cotton", "steel", "latex")
"""Materials of the paper's ropes."""
DEFAULT_SEGMENTS = 30
"""Flex elements of a custom rope unless it says, capped so that length / segments > D."""
DEFAULT_TIMESTEP = 0.001
"""Simulation step of a custom rope unless it says [s] (the thin ropes' validated step)."""
MAX_TIMESTEP = 0.004
"""Largest simulation step of a custom rope [s]: the robot's 4 ms command tick."""


class _Marker(enum.Enum):
    REQUIRED = "required"
    SAME = "same"

    def __repr__(self) -> str:
        return self.name


REQUIRED = _Marker.REQUIRED
"""A field's default: none, every rope gives the field (or, for some, its material does)."""
SAME = _Marker.SAME
"""A field's default in a user's ropes file: the same as in a ropes table."""


class ByMaterial(enum.Enum):
    """Whether a rope's material gives the field when the rope does not."""

    NO = "no"
    """The rope gives it (or the field's default holds)."""
    VALUE = "the material's"
    """A ropes table's ``[materials.<material>]`` may give it (the field's default if not); a
    user's rope takes its material's value in the lab's table."""
    SCALED = "the material's, scaled to the rope's size"
    """As :attr:`VALUE`, but a user's rope takes its material's value scaled to its diameter
    and linear density (:data:`~flyknot_sim.rope_custom.REFERENCE_CORD`)."""


# ----------------------------------------------------------------------------------------
# valid values
# ----------------------------------------------------------------------------------------
def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class Range:
    """The numbers a field may take: from ``low`` to ``high``, each end in or out.

    Attributes:
        low: Lower end (finite).
        high: Upper end (``math.inf``: none, but a value must be finite).
        low_in: ``low`` itself is valid.
        high_in: ``high`` itself is valid.
        integer: Only integers (not bools) are valid.
        why: Why the upper end is where it is, for the message.
    """

    low: float
    high: float = math.inf
    low_in: bool = False
    high_in: bool = False
    integer: bool = False
    why: str = ""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and self.low < self.high):
            raise ConfigError("range", f"needs a finite low < high, got {self.low}, {self.high}")

    def contains(self, value: object) -> bool:
        """Whether ``value`` lies in the range (and is an integer, if it must be)."""
        if not _is_number(value) or (self.integer and not isinstance(value, int)):
            return False
        above = value >= self.low if self.low_in else value > self.low
        below = value <= self.high if self.high_in else value < self.high
        return above and below and math.isfinite(value)

    def _bound(self) -> str:
        return f"{'>=' if self.low_in else '>'} {self.low:g}"

    def text(self, unit: str = "") -> str:
        """The range in words, e.g. ``> 0``, ``an integer >= 2``, ``(0, 0.004] s``."""
        if math.isinf(self.high):
            return f"an integer {self._bound()}" if self.integer else self._bound()
        interval = f"{'[' if self.low_in else '('}{self.low:g}, {self.high:g}"
        interval += "]" if self.high_in else ")"
        return f"{'an integer in ' if self.integer else ''}{interval}{f' {unit}' if unit else ''}"

    def check(self, field: str, value: object, unit: str = "") -> None:
        """Raise :class:`ConfigError` naming ``field`` and the range unless ``value`` is in it."""
        if self.contains(value):
            return
        if self.integer:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(field, f"must be an integer, got {value!r}")
            if math.isinf(self.high):
                raise ConfigError(field, f"must be {self._bound()}, got {value}")
        elif math.isinf(self.high):
            raise ConfigError(field, f"must be a finite number {self._bound()}, got {value!r}")
        why = f" ({self.why})" if self.why else ""
        raise ConfigError(field, f"must lie in {self.text(unit)}{why}, got {value!r}")


@dataclass(frozen=True)
class Choice:
    """A field that takes one of a few values.

    Attributes:
        values: The valid values.
    """

    values: tuple[object, ...]

    def __post_init__(self) -> None:
        if not self.values:
            raise ConfigError("choice", "needs at least one value")

    def text(self, unit: str = "") -> str:
        """The choices in words, e.g. ``one of cotton, steel, latex``."""
        return "one of " + ", ".join(str(v) for v in self.values)

    def check(self, field: str, value: object, unit: str = "") -> None:
        """Raise :class:`ConfigError` listing the choices unless ``value`` is one of them."""
        check_choice(field, value, self.values)


@dataclass(frozen=True)
class Text:
    """A field that takes any non-empty string."""

    def text(self, unit: str = "") -> str:
        """``a non-empty string``."""
        return "a non-empty string"

    def check(self, field: str, value: object, unit: str = "") -> None:
        """Raise :class:`ConfigError` unless ``value`` is a non-empty string."""
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(field, f"must be a non-empty string, got {value!r}")


Valid = Range | Choice | Text
POSITIVE = Range(0.0)
"""A finite number > 0."""
NONNEGATIVE = Range(0.0, low_in=True)
"""A finite number >= 0."""


# ----------------------------------------------------------------------------------------
# the field
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RopeField:
    """One parameter of a rope.

    Attributes:
        name: The field's name (of :class:`~flyknot_sim.rope_table.RopeParams` and the keys of
            a ropes table).
        type: The value's type (``float``, ``int``, ``str``; a tuple when it may be either).
        unit: SI unit of the value (``-`` for a ratio, ``""`` for a count or a text).
        valid: The valid values (None: :class:`~flyknot_sim.rope_table.RopeParams` checks
            them itself, the ``id``). A default of None is valid besides.
        doc: What it is, and where its values come from.
        example: A valid value, not the default (for tests and help texts).
        default: The value of a rope that gives none (:data:`REQUIRED`: every rope must, or
            its material).
        by_material: Whether the rope's material gives it (:class:`ByMaterial`).
        file_key: Its key in a user's ropes file (``""``: its name; None: none).
        file_default: Its default there (:data:`SAME`: as ``default``).
        file_valid: Its valid values there, when narrower (None: ``valid``).
        settable: ``rope-validate --set`` may change it (not the rope's id and name).
    """

    name: str
    type: type | tuple[type, ...]
    unit: str
    valid: Valid | None
    doc: str
    example: Any
    default: Any = REQUIRED
    by_material: ByMaterial = ByMaterial.NO
    file_key: str | None = ""
    file_default: Any = SAME
    file_valid: Range | None = None
    settable: bool = True

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ConfigError("rope field", f"name must be an identifier, got {self.name!r}")
        if self.file_key == "":
            object.__setattr__(self, "file_key", self.name)
        where = f"rope field {self.name}"
        if not isinstance(self.example, self.types) or isinstance(self.example, bool):
            raise ConfigError(where, f"example must be a {self.annotation}, got {self.example!r}")
        if self.example == self.default:
            raise ConfigError(where, f"needs an example other than its default {self.default!r}")
        for label, v in (("example", self.example), ("default", self.default)):
            if v is not REQUIRED:
                self.check(v, f"{where} {label}")
        if self.file_default not in (SAME, REQUIRED):
            self.check(self.file_default, f"{where} file_default", in_file=True)
        if self.settable and self.types not in ((float,), (int,), (str,)):
            raise ConfigError(where, f"--set reads float, int or str, not {self.annotation}")

    @property
    def types(self) -> tuple[type, ...]:
        """The value's types."""
        return self.type if isinstance(self.type, tuple) else (self.type,)

    @property
    def annotation(self) -> str:
        """The value's type as an annotation, e.g. ``float | None``."""
        names = [t.__name__ for t in self.types]
        return " | ".join(names + (["None"] if self.default is None else []))

    @property
    def in_file(self) -> bool:
        """A user's ropes file has this field."""
        return self.file_key is not None

    @property
    def file_required(self) -> bool:
        """Every rope of a user's ropes file must give this field."""
        default = self.default if self.file_default is SAME else self.file_default
        return self.in_file and default is REQUIRED and self.by_material is ByMaterial.NO

    def check(self, value: object, field: str | None = None, *, in_file: bool = False) -> None:
        """Raise :class:`ConfigError` naming the field (``field``: as the caller names it)
        and its valid values unless ``value`` is one of them (``in_file``: in a ropes file).
        """
        if value is None and self.default is None:
            return
        valid = (self.file_valid or self.valid) if in_file else self.valid
        if valid is not None:
            valid.check(field or self.name, value, self.unit)

    def from_text(self, text: str) -> object:
        """The value a command line's text gives (``--set bend_hysteresis=38``), not yet
        checked: a number for a number (an integer when it is one and the field takes
        integers), the text for a text.

        Raises:
            ConfigError: A number field given no number.
        """
        if str in self.types:
            return text
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(self.name, f"must be a number, got {text!r}") from None
        return int(value) if int in self.types and value.is_integer() else value

    def describe(self) -> str:
        """One line of documentation: name, unit, what it is, valid values, default."""
        unit = f" [{self.unit}]" if self.unit else ""
        facts = [] if self.valid is None else [self.valid.text(self.unit)]
        if self.by_material is not ByMaterial.NO:
            alt = "" if self.default is REQUIRED else f", else {self.default!r}"
            facts.append(f"default {self.by_material.value}{alt}")
        elif self.default is not REQUIRED:
            facts.append(f"default {self.default!r}")
        if self.in_file and self.file_key != self.name:
            facts.append(f"{self.file_key!r} in a ropes file")
        if self.file_valid is not None:
            facts.append(f"{self.file_valid.text(self.unit)} in a ropes file")
        if self.file_default not in (SAME, REQUIRED):
            facts.append(f"default {self.file_default!r} in a ropes file")
        return f"{self.name}{unit}: {self.doc}" + (f" ({'; '.join(facts)})" if facts else "")


# ----------------------------------------------------------------------------------------
# the declaration
# ----------------------------------------------------------------------------------------
ROPE_FIELDS = (
    RopeField(
        "id", (int, str), "", None, "Rope id of the paper (1..7), or, for a custom rope, its "
        "name.", example=8, file_key=None, settable=False,
    ),
    RopeField(
        "name", str, "", Text(), "Name in the paper's table (or the custom rope's name).",
        example="my rope", settable=False,
    ),
    RopeField(
        "material", str, "", Choice(MATERIALS), "What the rope is made of; a table's "
        "[materials.<material>] gives the values its ropes leave out.", example="steel",
    ),
    RopeField(
        "diameter", float, "m", POSITIVE, "Rope diameter; the flex capsule radius is half "
        "of it.", example=0.012,
    ),
    RopeField("density", float, "kg/m", POSITIVE, "Linear density.", example=0.05),
    RopeField(
        "end_mass", float, "kg", NONNEGATIVE, "Mass of the weight at the free end (separate "
        "from the rope's mass).", example=0.02, file_key="end_weight",
    ),
    RopeField("length", float, "m", POSITIVE, "Rope length.", example=1.2),
    RopeField(
        "bend_modulus", float, "Pa", NONNEGATIVE, "Effective Young's modulus E of a solid "
        "circular section of the rope's diameter; bending stiffness EI = E pi r^4 / 4 "
        "[N m^2].", example=1.0e5, by_material=ByMaterial.SCALED,
    ),
    RopeField(
        "shear_modulus", float, "Pa", NONNEGATIVE, "Effective shear modulus G; torsional "
        "stiffness GJ = G pi r^4 / 2. 0 lets MuJoCo use E / (2 (1 + nu)) with nu = 0.",
        example=3.0e4, by_material=ByMaterial.SCALED,
    ),
    RopeField(
        "damping", float, "s", NONNEGATIVE, "Rayleigh damping time of the bending/torsion "
        "stiffness.", example=0.02, by_material=ByMaterial.VALUE,
    ),
    RopeField(
        "friction", float, "-", POSITIVE, "Sliding friction coefficient of rope-rope and "
        "rope-geom contact.", example=0.4, by_material=ByMaterial.VALUE,
    ),
    RopeField(
        "segments", int, "", Range(2, low_in=True, integer=True), "Number of flex elements "
        "(capsules); length / segments > diameter (a user's rope's default is capped so).",
        example=20, file_default=DEFAULT_SEGMENTS,
    ),
    RopeField(
        "timestep", float, "s", POSITIVE, "Largest simulation step this rope was validated "
        "at.", example=0.002, file_default=DEFAULT_TIMESTEP,
        file_valid=Range(0.0, MAX_TIMESTEP, high_in=True, why="the robot's command tick"),
    ),
    RopeField(
        "cd", float, "-", POSITIVE, "Fixed cross-flow drag coefficient replacing the C_D(Re) "
        "curve of flyknot_sim.aero (the labs pass it on as AeroParams.cd); None: the curve.",
        example=1.2, default=None,
    ),
    RopeField(
        "condim", int, "", Choice((3, 4)), "Contact dimensionality of the rope's contacts: 3 "
        "(sliding friction) or 4 (plus torsional friction about the contact normal).",
        example=4, default=3,
    ),
    RopeField(
        "torsional_friction", float, "m", NONNEGATIVE, "MuJoCo's torsional friction "
        "coefficient (the moment about the normal is this times the normal force) when "
        "condim is 4; None: (2/3) friction r, the moment of uniform pressure over a contact "
        "disc of radius a = r (K. L. Johnson, 'Contact Mechanics', 1985, sec. 7.4; a soft cord "
        "flattens to a patch about its radius wide -- an upper bound, no measured value found).",
        example=0.001, default=None,
    ),
    RopeField(
        "bend_hysteresis", float, "1/m", NONNEGATIVE, "Kawabata's HB / B: the frictional "
        "couple of bending (Grosberg's M_0 = HB, flyknot_sim.bend_friction) over the elastic "
        "stiffness B = EI, i.e. the curvature at which the two moments are equal; 0: purely "
        "elastic bending.", example=23.0, default=0.0, by_material=ByMaterial.VALUE,
    ),
    RopeField(
        "link_friction_radius", float, "m", NONNEGATIVE, "A link chain's wire radius r: the "
        "links rub where they bear on each other, so each joint's frictional couple gains "
        "friction * T * r, T the joint's tension (flyknot_sim.bend_friction); 0: none. The "
        "lab's chain (rope 6) takes 0.0025: its 20 mm and 0.514 kg/m are a DIN 5685A 5 mm "
        "short-link chain's.", example=0.0025, default=0.0,
    ),
    RopeField(
        "lock_angle", float, "deg",
        Range(0.0, 180.0, low_in=True, why="at 180 a segment folds back onto the last"),
        "A link chain's lock-up: the largest turning angle between two consecutive "
        "segments, held by a limit on the chord of the two (flyknot_sim.rope); 0: none. For "
        "the lab's 30 segments of rope 6, 140.7 (DIN 5685A 5 mm links, assets/ropes.toml).",
        example=140.7,
        default=0.0,
    ),
    RopeField(
        "stretch_modulus", float, "Pa", NONNEGATIVE, "Effective Young's modulus of a solid "
        "circular section of the rope's diameter for stretching: axial stiffness EA = E pi "
        "r^2 [N], damped with the rope's damping time (flyknot_sim.rope); 0: an inextensible "
        "rope (its edges held hard), the default. The latex tube's is 1.2 MPa times its "
        "wall's share of the section (assets/ropes.toml). A value whose edge spring is "
        "faster than two of the rope's steps is refused, naming the largest allowed.",
        example=5.3e5, default=0.0, by_material=ByMaterial.VALUE,
    ),
)  # fmt: skip
"""Every field of a rope, in the order of :class:`~flyknot_sim.rope_table.RopeParams`' fields
(those with a default last)."""

FIELD: Mapping[str, RopeField] = {f.name: f for f in ROPE_FIELDS}
"""The rope fields by name."""
SETTABLE = tuple(f.name for f in ROPE_FIELDS if f.settable)
"""The fields ``flyknot-tools rope-validate --set`` may change."""


def rope_dataclass(cls: type) -> type:
    """Make ``cls`` a frozen dataclass whose fields are :data:`ROPE_FIELDS`, in order, with
    their defaults; its docstring gains the fields' descriptions (:meth:`RopeField.describe`).
    ``cls`` declares no fields of its own (its methods and properties stay).
    """
    if inspect.get_annotations(cls):
        raise ConfigError(cls.__name__, "declares its fields in flyknot_sim/rope_fields.py")
    cls.__annotations__ = {f.name: f.annotation for f in ROPE_FIELDS}
    for f in ROPE_FIELDS:
        if f.default is not REQUIRED:
            setattr(cls, f.name, f.default)
    doc = [
        textwrap.fill(f.describe(), 92, initial_indent=" " * 8, subsequent_indent=" " * 12)
        for f in ROPE_FIELDS
    ]
    cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n\n    Attributes:\n" + "\n".join(doc) + "\n"
    return dataclass(frozen=True)(cls)

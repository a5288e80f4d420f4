"""Options as frozen dataclasses, read from and written to plain mappings by their fields.

Every field of an options dataclass is an option a scenario file, a summary or the command
line may set, under the field's own name; its docstring is the option's documentation. A
field's metadata may change that:

* :data:`INLINE`: the field holds another options dataclass whose options sit beside the
  outer class's own (the update settings among the learning loop's options: ``objective``,
  not ``update.objective``).
* :data:`NOT_AN_OPTION`: the field is set by the program, never from a mapping (the joint
  limits a cell imposes).

A field whose default is itself a dataclass is a nested table (``weights = {w_control = 1}``,
``--set weights.w_control=1``). So adding an option is adding one field with its docstring:
:func:`option_names`, :func:`from_mapping` and :func:`to_mapping` find it.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import MISSING, Field, fields, is_dataclass, replace
from types import MappingProxyType
from typing import Any, TypeVar

from flyknot.errors import ConfigError

T = TypeVar("T")

INLINE = MappingProxyType({"options": "inline"})
"""Field metadata: the field's options sit beside the outer class's own."""
NOT_AN_OPTION = MappingProxyType({"options": "none"})
"""Field metadata: the program sets the field; no mapping may."""


class ReadOnlyMap(Mapping):
    """A read-only copy of a mapping that, unlike ``types.MappingProxyType``, pickles (options
    and summaries travel to and from worker processes)."""

    __slots__ = ("_data",)

    def __init__(self, data: Mapping[str, Any] | None = None):
        object.__setattr__(self, "_data", dict(data or {}))

    def __getitem__(self, key: str) -> Any:
        return self._data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("a ReadOnlyMap cannot be changed")

    def __repr__(self) -> str:
        return f"ReadOnlyMap({self._data!r})"

    def __reduce__(self):
        """Rebuild from a plain dict."""
        return (ReadOnlyMap, (self._data,))


def _mode(f: Field) -> str:
    return f.metadata.get("options", "option")


def _default(f: Field) -> Any:
    """The field's default value (None when it has none)."""
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    return None


def _nested_type(f: Field) -> type | None:
    """The options class a field nests (its default is a dataclass instance), or None."""
    d = _default(f)
    return type(d) if is_dataclass(d) and not isinstance(d, type) else None


def option_names(cls: type) -> tuple[str, ...]:
    """The names a mapping may give for ``cls``, in field order (inline fields expanded)."""
    names: list[str] = []
    for f in fields(cls):
        mode = _mode(f)
        if mode == "inline":
            names.extend(option_names(_nested_type(f)))
        elif mode == "option":
            names.append(f.name)
    return tuple(names)


def option_keys(cls: type) -> tuple[str, ...]:
    """Every key a command line may set for ``cls``: its options, a nested table's as
    ``table.option`` (``weights.w_control``)."""
    keys: list[str] = []
    for name in option_names(cls):
        nested = nested_options(cls, name)
        keys.extend(f"{name}.{k}" for k in option_keys(nested)) if nested else keys.append(name)
    return tuple(keys)


def nested_options(cls: type, name: str) -> type | None:
    """The options class of ``cls``'s option ``name`` when it is a nested table, else None.

    Raises:
        ConfigError: ``name`` is not an option of ``cls``.
    """
    for f in fields(cls):
        mode = _mode(f)
        if mode == "inline" and name in option_names(_nested_type(f)):
            return nested_options(_nested_type(f), name)
        if mode == "option" and f.name == name:
            return _nested_type(f)
    raise ConfigError(name, "unknown field", option_names(cls))


def from_mapping(
    cls: type[T],
    values: Mapping[str, Any],
    *,
    where: str = "",
    base: T | None = None,
    given: Mapping[str, Any] | None = None,
) -> T:
    """An instance of ``cls`` from ``values``, which may give any of :func:`option_names`.

    Nested tables are read the same way; fields ``values`` leaves out keep ``base``'s value
    (or the default when ``base`` is None). The class's own validation runs as it is built.

    Args:
        cls: An options dataclass.
        values: Option name -> value (nested tables as mappings).
        where: Prefix of the field names in error messages (``"run[2]"``).
        base: Values of the options ``values`` leaves out (None: the defaults).
        given: Values of fields that are not options (set by the program).

    Raises:
        ConfigError: An unknown option (the message lists the valid ones), a nested option
            that is not a table, or a value the class rejects.
    """
    prefix = f"{where}." if where else ""
    if not isinstance(values, Mapping):
        raise ConfigError(where or cls.__name__, f"must be a table of options, got {values!r}")
    names = option_names(cls)
    for key in values:
        if key not in names:
            raise ConfigError(f"{prefix}{key}", "unknown field", names)
    return _build(cls, values, prefix, base, given or {})


def _build(
    cls: type[T],
    values: Mapping[str, Any],
    prefix: str,
    base: T | None,
    given: Mapping[str, Any] | None = None,
) -> T:
    kwargs: dict[str, Any] = dict(given or {})
    for f in fields(cls):
        mode, nested = _mode(f), _nested_type(f)
        current = getattr(base, f.name) if base is not None else None
        if mode == "inline":
            own = set(option_names(nested))
            part = {k: v for k, v in values.items() if k in own}
            if part:
                kwargs[f.name] = _build(nested, part, prefix, current)
        elif mode == "option" and f.name in values:
            value = values[f.name]
            if nested is not None:
                value = from_mapping(nested, value, where=f"{prefix}{f.name}", base=current)
            kwargs[f.name] = value
    try:
        return replace(base, **kwargs) if base is not None else cls(**kwargs)
    except TypeError as e:
        raise ConfigError(prefix.rstrip(".") or cls.__name__, str(e)) from None


def coerce_override(value: str) -> Any:
    """A ``--set`` value as a scenario file would give it: a number, a boolean, none, a TOML
    array or inline table (``confirm=[3,4]``), else the string itself."""
    if value.startswith(("[", "{")):
        try:
            return tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            return value
    for cast in (int, float):
        try:
            return cast(value)
        except ValueError:
            pass
    low = value.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    return value


def to_mapping(obj: Any) -> dict[str, Any]:
    """The options of ``obj`` as a plain mapping :func:`from_mapping` reads back (nested
    tables as dicts, tuples as lists; fields that are not options left out)."""
    out: dict[str, Any] = {}
    for f in fields(obj):
        mode, value = _mode(f), getattr(obj, f.name)
        if mode == "inline":
            out.update(to_mapping(value))
        elif mode == "option":
            out[f.name] = _plain(value)
    return out


def _plain(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        return to_mapping(value)
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value

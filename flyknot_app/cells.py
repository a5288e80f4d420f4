"""The registry of cells: a scenario's ``[cell]`` table names a kind, the registry opens it.

A cell is where a command is tried (:class:`flyknot.record.Cell`): the simulated lab
(``kind = "sim"``, :mod:`flyknot_sim`) or the real xArm 7 with motion capture
(``kind = "xarm"``, :mod:`flyknot_hw`, assembled by :mod:`flyknot_app.hardware`). Each kind
has a small frozen spec, validated on construction, and a factory that opens the cell::

    [cell]
    kind = "sim"      # the default
    rope = 1          # rope, seed, settle_s may also be given per run, in a grid or by --set
    seed = 0
    variation = {servo_gain_rel = 0.003}   # or: --set cell.variation.servo_gain_rel=0.003

    [cell]
    kind = "xarm"
    lab = "my_lab.toml"   # the lab file (assets/lab_example.toml); or: flyknot run --cell FILE
    dry_run = false       # true: preflight as on the arm, then play in the simulated lab

The runner never names a cell class; it calls :func:`open_cell` with the run's spec.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

from flyknot.errors import ConfigError, check_nonnegative
from flyknot.record import Cell
from learner.jacobians import JacobianProvider


@dataclass(frozen=True)
class SimCellSpec:
    """The simulated lab (:class:`flyknot_sim.lab.SimLab`) as a run opens it.

    Attributes:
        rope: Rope id (1..7) or a rope's name (the paper's, or one of ``ropes``).
        seed: Seed of the lab's trial-to-trial variation (trial i uses (seed, i)).
        settle_s: A fixed wait before the knot is judged [s]; None: until the rope is at rest.
        ropes: A user's ropes file (absolute path), or None.
        knot_set: End the settle of a knotted rope once its knot has set
            (:attr:`flyknot.rest.SettleParams.knot_set_s`); false: such a rope waits for rest
            or the cap (what ``flyknot bench protocol --quick`` compares against).
        unknot_held: End the settle of a rope whose verdict has been unknotted for
            :attr:`flyknot.rest.SettleParams.unknot_held_s`; false: such a rope waits for
            rest, contact-free, or the cap (``flyknot bench protocol --quick`` compares).
        variation: Fields of the lab's trial-to-trial variation to change
            (:class:`flyknot_sim.lab_params.VariationParams`, where each number's source and
            bracket are); empty: the lab's own.
    """

    rope: int | str = 1
    seed: int = 0
    settle_s: float | None = None
    ropes: str | None = None
    knot_set: bool = True
    unknot_held: bool = True
    variation: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ConfigError("seed", f"must be an integer >= 0, got {self.seed!r}")
        if self.settle_s is not None:
            check_nonnegative("settle_s", self.settle_s)
        for name in ("knot_set", "unknot_held"):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise ConfigError(f"cell.{name}", f"must be true or false, got {value!r}")
        if not isinstance(self.variation, Mapping):
            raise ConfigError(
                "cell.variation", f"must be a table of variation fields, got {self.variation!r}"
            )
        object.__setattr__(self, "variation", dict(self.variation))
        if self.variation:  # the lab's own needs no check (nor the simulator's import)
            lab_variation(self.variation)


def lab_variation(values: Mapping[str, Any], where: str = "cell.variation"):
    """The lab's :class:`flyknot_sim.lab_params.VariationParams` with ``values`` changed
    (:func:`variation_from`)."""
    from flyknot_sim.lab_params import VariationParams

    return variation_from(VariationParams, values, where)


def variation_from(cls: type, values: Mapping[str, Any], where: str) -> Any:
    """A variation dataclass ``cls`` (the robot lab's or the hand lab's) with ``values``
    changed from its defaults.

    Raises:
        ConfigError: A field that is not one of ``cls``'s (the valid ones listed), or a bad
            value (the field's own message), each named ``<where>.<field>``.
    """
    valid = tuple(f.name for f in fields(cls))
    for key in values:
        if key not in valid:
            raise ConfigError(f"{where}.{key}", "not a field of the variation", valid)
    try:
        return cls(**values)
    except ConfigError as e:
        name = e.field.rsplit(".", 1)[-1]
        raise ConfigError(f"{where}.{name}", e.problem, e.choices) from None


def variation_pairs(pairs: Sequence[str]) -> dict[str, Any]:
    """``["servo_gain_rel=0.003", "rest_scale=0.1"]`` (``--variation``) -> the fields to
    change, each value read as a scenario file would give it.

    Raises:
        ConfigError: A pair without ``=`` (named as ``--variation``).
    """
    from flyknot.options import coerce_override

    out: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError("--variation", f"expected FIELD=VALUE, got {pair!r}")
        key, value = (part.strip() for part in pair.split("=", 1))
        out[key] = coerce_override(value)
    return out


def sim_lab_params(spec: SimCellSpec):
    """The :class:`flyknot_sim.lab.LabParams` of a simulated cell."""
    from flyknot.rest import EARLY_ENDS, SettleParams
    from flyknot_sim.lab import LabParams

    settle = SettleParams().without(*(end for end in EARLY_ENDS if not getattr(spec, end)))
    return LabParams(
        rope=spec.rope,
        seed=spec.seed,
        settle=settle,
        settle_s=spec.settle_s,
        ropes=spec.ropes,
        variation=lab_variation(spec.variation),
    )


def _open_sim(spec: SimCellSpec) -> Cell:
    from flyknot_sim.lab import SimLab

    return SimLab(sim_lab_params(spec))


def _sim_oracle(spec: SimCellSpec, t_c: float) -> JacobianProvider:
    from flyknot_app.diagnose.oracle import LabJacobian

    return LabJacobian(sim_lab_params(spec), t_c)


@dataclass(frozen=True)
class XArmCellSpec:
    """The real lab (:class:`flyknot_hw.xarm_cell.XArmCell`) as a run opens it.

    Attributes:
        lab: The lab file (TOML, ``assets/lab_example.toml``).
        rope: The rope the run needs: it must be the one the lab file says is mounted.
        seed: Seed of the simulated lab's variation in a dry run (unused on the arm).
        settle_s: Unused on the arm (the lab file's ``[settle]`` decides); accepted so that
            scenarios written for the simulated lab run unchanged.
        ropes: A user's ropes file naming ``rope``, or None.
        dry_run: Preflight each command as on the arm, then play it in the simulated lab
            (:class:`flyknot_app.hardware.DryRunCell`); nothing connects to a robot.
    """

    lab: str = ""
    rope: int | str = 1
    seed: int = 0
    settle_s: float | None = None
    ropes: str | None = None
    dry_run: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.lab, str) or not self.lab:
            raise ConfigError("cell.lab", "the real lab needs its lab file (--cell FILE)")
        if not isinstance(self.dry_run, bool):
            raise ConfigError("cell.dry_run", f"must be true or false, got {self.dry_run!r}")


def _open_xarm(spec: XArmCellSpec) -> Cell:
    from flyknot_app.hardware import DryRunCell, open_xarm_cell
    from flyknot_hw.config import load_lab_config

    config = load_lab_config(spec.lab)
    if config.rope.key != spec.rope:
        raise ConfigError(
            "rope",
            f"the run needs rope {spec.rope!r} but the lab file {spec.lab!r} says rope "
            f"{config.rope.key!r} is mounted (change [rope] in the lab file when you change "
            "the rope)",
        )
    if spec.dry_run:
        return DryRunCell(config, seed=spec.seed)
    return open_xarm_cell(config)


@dataclass(frozen=True)
class CellKind:
    """One registered kind of cell: its spec class and the factory opening it."""

    name: str
    spec: type
    open: Callable[[Any], Cell]
    description: str
    oracle: Callable[[Any, float], JacobianProvider] | None = None
    """Measures the cell's own M(t) (``jacobian = "oracle"``), or None: it cannot."""

    @property
    def fields(self) -> tuple[str, ...]:
        """Names of the spec's fields (what a ``[cell]`` table may set)."""
        return tuple(f.name for f in fields(self.spec))


CELLS: dict[str, CellKind] = {
    "sim": CellKind("sim", SimCellSpec, _open_sim, "the simulated lab (MuJoCo)", _sim_oracle),
    "xarm": CellKind("xarm", XArmCellSpec, _open_xarm, "a real xArm 7 with motion capture"),
}
"""Every kind of cell, by the name a scenario's ``[cell] kind`` gives."""


def cell_kind(name: object) -> CellKind:
    """The registered kind ``name``; the error lists the valid kinds."""
    if not isinstance(name, str) or name not in CELLS:
        raise ConfigError("cell.kind", f"unknown cell kind {name!r}", sorted(CELLS))
    return CELLS[name]


def cell_spec(kind: str, values: Mapping[str, Any]) -> Any:
    """A validated spec of ``kind`` from ``values`` (unknown fields are named, valid listed)."""
    k = cell_kind(kind)
    for key in values:
        if key not in k.fields:
            raise ConfigError(f"cell.{key}", f"not a field of a {kind!r} cell", k.fields)
    return k.spec(**values)


def open_cell(kind: str, spec: Any) -> Cell:
    """Open the cell ``spec`` of ``kind`` (a spec made by :func:`cell_spec`)."""
    k = cell_kind(kind)
    if not isinstance(spec, k.spec):
        raise ConfigError("cell", f"a {kind!r} cell needs a {k.spec.__name__}, got {spec!r}")
    return k.open(spec)


def check_oracle(kind: str, *, dry_run: bool = False) -> None:
    """Refuse the oracle Jacobian on a cell that cannot measure it (before anything runs).

    Raises:
        ConfigError: ``jacobian = "oracle"`` on such a cell, naming the kinds that can.
    """
    able = sorted(name for name, k in CELLS.items() if k.oracle is not None)
    if cell_kind(kind).oracle is None or dry_run:
        raise ConfigError(
            "jacobian",
            f"'oracle' replays commands without variation, which only a simulated lab can; "
            f"this run's cell is {kind!r}{' (dry run)' if dry_run else ''}",
            able,
        )


def oracle_provider(kind: str, spec: Any, t_c: float) -> JacobianProvider:
    """The oracle Jacobian of the cell ``spec`` of ``kind`` at the critical time ``t_c`` [s]."""
    check_oracle(kind, dry_run=bool(getattr(spec, "dry_run", False)))
    return cell_kind(kind).oracle(spec, t_c)

"""The linearised limit rows of the inverse-model QP as data: ``lo <= b - J dkappa <= hi``.

:mod:`learner.limit_rows` builds and selects them; :func:`learner.inverse_qp.build_inverse_qp`
turns them into the QP's constraint blocks. This module holds only the container, so that
neither of those imports the other's container.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from flyknot.constants import N_VARS
from flyknot.errors import ConfigError
from flyknot.geometry import readonly


@dataclass(frozen=True)
class LimitRows:
    """Linearised limits ``lo <= b - J dkappa <= hi`` on the updated command.

    Attributes:
        J: Knot Jacobians of the limited quantities (r, 80).
        b: Their values at the current knots (r,).
        lo: Lower bounds (r,) (may be -inf).
        hi: Upper bounds (r,) (may be +inf).
        blocks: Named row ranges ``name -> (start, stop)``.
    """

    J: np.ndarray
    b: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    blocks: Mapping[str, tuple[int, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        J = np.asarray(self.J, dtype=float)
        if J.ndim != 2 or J.shape[1] != N_VARS:
            raise ConfigError("J", f"must have shape (r, {N_VARS}), got {J.shape}")
        r = J.shape[0]
        for name in ("b", "lo", "hi"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (r,):
                raise ConfigError(name, f"must have shape ({r},), got {a.shape}")
            if np.any(np.isnan(a)):
                raise ConfigError(name, "must not contain NaN")
            object.__setattr__(self, name, readonly(a))
        for name, a in (("J", J), ("b", self.b)):
            if not np.all(np.isfinite(a)):
                raise ConfigError(name, "must be finite")
        if np.any(self.lo > self.hi):
            raise ConfigError("lo", "must be <= hi in every row")
        blocks = dict(self.blocks) if self.blocks else {"limits": (0, r)}
        for name, (a, z) in blocks.items():
            if not 0 <= a <= z <= r:
                raise ConfigError("blocks", f"range {name!r} = ({a}, {z}) outside 0..{r}")
        object.__setattr__(self, "J", readonly(J))
        object.__setattr__(self, "blocks", MappingProxyType(blocks))

    @property
    def n_rows(self) -> int:
        """Number of limit rows."""
        return int(self.J.shape[0])


__all__ = ["LimitRows"]

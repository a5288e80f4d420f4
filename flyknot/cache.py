"""Where flyknot keeps what a machine computes once and reuses (compiled robot functions,
initial guesses): ``$FLYKNOT_CACHE``, else ``$XDG_CACHE_HOME/flyknot``, else
``~/.cache/flyknot``."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_root"]


def cache_root() -> Path:
    """The cache's root directory (not created here)."""
    root = os.environ.get("FLYKNOT_CACHE")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return Path(xdg or Path.home() / ".cache") / "flyknot"

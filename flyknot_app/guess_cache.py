"""Initial guesses kept on disk: in a run directory (``initial_guess/``, by a readable name)
and in the machine's cache (:func:`flyknot.cache.cache_root`, ``initial_guess/``, by a key
naming every input, :func:`guess_key`)."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from flyknot.constants import FOLLOW_THROUGH_S, PATH_FRAC
from flyknot.record import atomic_save_npz

__all__ = ["cached_guess", "guess_cache_name", "guess_key", "store_guess"]


def guess_cache_name(demo_name: str, window: tuple[float, float], base_height: float) -> str:
    """File name of a cached initial guess: the demo's stem, the window when it is not the
    paper's, and the robot base's height [m] (the guess keeps the fingertip z_min above the
    floor, so a lab with another base height needs its own)."""
    stem = Path(demo_name).stem
    if tuple(window) != (FOLLOW_THROUGH_S, PATH_FRAC):
        stem += f"_ft{window[0]:g}_p{window[1]:g}"
    return f"{stem}_base{base_height:.4f}.npz"


def guess_key(
    demo_sha256: str,
    window: tuple[float, float],
    rope_dt: float,
    params: Any,
    robot: Any,
    solver: Any,
) -> str:
    """The key of an initial guess in the machine's cache (:func:`flyknot.cache.cache_root`,
    ``initial_guess/``): a digest of everything the guess is computed from — the
    demonstration file's content, the window, the model step, the guess's parameters (the
    base height among them), the robot model (its CasADi kinematics and dynamics, serialised;
    the shipped xArm 7 file for None), the function that makes it (a stand-in makes its own
    entries), the machine class and CasADi's version, and the source of the learner and the
    core it uses, so that a change of any of them makes the guess again."""
    import casadi

    import flyknot
    import learner
    from flyknot.constants import XARM7_XML
    from flyknot.numerics import numerics_class

    h = hashlib.sha256()
    parts = [
        demo_sha256,
        repr(tuple(float(w) for w in window)),
        repr(float(rope_dt)),
        repr(params),
        f"{solver.__module__}.{solver.__qualname__}",
        numerics_class(),
        casadi.__version__,
    ]
    for part in parts:
        h.update(part.encode() + b"\0")
    if robot is None:
        h.update(Path(XARM7_XML).read_bytes())
    else:
        h.update(robot.fk.serialize().encode() + robot.inverse_dynamics.serialize().encode())
    for pkg in (flyknot, learner):
        for f in sorted(Path(pkg.__file__).parent.glob("*.py")):
            h.update(f.read_bytes())
    return h.hexdigest()[:32]


def cached_guess(path: Path) -> tuple[np.ndarray, dict] | None:
    """A cached initial guess, or None when it is absent or unreadable (made again); the
    caller checks that it was made from the same demonstration file (``demo_sha256``)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return z["knots"], json.loads(str(z["info"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def store_guess(path: Path, knots: np.ndarray, info: dict) -> None:
    """Write a guess where :func:`cached_guess` reads it (atomically, the directory made)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_save_npz(path, {"knots": knots, "info": np.array(json.dumps(info))})

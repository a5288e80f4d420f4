"""The machine class a simulated result is bit-reproducible on.

The lab's trials are the same bit for bit when played again on one machine, but not across
machines whose numerical kernels differ: NumPy and Numba pick their vector code at run time
from the CPU (AVX-512 or AVX2 code paths round differently in the last bit), OpenBLAS picks
its kernel set at load time from what it recognises of the CPU (an AVX-512 CPU it does not
know gets its ``Haswell`` kernels), MuJoCo's constraint solver stops at its tolerance after a
number of iterations that a last-bit change can move (1e-8-level differences), and the rope's
motion, being chaotic, grows such differences into another sample of the lab (another settle
length, at times another verdict), as a change of seed would. Stored bit-level references (the
lab's fingerprints, the shipped demonstrations' recordings) therefore name the class they were
made on: the widest vector extension NumPy dispatches to (Numba compiles for the same CPU
features) and OpenBLAS's kernel set.
"""

from __future__ import annotations

import ctypes
import functools
import platform
from pathlib import Path

__all__ = ["numerics_class"]

_CORENAME_SYMBOLS = (
    "scipy_openblas_get_corename64_",  # NumPy's wheels (scipy-openblas64)
    "scipy_openblas_get_corename",
    "openblas_get_corename64_",
    "openblas_get_corename",
)
"""The names OpenBLAS builds give the function that says which kernel set was picked."""


def _numpy_cpu_features() -> dict[str, bool]:
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:  # NumPy 1.x
        from numpy.core._multiarray_umath import __cpu_features__
    return dict(__cpu_features__)


def _bundled_openblas() -> list[Path]:
    """The OpenBLAS libraries shipped inside NumPy's wheel (Linux, Windows: ``numpy.libs``;
    macOS: ``numpy/.dylibs``)."""
    import numpy as np

    package = Path(np.__file__).parent
    found = [*package.parent.glob("numpy.libs/*openblas*"), *package.glob(".dylibs/*openblas*")]
    return sorted(found)


@functools.cache
def _openblas_core() -> str | None:
    """The kernel set NumPy's OpenBLAS runs on, lower case (``haswell``, ``skylakex``,
    ``neoversen1``, ...; ``OPENBLAS_CORETYPE`` sets it), or None when NumPy's BLAS is not an
    OpenBLAS that says."""
    for path in _bundled_openblas():
        try:
            lib = ctypes.CDLL(str(path))
        except OSError:
            continue
        for name in _CORENAME_SYMBOLS:
            corename = getattr(lib, name, None)
            if corename is not None:
                corename.restype = ctypes.c_char_p
                return corename().decode().strip().lower() or None
    return None


def _vector_extension(machine: str) -> str | None:
    """The widest vector extension NumPy dispatches to on x86-64 (``avx512``, ``avx2`` or
    ``base``); None elsewhere."""
    if machine not in ("x86_64", "amd64"):
        return None
    features = _numpy_cpu_features()
    if features.get("AVX512F"):
        return "avx512"
    if features.get("AVX2") and features.get("FMA3"):
        return "avx2"
    return "base"


def numerics_class() -> str:
    """``<machine>[-<vector extension>][-<OpenBLAS kernel set>]``, e.g.
    ``x86_64-avx2-haswell`` or ``aarch64-neoversen1``: the vector extension on x86-64 only,
    the kernel set where NumPy's OpenBLAS names it."""
    machine = platform.machine().lower() or "unknown"
    parts = [machine, _vector_extension(machine), _openblas_core()]
    return "-".join(p for p in parts if p)

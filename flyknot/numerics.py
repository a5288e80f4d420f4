"""The machine class a simulated result is bit-reproducible on.

The lab's trials are the same bit for bit when played again on one machine, but not across
CPUs of different vector extensions: NumPy's and OpenBLAS's kernels are chosen at run time by
the CPU (AVX-512 or AVX2 code paths round differently in the last bit), MuJoCo's constraint
solver stops at its tolerance after a number of iterations that a last-bit change can move
(1e-8-level differences), and the rope's motion, being chaotic, grows such differences into
another sample of the lab (another settle length, at times another verdict), as a change of
seed would. Stored bit-level references (the lab's fingerprints, the shipped demonstrations'
recordings) therefore name the class they were made on.
"""

from __future__ import annotations

import platform

__all__ = ["numerics_class"]


def _numpy_cpu_features() -> dict[str, bool]:
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:  # NumPy 1.x
        from numpy.core._multiarray_umath import __cpu_features__
    return dict(__cpu_features__)


def numerics_class() -> str:
    """``<machine>-<widest vector extension NumPy dispatches to>``, e.g. ``x86_64-avx2``
    (``avx512``, ``avx2`` or ``base`` on x86-64; the machine alone elsewhere)."""
    machine = platform.machine().lower() or "unknown"
    if machine not in ("x86_64", "amd64"):
        return machine
    features = _numpy_cpu_features()
    if features.get("AVX512F"):
        return f"{machine}-avx512"
    if features.get("AVX2") and features.get("FMA3"):
        return f"{machine}-avx2"
    return f"{machine}-base"

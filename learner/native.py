"""CasADi SX functions as native code: a batch of evaluations in one call.

A mapped CasADi function evaluates its expression graph instruction by instruction in
CasADi's virtual machine, one sample at a time. For the robot model's inverse dynamics and its
derivatives (2,000-19,000 instructions a sample, a few hundred samples an ILC update) that
interpreter is most of the update's time in CasADi. :func:`compile_batch` writes the function
as C with CasADi's code generator, adds a loop over a batch of samples, compiles it with the
system's C compiler and loads it with :mod:`ctypes`.

The generated C performs the graph's operations in the virtual machine's order and in IEEE
double arithmetic (``-ffp-contract=off``: no fused multiply-add), so its outputs are the
interpreter's bit for bit (``tests/test_native.py`` checks every function of the robot model).
A compiled library is cached by the SHA-256 of its source and compiler command
(``$FLYKNOT_CACHE`` or ``~/.cache/flyknot``, ``native/``), so each machine compiles a function
once. Without a C compiler :func:`compile_batch` raises :class:`NativeUnavailableError` and the
caller keeps the interpreter.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from flyknot.cache import cache_root
from flyknot.errors import ConfigError, FlyknotError

__all__ = ["NativeBatch", "NativeUnavailableError", "cache_dir", "compile_batch"]

CFLAGS = ("-O2", "-fPIC", "-shared", "-ffp-contract=off")
"""Compiler flags: optimised, position independent, no contraction of a*b+c into one FMA."""

_ENTRY = "flyknot_batch"


class NativeUnavailableError(FlyknotError):
    """No C compiler, or it failed: the function stays in CasADi's interpreter."""


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``native/`` under :func:`flyknot.cache.cache_root`
    (``$FLYKNOT_CACHE``, else ``$XDG_CACHE_HOME/flyknot``, else ``~/.cache/flyknot``)."""
    return cache_root() / "native"


def _compiler() -> str:
    """The C compiler: ``$CC`` or ``cc`` on the PATH."""
    cc = os.environ.get("CC", "cc")
    path = shutil.which(cc)
    if path is None:
        raise NativeUnavailableError(f"no C compiler {cc!r} on the PATH (set CC to one)")
    return path


def _dense(fun: ca.Function) -> ca.Function:
    """``fun`` with every input and output dense (structural zeros written as zeros)."""
    if not fun.is_a("SXFunction"):
        raise NativeUnavailableError(f"{fun.name()} is not an SX function")
    x = [ca.SX.sym(f"x{i}", fun.sparsity_in(i).numel()) for i in range(fun.n_in())]
    args = [ca.reshape(xi, fun.size1_in(i), fun.size2_in(i)) for i, xi in enumerate(x)]
    args = [ca.project(a, fun.sparsity_in(i)) for i, a in enumerate(args)]
    outs = [ca.densify(ca.vec(y)) for y in fun.call(args)]
    return ca.Function(fun.name(), x, outs)


def _source(fun: ca.Function) -> str:
    """C source: CasADi's code for ``fun`` and a loop of it over a batch of samples.

    ``flyknot_batch(x, y, m)`` reads input i of sample s at ``x[i] + s * n_in_i`` and writes
    output j at ``y[j] + s * n_out_j`` (row-major (m, n) arrays); it returns the first
    sample's index whose evaluation failed, or -1.
    """
    with tempfile.TemporaryDirectory() as tmp:
        gen = ca.CodeGenerator("fun.c", {"with_header": False, "casadi_real": "double"})
        gen.add(fun)
        body = Path(gen.generate(tmp + os.sep)).read_text()
    n_in = [fun.nnz_in(i) for i in range(fun.n_in())]
    n_out = [fun.nnz_out(j) for j in range(fun.n_out())]
    set_args = "".join(f"    arg[{i}] = x[{i}] + s * {n};\n" for i, n in enumerate(n_in))
    set_res = "".join(f"    res[{j}] = y[{j}] + s * {n};\n" for j, n in enumerate(n_out))
    loop = (
        f"\nlong long {_ENTRY}(const double** x, double** y, long long m) {{\n"
        f"  const double* arg[{fun.sz_arg()}];\n"
        f"  double* res[{fun.sz_res()}];\n"
        f"  casadi_int iw[{fun.sz_iw() + 1}];\n"
        f"  double w[{fun.sz_w() + 1}];\n"
        "  for (long long s = 0; s < m; ++s) {\n"
        f"{set_args}{set_res}"
        f"    if ({fun.name()}(arg, res, iw, w, 0)) return s;\n"
        "  }\n"
        "  return -1;\n"
        "}\n"
    )
    return body + loop


def _build(source: str, cc: str, target: Path) -> None:
    """Compile ``source`` into the shared library ``target`` (written atomically)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        src, lib = Path(tmp) / "fun.c", Path(tmp) / target.name
        src.write_text(source)
        done = subprocess.run(
            [cc, *CFLAGS, str(src), "-o", str(lib), "-lm"], capture_output=True, text=True
        )
        if done.returncode != 0:
            raise NativeUnavailableError(f"{cc} failed: {done.stderr.strip()[-400:]}")
        os.replace(lib, target)


@dataclass(frozen=True)
class NativeBatch:
    """A compiled batch evaluation of one CasADi function.

    Attributes:
        name: The CasADi function's name.
        n_in: Entries of each input (numel, column-major as CasADi stores them).
        n_out: Entries of each output (numel, dense).
        path: The shared library.
    """

    name: str
    n_in: tuple[int, ...]
    n_out: tuple[int, ...]
    path: Path
    _fn: object

    def __call__(self, *inputs: np.ndarray) -> list[np.ndarray]:
        """Evaluate every sample: inputs (m, n_in_i) each, outputs (m, n_out_j) each."""
        xs = [np.ascontiguousarray(x, dtype=float) for x in inputs]
        m = xs[0].shape[0]
        for i, (x, n) in enumerate(zip(xs, self.n_in, strict=True)):
            if x.shape != (m, n):
                raise ConfigError(f"{self.name} input {i}", f"expected ({m}, {n}), got {x.shape}")
        ys = [np.empty((m, n)) for n in self.n_out]
        xp = (ctypes.c_void_p * len(xs))(*(x.ctypes.data for x in xs))
        yp = (ctypes.c_void_p * len(ys))(*(y.ctypes.data for y in ys))
        failed = self._fn(xp, yp, m)
        if failed >= 0:
            raise NativeUnavailableError(f"{self.name} failed at sample {failed}")
        return ys


def compile_batch(fun: ca.Function, cache: Path | None = None) -> NativeBatch:
    """``fun`` (an SX function) compiled for batches, from the cache when it is there.

    Args:
        fun: The function; inputs and outputs are evaluated dense.
        cache: Directory of compiled libraries (default :func:`cache_dir`).

    Returns:
        The batch evaluator; its outputs equal ``fun.map(m)``'s bit for bit.

    Raises:
        NativeUnavailableError: ``fun`` is not an SX function, or no C compiler could build it.
    """
    dense = _dense(fun)
    cc = _compiler()
    source = _source(dense)
    key = hashlib.sha256("\0".join([source, cc, *CFLAGS]).encode()).hexdigest()[:24]
    path = (cache or cache_dir()) / f"{dense.name()}-{key}.so"
    if not path.is_file():
        try:
            _build(source, cc, path)
        except OSError as exc:
            raise NativeUnavailableError(f"cannot write {path}: {exc}") from exc
    fn = ctypes.CDLL(str(path))[_ENTRY]
    fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_longlong]
    fn.restype = ctypes.c_longlong
    n_in = tuple(dense.nnz_in(i) for i in range(dense.n_in()))
    n_out = tuple(dense.nnz_out(j) for j in range(dense.n_out()))
    return NativeBatch(dense.name(), n_in, n_out, path, fn)

"""Compiled kernels: numba's njit where numba is installed, plain Python where it is not.

The fusion hot path works on arrays of 3..60 numbers, where numpy's
per-call overhead (several microseconds for one ufunc on a 4x3 array), not
arithmetic, sets the cost. Those steps are written as explicit loops and
compiled by numba (cached on disk after the first run). Without numba (no
wheel for the platform, e.g. 32-bit ARM) the same functions run as Python:
correct, only slower; `COMPILED` says which.
"""

from __future__ import annotations

import logging
import os
from typing import Callable, TypeVar

import numpy as np

F = TypeVar("F", bound=Callable)

def _sources_stamp() -> str:
    """A digest of every source file a kernel can inline (the visionpos, bridge and stations packages: names,
    sizes, modification times)."""
    import hashlib
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha1()
    for pkg in ("visionpos", "bridge", "stations"):
        for f in sorted((root / pkg).rglob("*.py")):
            st = f.stat()
            h.update(f"{f.relative_to(root)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def _cache_dir() -> str:
    """numba's cache for this exact source tree. numba keys a cached kernel on its own file only, so a kernel
    that inlines a function from another module (most of them) would otherwise keep the old code after that
    module changed, an upgrade included. Under $NUMBA_CACHE_DIR (else ~/.cache/visionpos/numba), one
    folder per source stamp; older folders are removed, keeping the three newest."""
    import shutil
    from pathlib import Path

    base = Path(os.environ.get("NUMBA_CACHE_DIR") or
                Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "visionpos" / "numba")
    here = base / _sources_stamp()
    try:
        here.mkdir(parents=True, exist_ok=True)
        here.touch()
        old = sorted((d for d in base.iterdir() if d.is_dir() and d != here), key=lambda d: d.stat().st_mtime)
        for d in old[:-2]:
            shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass  # not writable: numba says so when it tries, and the kernels compile uncached
    return str(here)


try:
    if os.environ.get("VISIONPOS_NO_JIT"):  # for testing the interpreted path
        raise ImportError("VISIONPOS_NO_JIT is set")
    import numba
    from numba import njit as _njit

    numba.config.CACHE_DIR = _cache_dir()
    COMPILED = True

    def njit(fn: F) -> F:
        """Compile fn in nopython mode, cached on disk. No fastmath: results stay IEEE-exact.
        numpy's error model: a division by zero gives inf / NaN as in numpy, never an exception
        in the middle of a fusion."""
        try:
            return _njit(cache=True, nogil=True, error_model="numpy")(fn)
        except RuntimeError as e:  # numba finds no writable cache directory (read-only install, no home)
            if not _uncached:
                _uncached.append(fn.__qualname__)
                logging.getLogger(__name__).warning(
                    "numba cannot cache the compiled kernels (%s): they compile on every start; "
                    "set NUMBA_CACHE_DIR to a writable directory", e)
            return _njit(nogil=True, error_model="numpy")(fn)

    _uncached: list[str] = []

except ImportError:
    COMPILED = False

    def njit(fn: F) -> F:
        return fn


# Building blocks for the kernels. numba's `@` and np.cross go through generic
# BLAS / broadcasting code that costs seconds to compile and microseconds per
# call on 3-vectors; these are the loops written out. cross3 is also the
# single-vector cross product outside the kernels (bridge/convert.py); rotation
# helpers live in visionpos/geometry/rotations.py.


@njit
def matmul3(A, B):
    """(3, 3) @ (3, 3) -> (3, 3) (either may be a transposed view)."""
    C = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
    return C


@njit
def matvec3(A, v):
    """(3, 3) @ (3,) -> (3,)."""
    out = np.empty(3)
    for i in range(3):
        out[i] = A[i, 0] * v[0] + A[i, 1] * v[1] + A[i, 2] * v[2]
    return out


@njit
def cross3(a, b):
    """(3,) x (3,) -> (3,)."""
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit
def dot3(a, b):
    """(3,) . (3,) -> float."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

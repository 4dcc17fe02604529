"""Compiled kernels: numba's njit where numba is installed, plain Python where it is not.

The fusion hot path works on arrays of 3..60 numbers, where numpy's
per-call overhead (several microseconds for one ufunc on a 4x3 array), not
arithmetic, sets the cost. Those steps are written as explicit loops and
compiled by numba (cached on disk after the first run). Without numba (no
wheel for the platform, e.g. 32-bit ARM) the same functions run as Python:
correct, only slower; `COMPILED` says which.

The on-disk cache is keyed per module on the content of the modules its kernels can inline
(`module_key`), so editing any other file recompiles nothing. While a first compilation runs in
the background (fusion/warmup.py), `interpret()` makes every kernel run as Python and `use_compiled()`
switches them back: the two paths give the same numbers (tests/fusion/test_kernels.py).
"""

from __future__ import annotations

import ast
import hashlib
import logging
import os
import sys
import types
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

F = TypeVar("F", bound=Callable)

_ROOTS = ("visionpos", "bridge", "stations")  # the packages whose modules a kernel can inline
_KEEP_KEYS = 3  # cache folders kept per module (the newest; older ones are removed)
_module_keys: dict[str, str] = {}  # module -> module_key, computed once per process


def _imported_names(tree: ast.Module, package: str) -> list[tuple[str, str, str | None]]:
    """The module-level imports of a parsed module: (bound name, source module, attribute or None for a
    module), relative imports resolved against `package`. Imports inside functions bind no global."""
    out: list[tuple[str, str, str | None]] = []

    def visit(stmts: list[ast.stmt]) -> None:
        for node in stmts:
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.asname:
                        out.append((a.asname, a.name, None))
                    else:  # `import a.b` binds a, and a kernel may reach a.b
                        out.append((a.name.split(".")[0], a.name, None))
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                for a in node.names:
                    out.append((a.asname or a.name, base, a.name))
            elif isinstance(node, (ast.If, ast.Try)):
                visit(node.body)
                visit(node.orelse)
                for h in getattr(node, "handlers", []):
                    visit(h.body)
                visit(getattr(node, "finalbody", []))

    visit(tree.body)
    return out


def _freezable(value: object) -> bool:
    """Whether numba can take this global into a kernel (it freezes constants, calls kernels, reads modules)."""
    return (isinstance(value, (int, float, complex, str, bytes, tuple, slice, np.ndarray, np.generic,
                               types.ModuleType)) or hasattr(value, "py_func"))


def _dependencies(name: str, roots: tuple[str, ...], seen: dict[str, bytes]) -> None:
    """Add module `name` and, recursively, every module of `roots` it takes a kernel-visible global from
    (a constant, a kernel, a module) to seen: module -> its source bytes."""
    if name in seen or name.split(".")[0] not in roots:
        return
    mod = sys.modules.get(name)
    path = getattr(mod, "__file__", None)
    if mod is None or not path:
        return
    source = Path(path).read_bytes()
    seen[name] = source
    package = name if path.endswith("__init__.py") else name.rpartition(".")[0]
    for bound, source_module, attr in _imported_names(ast.parse(source), package):
        value = vars(mod).get(bound)
        if attr is None:
            _dependencies(source_module, roots, seen)
        elif isinstance(value, types.ModuleType):
            _dependencies(value.__name__, roots, seen)
        elif _freezable(value):
            _dependencies(source_module, roots, seen)


def module_key(name: str, roots: tuple[str, ...] = _ROOTS) -> str:
    """The cache key of the kernels of module `name` (imported): a digest of the content of that module and
    of every module (of the packages `roots`) it takes a constant, a kernel or a module from, recursively:
    what numba can inline into its kernels. numba itself checks only a kernel's own file."""
    if name not in _module_keys:
        seen: dict[str, bytes] = {}
        _dependencies(name, roots, seen)
        h = hashlib.sha1()
        for dep in sorted(seen):
            h.update(f"{dep}:{hashlib.sha1(seen[dep]).hexdigest()};".encode())
        _module_keys[name] = h.hexdigest()[:16]
    return _module_keys[name]


def cache_base() -> Path:
    """numba's cache root: $NUMBA_CACHE_DIR, else ~/.cache/visionpos/numba."""
    return Path(os.environ.get("NUMBA_CACHE_DIR") or
                Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "visionpos" / "numba")


def _cache_dir(module: str) -> str:
    """The cache folder of one module's kernels, `<module>-<module_key>` under cache_base(); of the folders
    of the same module the _KEEP_KEYS newest are kept."""
    import shutil

    module = module or "__main__"  # a function made by exec() has no module
    base = cache_base()
    here = base / f"{module}-{module_key(module)}"
    try:
        here.mkdir(parents=True, exist_ok=True)
        here.touch()
        if not _module_keys.get("", ""):  # once per process: the folders of the old layout (one per tree)
            _module_keys[""] = "cleaned"
            for d in base.iterdir():
                if d.is_dir() and len(d.name) == 16 and all(c in "0123456789abcdef" for c in d.name):
                    shutil.rmtree(d, ignore_errors=True)
        old = sorted((d for d in base.glob(f"{module}-*") if d.is_dir() and d != here
                      and len(d.name) == len(here.name)), key=lambda d: d.stat().st_mtime)
        for d in old[: max(len(old) - (_KEEP_KEYS - 1), 0)]:
            shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass  # not writable: numba says so when it tries, and the kernels compile uncached
    return str(here)


_kernels: list = []  # every dispatcher njit made, for interpret() / use_compiled() and the warm-up's signatures

try:
    if os.environ.get("VISIONPOS_NO_JIT"):  # for testing the interpreted path
        raise ImportError("VISIONPOS_NO_JIT is set")
    import numba
    from numba import njit as _njit
    from numba.core.registry import CPUDispatcher

    COMPILED = True

    class _Interpreted(CPUDispatcher):
        """A kernel that runs its Python function (interpret()): numba still types and compiles it as a
        callee of other kernels; only calls from Python run interpreted."""

        def __call__(self, *args, **kwargs):
            _depth[0] += 1
            try:
                return self.py_func(*args, **kwargs)
            finally:
                _depth[0] -= 1
                if _switch[0] and not _depth[0]:
                    _switch_now()

    def njit(fn: F) -> F:
        """Compile fn in nopython mode, cached on disk. No fastmath: results stay IEEE-exact.
        numpy's error model: a division by zero gives inf / NaN as in numpy, never an exception
        in the middle of a fusion."""
        numba.config.CACHE_DIR = _cache_dir(fn.__module__)
        try:
            d = _njit(cache=True, nogil=True, error_model="numpy")(fn)
        except RuntimeError as e:  # numba finds no writable cache directory (read-only install, no home)
            if not _uncached:
                _uncached.append(fn.__qualname__)
                logging.getLogger(__name__).warning(
                    "numba cannot cache the compiled kernels (%s): they compile on every start; "
                    "set NUMBA_CACHE_DIR to a writable directory", e)
            d = _njit(nogil=True, error_model="numpy")(fn)
        if _interpreting[0]:
            d.__class__ = _Interpreted
        _kernels.append(d)
        return d

    _uncached: list[str] = []
    _interpreting = [False]
    _depth = [0]  # interpreted kernels on the stack (calls from Python and their nested calls)
    _switch = [False]  # use_compiled() came while a kernel ran interpreted: switch when the outermost returns

    def interpret() -> None:
        """From now on every kernel called from Python runs as Python (the same numbers, slower) until
        use_compiled(): what a live server does while its kernels compile in the background."""
        _interpreting[0] = True
        for d in _kernels:
            d.__class__ = _Interpreted

    def use_compiled() -> None:
        """Undo interpret(): calls from Python run the compiled kernels again (compiled or loaded from the
        cache on their first call with new argument types). Called (from another thread) while a kernel
        runs interpreted, the switch waits until the outermost one returns: a kernel's interpreted body
        would call the compiled callees with the argument types Python gives, which can differ from those
        compiled (a non-contiguous view, a Python int), and compile them then."""
        if _depth[0]:
            _switch[0] = True
        else:
            _switch_now()

    def use_compiled_for(kernels: list) -> None:
        """Run these kernels compiled from now on (the others stay as interpret() left them); for argument
        types Python gives them, so compile (or load) them for those first."""
        for d in kernels:
            d.__class__ = CPUDispatcher

    def _switch_now() -> None:
        _switch[0] = False
        _interpreting[0] = False
        for d in _kernels:
            d.__class__ = CPUDispatcher

    def interpreting() -> bool:
        """Whether interpret() is in force."""
        return _interpreting[0]

except ImportError:
    COMPILED = False

    def njit(fn: F) -> F:
        return fn

    def interpret() -> None:
        """Without numba everything runs as Python already."""

    def use_compiled() -> None:
        """Without numba everything runs as Python."""

    def interpreting() -> bool:
        return False

    def use_compiled_for(kernels: list) -> None:
        """Without numba everything runs as Python."""


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

"""visionpos/jit.py: the compile shim and its small linear-algebra building blocks."""

import logging

import numpy as np
import pytest

from visionpos import jit


def test_building_blocks_match_numpy():
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    a, b = rng.normal(size=3), rng.normal(size=3)
    assert np.allclose(jit.matmul3(A, B), A @ B, atol=1e-15)
    assert np.allclose(jit.matmul3(A, B.T), A @ B.T, atol=1e-15)
    assert np.allclose(jit.matvec3(A, a), A @ a, atol=1e-15)
    assert np.allclose(jit.cross3(a, b), np.cross(a, b), atol=1e-15)
    assert jit.dot3(a, b) == pytest.approx(float(a @ b), abs=1e-15)


def test_a_function_numba_cannot_cache_still_compiles(caplog):
    """A function with no source file has no cache locator (as a read-only install with no
    writable home): the shim compiles it uncached and says how to fix it, instead of failing."""
    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    jit._uncached.clear()
    ns: dict = {}
    exec("def add_one(x):\n    return x + 1\n", ns)
    with caplog.at_level(logging.WARNING, logger="visionpos.jit"):
        f = jit.njit(ns["add_one"])
    assert f(41) == 42
    assert hasattr(f, "signatures") and f.signatures  # compiled, not the Python function
    assert "NUMBA_CACHE_DIR" in caplog.text


def _write_package(root, consts="N_ROWS = 3\n", other='"""Unrelated."""\n\n\nclass Thing:\n    pass\n'):
    pkg = root / "kpkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "consts.py").write_text(consts)
    (pkg / "other.py").write_text(other)
    (pkg / "kern.py").write_text(
        "from kpkg.consts import N_ROWS\nfrom kpkg.other import Thing\n\n\ndef rows():\n    return N_ROWS\n")


def test_module_key_follows_what_a_kernel_can_inline(tmp_path, monkeypatch):
    """The cache key of a kernel module changes with its own source and with a module it takes a constant
    from, and not with a module it only takes a class from (no kernel can inline that)."""
    import importlib

    _write_package(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("kpkg", "kpkg.consts", "kpkg.other", "kpkg.kern"):
        monkeypatch.delitem(__import__("sys").modules, name, raising=False)
    importlib.import_module("kpkg.kern")

    def key():
        monkeypatch.setattr(jit, "_module_keys", {})
        return jit.module_key("kpkg.kern", roots=("kpkg",))

    k0 = key()
    assert key() == k0  # deterministic
    (tmp_path / "kpkg" / "other.py").write_text('"""Edited doc-string."""\n\n\nclass Thing:\n    pass\n')
    assert key() == k0
    (tmp_path / "kpkg" / "consts.py").write_text("N_ROWS = 4\n")
    k1 = key()
    assert k1 != k0
    kern = tmp_path / "kpkg" / "kern.py"
    kern.write_text(kern.read_text() + "# a comment\n")
    assert key() not in (k0, k1)


def test_the_fusion_kernels_key_covers_their_modules_only():
    """visionpos.fusion.kernels inlines the layout's offsets (made from fusion/settings.py's parameter tables, so
    that module is in the key too) and the tracking, matching, camera and rotation kernels; the pipeline, the
    warm-up, the config layer and the bridge are Python only and stay out of its key."""
    import visionpos.fusion.pipeline  # noqa: F401

    seen: dict = {}
    jit._dependencies("visionpos.fusion.kernels", jit._ROOTS, seen)
    for inlined in ("visionpos.fusion.kernels", "visionpos.fusion.layout", "visionpos.fusion.tracking",
                    "visionpos.fusion.matching", "visionpos.camera.pinhole", "visionpos.camera.fisheye",
                    "visionpos.camera.model", "visionpos.geometry.rotations", "visionpos.geometry.alignment",
                    "visionpos.jit", "visionpos.fusion.settings"):
        assert inlined in seen
    for python_only in ("visionpos.fusion.pipeline", "visionpos.fusion.warmup",
                        "visionpos.config.arena", "visionpos.messages"):
        assert python_only not in seen
    assert not any(m.startswith(("bridge", "stations")) for m in seen)


@jit.njit
def _halve(x):
    return x / 2.0


def test_interpret_runs_python_until_use_compiled():
    """interpret(): calls from Python run the Python function (nothing compiles); use_compiled() switches back.
    Both give the same number."""
    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    try:
        jit.interpret()
        assert jit.interpreting()
        assert _halve(3.0) == 1.5
        assert not _halve.signatures  # ran as Python
    finally:
        jit.use_compiled()
    assert not jit.interpreting()
    assert _halve(3.0) == 1.5
    assert _halve.signatures


@jit.njit
def _outer(x):
    return _halve(x) + 1.0


def test_use_compiled_during_an_interpreted_call_waits_for_it_to_return():
    """A switch asked for while a kernel runs interpreted (the compile watcher's thread) happens when the
    outermost interpreted call returns, never between its nested calls."""
    if not jit.COMPILED:
        pytest.skip("numba is not installed")
    seen = []
    py_halve = _halve.py_func

    def halve_and_ask(x):  # the nested call asks for the switch, then looks whether it happened
        jit.use_compiled()
        seen.append(jit.interpreting())
        return py_halve(x)

    try:
        jit.interpret()
        _halve.py_func = halve_and_ask
        assert _outer(3.0) == 2.5
        assert seen == [True]  # still interpreted inside the call
        assert not jit.interpreting()  # switched when _outer returned
    finally:
        _halve.py_func = py_halve
        jit.use_compiled()

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

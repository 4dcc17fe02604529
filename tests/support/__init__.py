"""Inputs that only the tests build (never shipped): `from tests.support.calibration import ring_cameras`.

Importable because the suite runs as `python -m pytest` from the repository root (.ci/run).
"""

"""The `visionpos` command line: one module per command, each a thin layer over library functions.

The application layer: it may import everything; nothing in the core imports it.
"""

# `from visionpos.cli import main` keeps working for scripts and tests written before the package
from visionpos.cli.main import main

__all__ = ["main"]

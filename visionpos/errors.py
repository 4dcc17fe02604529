"""The root of every error visionpos reports to a user.

A `VisionposError` is a problem with the user's input or environment (a config key, a packet,
a recording, a calibration, a camera model): the CLI prints it as one line and exits 2. Any
other exception is a bug and shows its traceback. Subclasses live beside the code that raises
them (ConfigError in config/, ProtocolError in protocol/, ...).
"""

from __future__ import annotations


class VisionposError(Exception):
    """A user-facing error: its message says what is wrong and how to fix it."""


class UsageError(VisionposError):
    """A command-line argument that cannot work (a missing file, an unknown setting, ...)."""

"""Where the ArduPilot SITL binary is: --sitl PATH, the arena's sitl.binary, $VISIONPOS_SITL, or
../shared/sitl/arducopter beside the checkout (for a git worktree: beside its main checkout).
"""

from __future__ import annotations

import os
from pathlib import Path

from visionpos.app.sitl.settings import SHARED_SITL_DIR, SITL
from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.errors import UsageError

SITL_ENV = "VISIONPOS_SITL"
SHARED_BINARY = SHARED_SITL_DIR / "arducopter"  # a checkout beside ../shared (tests, CI)


def default_sitl_binary() -> Path | None:
    """$VISIONPOS_SITL, else ../shared/sitl/arducopter beside the checkout; None when neither is a file."""
    env = os.environ.get(SITL_ENV)
    if env:
        return Path(env) if Path(env).is_file() else None
    return SHARED_BINARY if SHARED_BINARY.is_file() else None


def find_sitl_binary(cli_path: str | None, arena: ArenaConfig | None = None) -> Path:
    """The SITL binary: --sitl PATH, else the arena's sitl.binary, else $VISIONPOS_SITL, else ../shared/sitl."""
    if cli_path:
        p = Path(cli_path)
        if not p.is_file() or not os.access(p, os.X_OK):
            raise UsageError(f"--sitl {cli_path}: no executable file there")
        return p
    if arena is not None:
        sec = SITL.check(arena.section("sitl"))
        configured = SITL.read(sec, "binary")
        if configured:
            p = Path(configured)
            if not p.is_absolute():
                p = Path(arena.source).resolve().parent / p
            if not p.is_file() or not os.access(p, os.X_OK):
                raise ConfigError(arena.source, "sitl.binary", f"{configured!r}: no executable file at {p}; give "
                                  "the path of ArduPilot's arducopter built with `./waf configure --board sitl && "
                                  "./waf copter`")
            return p
    env = os.environ.get(SITL_ENV)
    if env:
        if not Path(env).is_file() or not os.access(env, os.X_OK):
            raise UsageError(f"{SITL_ENV}={env}: no executable file there")
        return Path(env)
    if SHARED_BINARY.is_file():
        return SHARED_BINARY
    raise UsageError("no ArduPilot SITL binary: give --sitl PATH, set sitl.binary in the arena file or "
                     f"{SITL_ENV}=PATH (build it from ArduPilot with `./waf configure --board sitl && ./waf copter`; "
                     "the binary is build/sitl/bin/arducopter)")

"""ArduPilot SITL as a child process: a free instance (-I) whose ports are free, a fresh temporary
working directory (its eeprom.bin, logs), killed when the run ends, however it ends.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from visionpos.app.sitl.settings import SitlError, SitlSettings


def _ports_free(instance: int) -> bool:
    for port in (5760, 5762, 5763, 5501):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port + 10 * instance))
            except OSError:
                return False
    return True


def free_instance() -> int:
    return free_instances(1)[0]


def free_instances(n: int) -> list[int]:
    """n SITL instances whose ports are all free, the lowest first."""
    found = [i for i in range(1, 200) if _ports_free(i)][:n]
    if len(found) < n:
        raise SitlError(f"not {n} free SITL instances: ports 5770-7763 are taken")
    return found


class ChildProcess:
    """A simulator binary in a fresh temporary working directory, its output in a log file there; close() stops
    it (SIGTERM, then SIGKILL after term_wait_s) and removes the folder. A context manager."""

    term_wait_s = 3.0

    def _start(self, args: list[str], folder_prefix: str, log_name: str, env: dict[str, str] | None = None) -> None:
        self.args = args
        self.folder = tempfile.mkdtemp(prefix=folder_prefix)
        self.log_path = os.path.join(self.folder, log_name)
        self._log = open(self.log_path, "wb")
        try:
            self.proc = subprocess.Popen(self.args, cwd=self.folder, env=env, stdout=self._log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as e:
            self.close()
            raise SitlError(f"could not start {self.args[0]}: {e}") from e

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, n: int = 15) -> str:
        try:
            return "\n".join(Path(self.log_path).read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def close(self) -> None:
        proc = getattr(self, "proc", None)
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(self.term_wait_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(3.0)
        self._log.close()
        self.before_removal()
        shutil.rmtree(self.folder, ignore_errors=True)

    def before_removal(self) -> None:
        """Read what the stopped process left in its folder (nothing here)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class SitlProcess(ChildProcess):
    """ArduPilot SITL in a fresh temporary working directory; close() kills it and removes the folder."""

    def __init__(self, cfg: SitlSettings, instance: int, serial1: str | None = None, sysid: int | None = None):
        self.instance = instance
        self.gcs_port = 5760 + 10 * self.instance
        lat, lon, alt, hdg = cfg.home
        # --speedup 1: the cameras, the fusion and the bridge run on the wall clock
        args = [str(cfg.binary), "--model", cfg.model, "--speedup", "1", "-I", str(self.instance),
                "--home", f"{lat:.7f},{lon:.7f},{alt:.2f},{hdg:g}"]
        if serial1 is not None:  # e.g. udpclient:HOST:PORT (SITL's own syntax; MAVProxy's --out is not one)
            args.append(f"--serial1={serial1}")
        if sysid is not None:  # SYSID_THISMAV (a fleet: one system per vehicle)
            args += ["--sysid", str(sysid)]
        if cfg.defaults is not None:
            args += ["--defaults", str(cfg.defaults.resolve())]
        self._start(args, "visionpos-sitl-", "sitl.log")


# ---------------------------------------------------------------- the true pose

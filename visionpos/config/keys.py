"""The shared HMAC key of a server and its stations: where it lives, how a config names it, making one.

Every station packet and every server reply is signed with one shared secret (docs/security.md).
A config (the arena's `server:` section, a station's YAML) says which key in one of three ways:

    key_file: PATH     that file (relative to the config file)
    insecure: true     no key: packets are neither signed nor checked (a warning says so)
    (neither)          the default key file: $VISIONPOS_KEY_FILE, else ~/.config/visionpos/key

With neither and no default key file, loading the config fails with the fix: `visionpos keygen`
writes one (32 random bytes, mode 0600), to be copied to every station. Both keys at once is
refused: which one wins would be a guess.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from visionpos.config.arena import Section

KEY_ENV = "VISIONPOS_KEY_FILE"
KEY_BYTES = 32  # what keygen writes: the HMAC-SHA256 block-size sweet spot, 256 bits of secret
MIN_KEY_BYTES = 16  # shorter than 128 bits is a password, not a key


def default_key_path() -> Path:
    """$VISIONPOS_KEY_FILE, else ~/.config/visionpos/key (not read here; it may not exist)."""
    env = os.environ.get(KEY_ENV)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".config" / "visionpos" / "key"


def check_key_bytes(data: bytes, path: Path) -> str | None:
    """Why `data` (read from path) is no usable key, or None."""
    if len(data) < MIN_KEY_BYTES:
        size = "is empty" if not data else f"holds only {len(data)} bytes"
        return (f"{path} {size}; a key needs at least {MIN_KEY_BYTES} random bytes: "
                f"make one with `visionpos keygen --out {path} --force` and copy it to the server and every station")
    return None


def resolve_key(sec: Section, base_dir: Path | None, fallback_key: bytes | None = None,
                insecure_hint: str = "insecure: true") -> tuple[bytes | None, str | None]:
    """(key, path it was read from) for a section with optional `key_file` and `insecure` keys.

    base_dir: relative key_file paths start here (None: the working directory). fallback_key:
    used instead of the default key file when the section names neither (the demo's in-memory
    key; its path is then None). insecure_hint: how the user writes the insecure key in this
    file (`server.insecure: true` in an arena), for the messages. Raises ConfigError naming the
    file, the key and the fix.
    """
    insecure = sec.boolean("insecure", False)
    if insecure and sec.has("key_file"):
        raise sec.error("insecure", "true together with key_file: remove one (key_file signs every packet, "
                                    "insecure: true turns signing off)")
    if insecure:
        return None, None
    if sec.has("key_file"):
        p = Path(sec.string("key_file")).expanduser()
        if not p.is_absolute() and base_dir is not None:
            p = base_dir / p
        missing = f"cannot read key file {p}: no such file"
        make = f"visionpos keygen --out {p}"
        where = f"key file {p}"
    elif fallback_key is not None:
        return fallback_key, None
    else:
        p = default_key_path()
        missing = (f"no shared key: key_file is not set and the default key file {p} does not exist (the default is "
                   f"${KEY_ENV}, else ~/.config/visionpos/key)")
        where = f"the default key file {p}"
        make = "visionpos keygen"
    try:
        data = p.read_bytes()  # the exact bytes: server and stations read the same copied file
    except FileNotFoundError:
        raise sec.error("key_file", f"{missing}. Run `{make}` and copy the file to "
                                    f"every station, or set {insecure_hint} to run without authentication "
                                    "(unsafe on a shared network)") from None
    except OSError as e:
        raise sec.error("key_file", f"cannot read {where}: {e.strerror or e}") from None
    why = check_key_bytes(data, p)
    if why is not None:
        raise sec.error("key_file", why)
    return data, str(p)


def write_key(path: Path, force: bool = False) -> None:
    """KEY_BYTES random bytes (secrets) to path with mode 0600, its folder created (0700).

    Raises FileExistsError when path exists and not force; the old key is then untouched.
    """
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if force else os.O_EXCL)
    fd = os.open(path, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)  # an existing file overwritten with --force keeps no wider mode
        os.write(fd, secrets.token_bytes(KEY_BYTES))
    finally:
        os.close(fd)


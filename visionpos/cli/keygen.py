"""`visionpos keygen`: make the shared key the server and its stations sign every packet with.

32 random bytes (Python's `secrets`) in a file of mode 0600, by default where the server and
stations look when their config names no key_file ($VISIONPOS_KEY_FILE, else
~/.config/visionpos/key). Never overwrites a key without --force: stations holding the old key
would stop being heard. docs/security.md has the whole set-up.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from visionpos.config.keys import KEY_BYTES, KEY_ENV, default_key_path, write_key
from visionpos.errors import UsageError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", metavar="PATH", default=None,
                   help=f"where to write the key (default: ${KEY_ENV}, else ~/.config/visionpos/key)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing key (every station then needs the new one)")


def run(args: argparse.Namespace) -> int:
    default = default_key_path()
    path = Path(args.out).expanduser() if args.out else default
    try:
        write_key(path, force=args.force)
    except FileExistsError:
        raise UsageError(f"{path} already exists; keep it (the stations have it) or pass --force to replace it "
                         "and copy the new key to every station") from None
    except OSError as e:
        raise UsageError(f"cannot write {path}: {e.strerror or e}") from None
    path = path.resolve()
    is_default = path == default.expanduser().resolve()
    print(f"visionpos keygen: wrote a new {KEY_BYTES}-byte key to {path} (mode 0600)")
    print("Copy the same file to every station (keep it secret: whoever has it can send poses), e.g. for each:")
    print("  ssh pi@STATION 'mkdir -p -m 700 ~/.config/visionpos'")
    print(f"  scp -p {path} pi@STATION:.config/visionpos/key")
    if is_default:
        print("The server and the stations read it from this default place when their config names no key_file; "
              "to name it explicitly:")
    else:
        print("This is not the default place, so name it in the configs:")
    print(f"  arena YAML:   server: {{key_file: {path}}}")
    print("  station YAML: key_file: ~/.config/visionpos/key   (where you copied it on the station)")
    return 0

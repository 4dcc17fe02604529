"""The arena file's `sitl:` section, read into SitlSettings, and the error every part of `visionpos sitl` raises."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from visionpos.config.arena import ArenaConfig, ConfigError
from visionpos.config.schema import register_section
from visionpos.config.settings import Setting, section
from visionpos.errors import VisionposError

SITL = section(
    "sitl",
    "ArduPilot SITL for `visionpos sitl` (docs/autopilot-setup.md, \"Try it in SITL first\").",
    Setting("binary", "text", None, "the arducopter SITL binary (relative to the arena file)",
            default_doc="--sitl PATH, else $VISIONPOS_SITL, else ../shared/sitl/arducopter beside the checkout"),
    Setting("defaults", "text", None, "ArduPilot's SITL parameter defaults file, passed as --defaults "
            "(Tools/autotest/default_params/copter.parm; relative to the arena file)",
            default_doc="--defaults PATH, else copter.parm beside the binary, in the ArduPilot tree it was built "
            "in, or in ../shared/sitl"),
    Setting("px4_dir", "text", None, "PX4's SITL build folder, holding bin/px4 and etc/ (`visionpos sitl --autopilot "
            "px4`; relative to the arena file)",
            default_doc="--sitl DIR, else $VISIONPOS_PX4_SITL, else ../shared/sitl-px4/build beside the checkout"),
    Setting("model", "text", "+", "SITL frame model (--model)"),
    Setting("instance", "integer", None, "SITL instance (-I): ports 5760 + 10*I ...", min=0, max=200,
            default_doc="the first whose ports are free from 1"),
    Setting("home", "array", [-35.363261, 149.165230, 584.0, 0.0], "SITL home and EKF origin: lat, lon (deg), "
            "alt (m AMSL), heading (deg)", shape=(4,)),
    Setting("viso_delay_ms", "number", None, "VISO_DELAY_MS to set", min=0.0, max=250.0,
            default_doc="measured once the vision flows: the smallest pose stamp -> send delay of the bridge's first "
            "100 poses, which ArduPilot's jitter correction leaves; bridge/estimator_delay.py"),
    Setting("viso_pos_m_nse", "number", 0.01, "VISO_POS_M_NSE: ArduPilot's floor on the position noise (m)",
            min=0.001, max=10.0),
    Setting("viso_yaw_m_nse", "number", 0.02, "VISO_YAW_M_NSE: floor on the yaw noise (rad)", min=0.001, max=1.0),
    Setting("viso_vel_m_nse", "number", 0.05, "VISO_VEL_M_NSE: floor on the velocity noise (m/s; ODOMETRY and "
            "VISION_SPEED_ESTIMATE)", min=0.001, max=5.0),
)


class SitlError(VisionposError):
    """SITL did not start, did not answer, or refused what the run needs."""


@dataclasses.dataclass(frozen=True)
class SitlSettings:
    binary: Path
    defaults: Path | None  # None: none passed (tests that build SitlSettings themselves)
    model: str
    instance: int | None
    home: tuple[float, float, float, float]
    viso_delay_ms: float | None
    viso_pos_m_nse: float
    viso_yaw_m_nse: float
    viso_vel_m_nse: float


REPO_ROOT = Path(__file__).resolve().parents[3]


def _shared_sitl_dir() -> Path:
    """../shared/sitl beside the checkout (for a git worktree: beside its main checkout)."""
    root = REPO_ROOT
    dotgit = root / ".git"
    if dotgit.is_file():  # a worktree: "gitdir: MAIN/.git/worktrees/NAME"
        text = dotgit.read_text(errors="replace").strip()
        if text.startswith("gitdir:") and "/.git/worktrees/" in text:
            root = Path(text.split(":", 1)[1].strip().split("/.git/worktrees/")[0])
    return root.parent / "shared" / "sitl"


SHARED_SITL_DIR = _shared_sitl_dir()  # the SITL binary and copter.parm of a checkout beside ../shared (tests, CI)
DEFAULTS_NAME = "copter.parm"
DEFAULTS_IN_TREE = Path("Tools") / "autotest" / "default_params" / DEFAULTS_NAME


def defaults_candidates(binary: Path) -> list[Path]:
    """Where copter.parm may be, in order: beside the binary; in the ArduPilot tree it was built in (the binary
    at build/sitl/bin/arducopter, the file at Tools/autotest/default_params/copter.parm); in ../shared/sitl
    beside the checkout."""
    b = binary.resolve()
    return [b.parent / DEFAULTS_NAME, *(p / DEFAULTS_IN_TREE for p in b.parents[:4]), SHARED_SITL_DIR / DEFAULTS_NAME]


def find_defaults(binary: Path) -> Path:
    """The first copter.parm of defaults_candidates; a SitlError in one line when there is none (without it
    SITL spends its time refusing to arm with "Motors: Check frame class and type")."""
    for p in defaults_candidates(binary):
        if p.is_file():
            return p
    raise SitlError(f"no {DEFAULTS_NAME} beside {binary} nor in its ArduPilot tree: SITL cannot arm without its "
                    "defaults (\"Motors: Check frame class and type\"); give --defaults PATH or sitl.defaults "
                    f"(ArduPilot's {DEFAULTS_IN_TREE})")


def parse_sitl(arena: ArenaConfig, binary: Path) -> SitlSettings:
    """The validated `sitl:` section; binary: the SITL executable (binary.find_sitl_binary)."""
    sec = SITL.check(arena.section("sitl"))
    defaults = SITL.read(sec, "defaults")
    if defaults:
        dp = Path(defaults)
        dp = dp if dp.is_absolute() else Path(arena.source).resolve().parent / dp
        if not dp.is_file():
            raise ConfigError(arena.source, "sitl.defaults", f"{defaults!r}: no file at {dp}")
    else:
        dp = find_defaults(binary)
    home = tuple(float(x) for x in SITL.read(sec, "home"))
    if not (-90 <= home[0] <= 90 and -180 <= home[1] <= 180):
        raise ConfigError(arena.source, "sitl.home", f"{list(home)}: give [lat (-90..90), lon (-180..180), "
                          "alt m, heading deg]")
    return SitlSettings(binary, dp, SITL.read(sec, "model"), SITL.read(sec, "instance"),
                        home, SITL.read(sec, "viso_delay_ms"), SITL.read(sec, "viso_pos_m_nse"),
                        SITL.read(sec, "viso_yaw_m_nse"), SITL.read(sec, "viso_vel_m_nse"))


register_section("sitl", SITL, parse_sitl)

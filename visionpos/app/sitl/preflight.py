"""Setting SITL up for vision-only flight, before the cameras start.

Order of the set-up, which matters to EKF3 (see docs/autopilot-setup.md):
parameters (GPS and compass off, external nav on) -> reboot -> signing key -> EKF origin sent
until SITL reports GPS_GLOBAL_ORIGIN, and home (MAV_CMD_DO_SET_HOME) -> only then the cameras
start: a vision stream that reaches EKF3 before its origin leaves the height off by centimetres
for the whole flight. The origin is the SITL home, so EKF NED = the arena's world turned by
visionpos/geometry/frames.py (N = x, E = -y, D = -z).

Each step is a function below; prepare_vehicle runs them in that order.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, Callable

from bridge.estimator_delay import EKF3_HALF_STEP_MS, EKF3_HORIZON_PARAM, ekf3_history_param_ms
from visionpos.app.sitl.gcs import (
    MAV_CMD_DO_SET_HOME,
    MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN,
    MAV_CMD_REQUEST_MESSAGE,
    MSG_HOME_POSITION,
    Gcs,
)
from visionpos.app.sitl.process import SitlProcess
from visionpos.app.sitl.settings import SitlError, SitlSettings

if TYPE_CHECKING:
    from bridge.config import VehicleConfig

HOME_TOLERANCE_M = 0.01  # home read back further than this from the origin: an error


BOOT_VISO_DELAY_MS = 20.0  # VISO_DELAY_MS at boot, plus the link's delay; the flight sets the advice before arming
# the poses' stamp-to-arrival p99 expected on a direct link (the 2-core VM: 20-30 ms), plus the link's delay: what
# EKF3's IMU history is sized for at boot (bridge/estimator_delay.py)
EXPECTED_LATE_MS = 40.0


def boot_viso_delay_ms(cfg: SitlSettings, link_delay_ms: float | None) -> int:
    """VISO_DELAY_MS to boot with: sitl.viso_delay_ms when given (kept for the flight), else a value the flight
    replaces with the bridge's advice once the poses are timed."""
    if cfg.viso_delay_ms is not None:
        return round(cfg.viso_delay_ms)
    return round(BOOT_VISO_DELAY_MS + (link_delay_ms or 0.0))


def boot_history_params(link_delay_ms: float | None) -> dict[str, float]:
    """EKF3's IMU history sized at boot (it is sized only then: NavEKF3_core::setup_core) for poses up to
    EXPECTED_LATE_MS plus the link's delay old, as the bridge advises it (EK3_BCN_DELAY,
    bridge/estimator_delay.py); nothing where EK3_HGT_DELAY's default already holds them. Without it, a relay
    adding 50 ms left the EKF 15-20 ms behind the truth with the advised VISO_DELAY_MS (issue 31)."""
    need = ekf3_history_param_ms(EXPECTED_LATE_MS + (link_delay_ms or 0.0) + EKF3_HALF_STEP_MS)
    return {} if need is None else {EKF3_HORIZON_PARAM: float(need)}


SERIAL1_BAUD_BPS = 921_600  # the vision port's speed: SITL takes each pose's bytes' time at it off its arrival


def vision_parameters(cfg: SitlSettings, message: str, vision_speed: bool,
                      link_delay_ms: float | None = None) -> dict[str, float]:
    """The vision-only parameters of docs/autopilot-setup.md (GPS and compass off, external nav on),
    VISO_DELAY_MS for the boot (boot_viso_delay_ms) and EKF3's history (boot_history_params)."""
    vel = 6.0 if (message == "odometry" or vision_speed) else 0.0
    return {
        "VISO_TYPE": 1, "SERIAL1_PROTOCOL": 2, "SERIAL1_BAUD": SERIAL1_BAUD_BPS // 1000,
        "EK3_SRC1_POSXY": 6, "EK3_SRC1_POSZ": 6, "EK3_SRC1_VELXY": vel, "EK3_SRC1_VELZ": vel, "EK3_SRC1_YAW": 6,
        "GPS1_TYPE": 0, "COMPASS_USE": 0, "COMPASS_USE2": 0, "COMPASS_USE3": 0, "COMPASS_ENABLE": 0,
        "VISO_DELAY_MS": boot_viso_delay_ms(cfg, link_delay_ms), **boot_history_params(link_delay_ms),
    }


def _setup_signing(gcs: Gcs, key: bytes) -> None:
    """Install the vision link's key with SETUP_SIGNING on SERIAL0 (channel 0, which ArduPilot lets through
    unsigned): SITL then signs on SERIAL1 and takes only signed vision there, as a real signed set-up, and
    the bridge's udpin endpoint learns SITL's address from signed packets only."""
    stamp = int((time.time() - 1420070400) * 1e5)  # 10 us since 2015-01-01
    gcs.conn.mav.setup_signing_send(gcs.target, 1, key, stamp)


def _set_origin(gcs: Gcs, cfg: SitlSettings, say: Callable[[str], None],
                home: tuple[float, float, float] | None = None) -> None:
    """SET_GPS_GLOBAL_ORIGIN (cfg.home) until SITL reports GPS_GLOBAL_ORIGIN (EKF3 drops it until it runs), then
    MAV_CMD_DO_SET_HOME as COMMAND_INT (ArduCopter 4.3+ ignores SET_HOME_POSITION; a COMMAND_LONG's float32
    degrees put home 2 cm N and 47 cm E of the origin) at home (lat, lon deg, alt m; default: the origin; a fleet
    vehicle's: where it stands), read back with HOME_POSITION."""
    lat, lon, alt, _ = cfg.home
    end = time.monotonic() + 60.0
    while gcs.origin is None:
        if time.monotonic() > end:
            raise SitlError("SITL never reported GPS_GLOBAL_ORIGIN: EKF3 did not take the origin")
        gcs.conn.mav.set_gps_global_origin_send(gcs.target, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                int(round(alt * 1000)), int(time.time() * 1e6))
        for _ in range(50):
            if gcs.origin is not None:
                break
            time.sleep(0.02)
    m = gcs.origin[1]
    say(f"EKF origin confirmed by SITL: {m.latitude * 1e-7:.7f}, {m.longitude * 1e-7:.7f}, {m.altitude * 1e-3:.2f} m")
    gcs.home = None
    lat, lon, alt = home if home is not None else (lat, lon, alt)
    gcs.command_int(MAV_CMD_DO_SET_HOME, lat, lon, alt)
    gcs.wait(lambda: MAV_CMD_DO_SET_HOME in gcs.acks, 5.0, "COMMAND_ACK for MAV_CMD_DO_SET_HOME")
    if gcs.acks[MAV_CMD_DO_SET_HOME][0] != 0:
        say(f"note: SITL refused MAV_CMD_DO_SET_HOME (MAV_RESULT {gcs.acks[MAV_CMD_DO_SET_HOME][0]}); it sets home "
            "itself when it arms")
        return
    gcs.command(MAV_CMD_REQUEST_MESSAGE, MSG_HOME_POSITION)
    try:
        gcs.wait(lambda: gcs.home is not None, 3.0, "HOME_POSITION")
    except SitlError:
        say("note: SITL did not report HOME_POSITION; home not checked")
        return
    north, east = home_offset_m(gcs.home[1], lat, lon)
    where = "the origin" if home is None else "where it stands"
    say(f"home set and read back: {1000 * north:+.1f} mm N, {1000 * east:+.1f} mm E of {where}")
    if math.hypot(north, east) > HOME_TOLERANCE_M:
        raise SitlError(f"SITL's home is {north:.3f} m N, {east:.3f} m E of {where} (over "
                        f"{100 * HOME_TOLERANCE_M:g} cm): it did not take MAV_CMD_DO_SET_HOME's position")


def home_offset_m(home: Any, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    """(north, east) m of a HOME_POSITION (degE7 fields) from lat_deg, lon_deg."""
    from bridge.telemetry import geodetic_offset_m

    return geodetic_offset_m(home.latitude * 1e-7, home.longitude * 1e-7, lat_deg, lon_deg)


def prepare_vehicle(gcs: Gcs, proc: SitlProcess, cfg: SitlSettings, veh: VehicleConfig, key: bytes,
                    say: Callable[[str], None], link_delay_ms: float | None = None,
                    home: tuple[float, float, float] | None = None) -> None:
    """The whole set-up, in its order: connect, the vision-only parameters (read back), reboot, reconnect,
    the noise floors, the signing key, the EKF origin and home."""
    gcs.connect(30.0, proc)
    if gcs.autopilot_type == 12:  # MAV_AUTOPILOT_PX4
        raise SitlError(f"{cfg.binary} runs PX4, not ArduPilot: fly it with --autopilot px4")
    params = vision_parameters(cfg, veh.message, veh.vision_speed, link_delay_ms)
    gcs.set_params(params)
    say(f"parameters set and read back ({len(params)}); rebooting SITL")
    gcs.command(MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    time.sleep(0.1)
    gcs.close()
    time.sleep(2.0)
    gcs.connect(30.0, proc)
    noise = {"VISO_POS_M_NSE": cfg.viso_pos_m_nse, "VISO_YAW_M_NSE": cfg.viso_yaw_m_nse,
             "VISO_VEL_M_NSE": cfg.viso_vel_m_nse}
    gcs.set_params(noise)
    _setup_signing(gcs, key)
    _set_origin(gcs, cfg, say, home)

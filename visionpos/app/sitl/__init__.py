"""`visionpos sitl`: a real ArduPilot (SITL) flown on visionpos alone, closed loop, on loopback.

    ArduPilot SITL (arducopter: the real flight code and EKF3, its own physics)
      SERIAL0 tcp:127.0.0.1:5760+10*I  <-> our GCS link: parameters, signing key, EKF origin and home,
                                            SIM_STATE (the true pose, 100 Hz), flight commands, telemetry
      SERIAL1 udpclient --> the bridge's udpin endpoint: the signed vision stream comes back on it
    SIM_STATE -> TruthTrack -> LiveTrajectory (the simulated body follows the vehicle)
      -> the demo's simulated stations (live frames: noise, latency, asynchrony)
      -> FusionServer -> Bridge (VISION_POSITION_ESTIMATE or ODOMETRY) -> SITL's EKF3

SITL runs in a fresh temporary folder (its eeprom.bin, logs), on an instance (-I) whose ports
are free, and is killed when the run ends, however it ends. Its SERIAL0 takes one TCP client and
waits for it again after a reboot; the binary takes `--serialN=udpclient:HOST:PORT` (MAVProxy's
`--out` is not a SITL option), which points SERIAL1 at the bridge's udpin endpoint. The vision
link is signed with the vehicle's key (installed by SETUP_SIGNING over SERIAL0), so the bridge
learns SITL's address from signed packets only. The demo's fake autopilot is not started: it
would answer on the same link as the same system.

The package, one module per part:
    settings.py   the arena's `sitl:` section (SitlSettings) and SitlError
    binary.py     where the arducopter binary is (--sitl, sitl.binary, $VISIONPOS_SITL, ../shared/sitl)
    process.py    SitlProcess: SITL in a temporary folder on a free instance, killed at the end
    truth.py      TruthTrack (SIM_STATE resampled in the world frame) and LiveArena (the cameras render it)
    gcs.py        Gcs: the SERIAL0 link (reader thread, parameters, commands)
    clock.py      SitlClock and IntakeProbe: SITL's clock against ours, for the true delay
    preflight.py  the set-up before the cameras start (parameters, reboot, signing, origin and home)
    flight.py     FlightPlan and the scripted flight
    delay.py      delay_record: the back-channel's delay against the true one
    report.py     flight_summary and format_flight
    run.py        run_sitl: all of it, the flight on the demo's live arena (app/demo.py run_demo)
    fleet.py      run_fleet: --vehicles N, one SITL each flown together, their links swappable (--swap-at)
    px4.py        PX4 SITL (SIH) for --autopilot px4: the build, EKF2's parameters (PX4_PARAM_ env), the process,
                  Px4Gcs (its GCS link, SIH's truth, the keep-alive; parameters read back)
    px4_run.py    run_px4: the flight on PX4 (EKF2 on the vision, Position mode, arm, Offboard, AUTO.LAND)
"""

from visionpos.app.sitl.binary import SHARED_BINARY, SITL_ENV, default_sitl_binary, find_sitl_binary
from visionpos.app.sitl.clock import IntakeProbe, SitlClock
from visionpos.app.sitl.delay import delay_record
from visionpos.app.sitl.flight import FlightPlan
from visionpos.app.sitl.gcs import EXTNAV_TEXT, Gcs
from visionpos.app.sitl.preflight import vision_parameters
from visionpos.app.sitl.process import SitlProcess
from visionpos.app.sitl.report import flight_summary, format_flight
from visionpos.app.sitl.run import run_sitl, sitl_arena
from visionpos.app.sitl.settings import SITL, SitlError, SitlSettings, parse_sitl
from visionpos.app.sitl.truth import LATLON_TO_M, LiveArena, TruthTrack

__all__ = [
    "EXTNAV_TEXT",
    "LATLON_TO_M",
    "SHARED_BINARY",
    "SITL",
    "SITL_ENV",
    "FlightPlan",
    "Gcs",
    "IntakeProbe",
    "LiveArena",
    "SitlClock",
    "SitlError",
    "SitlProcess",
    "SitlSettings",
    "parse_sitl",
    "TruthTrack",
    "default_sitl_binary",
    "delay_record",
    "find_sitl_binary",
    "flight_summary",
    "format_flight",
    "run_sitl",
    "sitl_arena",
    "vision_parameters",
]

"""The accelerometer half of the autopilot's IMU messages, for the fleet's binding (bridge/fleet_binding.py).

The back-channel (bridge/backchannel.py) asks for the vehicle's IMU (ArduPilot's RAW_IMU, PX4's HIGHRES_IMU;
SCALED_IMU is read too) and keeps its gyro; each accepted IMU message also goes here (AccelSamples.add), where its
specific force is kept in m/s^2 FRD on the autopilot's clock. `on_server_clock` maps the samples onto the server
clock as the attitude is mapped (Backchannel.attitude_on_server_clock: the lag the gyro's correlation measured,
else the fastest message's offset).

Units: HIGHRES_IMU carries m/s^2; ArduPilot's RAW_IMU and SCALED_IMU carry milli-g (MAVLink: "mG"). PX4's
RAW_IMU carries raw sensor counts and is not read (as for its gyro).
"""

from __future__ import annotations

import numpy as np

from bridge.telemetry import Ring
from visionpos.geometry.frames import GRAVITY_M_S2

RING = 1024  # samples kept: 20 s at 50 Hz (the binding uses the newest second or two)
MAX_ABS_M_S2 = 16.0 * GRAVITY_M_S2  # a reading beyond an IMU's range is corrupt: dropped


class AccelSamples(Ring):
    """The newest RING accelerometer samples of one vehicle: (autopilot time ns, ax, ay, az m/s^2 FRD)."""

    def __init__(self):
        super().__init__(RING, 3)

    def add(self, t_ap_ns: int, accel_frd_m_s2) -> None:
        """One IMU sample the back-channel accepted (bridge/telemetry.py imu_sample): its specific force (3,) m/s^2
        FRD, stamped t_ap_ns on the autopilot's clock. A reading beyond an IMU's range is dropped; a stamp older
        than the newest kept (the autopilot rebooted: a new clock) starts afresh."""
        a = tuple(float(x) for x in accel_frd_m_s2)
        if not all(abs(x) <= MAX_ABS_M_S2 for x in a):
            return
        if self.d and t_ap_ns <= self.d[-1][0]:
            self.clear()
        super().add(int(t_ap_ns), a)

    def on_server_clock(self, clock_map_ns: float | None) -> tuple[np.ndarray, np.ndarray] | None:
        """Times (N,) int64 ns on the server clock and (N, 3) m/s^2 FRD, safe to call from another thread;
        clock_map_ns: the autopilot time less the server time of one instant (None: not known yet, None back)."""
        rows = list(self.d)  # list() copies under the GIL while the receiving thread appends
        if clock_map_ns is None:
            return None
        if not rows:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        a = np.array(rows, dtype=np.float64)
        return (a[:, 0] - clock_map_ns).astype(np.int64), a[:, 1:]

"""The accelerometer half of the autopilot's IMU messages, for the fleet's binding (bridge/fleet_binding.py).

The back-channel (bridge/backchannel.py) asks for the vehicle's IMU (ArduPilot's RAW_IMU, PX4's HIGHRES_IMU;
SCALED_IMU is read too) and keeps its gyro; each accepted IMU message also goes here (AccelSamples.add), where its
specific force is kept in m/s^2 FRD on the autopilot's clock. `on_server_clock` maps the samples onto the server
clock as the attitude is mapped (Backchannel.ap_to_server_ns: the lag the gyro's correlation measured, carried by
the clocks' drift, else the fastest message's offset).

Units: HIGHRES_IMU carries m/s^2; ArduPilot's RAW_IMU and SCALED_IMU carry milli-g (MAVLink: "mG"). PX4's
RAW_IMU carries raw sensor counts and is not read (as for its gyro).
"""

from __future__ import annotations

from collections.abc import Callable

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

    def on_server_clock(self, to_server_ns: Callable[[np.ndarray], np.ndarray | None]
                        ) -> tuple[np.ndarray, np.ndarray] | None:
        """Times (N,) int64 ns on the server clock and (N, 3) m/s^2 FRD, safe to call from another thread;
        to_server_ns: autopilot-clock times (N,) ns -> server-clock times (N,) int64 ns, None while the clocks are
        not mapped (then None back)."""
        a = np.array(list(self.d), dtype=np.float64).reshape(-1, 4)  # list() copies under the GIL as it appends
        t = to_server_ns(a[:, 0])
        return None if t is None else (t, a[:, 1:])

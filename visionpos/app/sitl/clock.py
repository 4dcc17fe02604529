"""SITL's clock against ours, for the delay benchmark: SitlClock (its records) and IntakeProbe (TIMESYNC
requests into SITL's vision port through the relay).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np


class SitlClock:
    """SITL's clock against ours; thread-safe appends (the GCS reader, the intake probe's threads).

    SITL's clock is its simulation time, stopped at each physics step while its loop runs (AP_HAL_SITL), so
    everything it stamps in one loop carries that step's time. Three records:
    - truth: (arrival here, SITL time) for each SIM_STATE, the SITL time being RAW_IMU's time_usec sent in the
      same message bucket (both asked for at TRUTH_RATE_HZ (gcs.py) on the GCS link; SITL sends RAW_IMU, SIM_STATE,
      SYSTEM_TIME together; RAW_IMU is stamped when sent, to the microsecond, i.e. the physics step SIM_STATE
      reports; SYSTEM_TIME's time_boot_ms, whole milliseconds, only cross-checks the bucket);
    - intake: (our send time s1, SITL's tc1) for TIMESYNC requests sent into the vision link's port (SERIAL1)
      from the relay's socket (IntakeProbe): tc1 is SITL's receive time of the datagram (the UART's receive
      timestamp, which ArduPilot also gives a vision message), so tc1 - s1 is how late on SITL's clock a
      datagram the relay sends now is taken in;
    - timesync: the same on the GCS link (SERIAL0), for comparison.
    median(arrival - SITL time) + median(tc1 - s1) = how old SIM_STATE's physics is when it arrives here plus
    how late SITL takes a datagram in, on SITL's clock: the two clocks' offset cancels."""

    TIMESYNC_EVERY_NS = 250_000_000
    BUCKET_NS = 1_000_000  # messages of one bucket arrive together (one TCP write)
    MIN_TIMESYNCS = 5

    def __init__(self) -> None:
        self.truth: list[tuple[int, int]] = []
        self.intake: list[tuple[int, int]] = []
        self.timesync: list[tuple[int, int]] = []
        self.pending: dict[int, int] = {}
        self.bucket_checks = 0
        self.bucket_mismatches = 0  # SYSTEM_TIME ms != floor(RAW_IMU us / 1000): not one bucket
        self._imu: tuple[int, int] | None = None  # (arrival, SITL ns) of the last RAW_IMU
        self._last_imu: tuple[int, int] | None = None  # the same, for the SYSTEM_TIME check

    def on_system_time(self, now: int, time_boot_ms: int) -> None:
        """SITL sends it after RAW_IMU and SIM_STATE in their bucket: it checks the RAW_IMU before it."""
        imu = self._last_imu
        if imu is not None and now - imu[0] < self.BUCKET_NS:
            self.bucket_checks += 1
            self.bucket_mismatches += int(int(time_boot_ms) != imu[1] // 1_000_000)
            self._last_imu = None

    def on_raw_imu(self, now: int, time_usec: int) -> None:
        self._imu = self._last_imu = (now, int(time_usec) * 1000)

    def on_sim_state(self, now: int) -> None:
        imu = self._imu
        if imu is not None and now - imu[0] < self.BUCKET_NS:
            self.truth.append((now, imu[1]))
        self._imu = None  # one pair per bucket

    def on_timesync(self, tc1: int, ts1: int) -> None:
        """A TIMESYNC answer on the GCS link (ts1: our request's send time)."""
        s1 = self.pending.pop(ts1, None)
        if s1 is not None and tc1 > 0:
            self.timesync.append((s1, tc1))

    def summary(self, since_ns: int, until_ns: int | None = None) -> dict[str, Any]:
        """The records since since_ns (our clock), in ms: sitl_term (SIM_STATE's age plus SITL's intake of the
        vision link's datagrams, the term the true delay gains; None with too few records) and
        sitl_term_serial0 (the same with the GCS link's intake, for comparison)."""
        def rows(records: list) -> np.ndarray:
            end = until_ns if until_ns is not None else np.iinfo(np.int64).max
            return np.array([r for r in list(records) if since_ns <= r[0] <= end], dtype=np.int64).reshape(-1, 2)

        tr, ts1, ts0 = rows(self.truth), rows(self.intake), rows(self.timesync)
        out: dict[str, Any] = {"truth_pairs": len(tr), "intake_timesyncs": len(ts1), "gcs_timesyncs": len(ts0),
                               "sitl_term_ms": None, "sitl_term_serial0_ms": None, "intake_ms": None,
                               "bucket_mismatch_fraction": self.bucket_mismatches / max(1, self.bucket_checks)}
        if len(tr) < 10:
            return out
        if len(ts1) >= self.MIN_TIMESYNCS:
            out["intake_ms"] = float(np.median(ts1[:, 1] - ts1[:, 0])) * 1e-6  # offset-laden
        age = float(np.median(tr[:, 0] - tr[:, 1]))  # offset-laden: our arrival less SITL's time
        for key, ts in (("sitl_term_ms", ts1), ("sitl_term_serial0_ms", ts0)):
            if len(ts) >= self.MIN_TIMESYNCS:  # offset-laden the other way: SITL's intake less our send
                out[key] = (age + float(np.median(ts[:, 1] - ts[:, 0]))) * 1e-6
        return out


def clock_rate(pairs: np.ndarray, window_ns: int, min_span_ns: int) -> float | None:
    """The other clock's seconds per ours over the newest window_ns of TIMESYNC pairs (N, 2: our send ns, its
    receive ns), by least squares (each pair's one-way jitter is noise about the line); None while they span
    under min_span_ns."""
    if len(pairs) < 3:
        return None
    pairs = pairs[pairs[:, 0] >= pairs[-1, 0] - window_ns]
    ours = (pairs[:, 0] - pairs[0, 0]).astype(np.float64)
    theirs = (pairs[:, 1] - pairs[0, 1]).astype(np.float64)
    if ours[-1] < min_span_ns:
        return None
    ours -= ours.mean()
    return float((ours * (theirs - theirs.mean())).sum() / (ours * ours).sum())


class IntakeProbe:
    """TIMESYNC requests into SITL's vision port (SERIAL1) from the relay's own socket, every
    SitlClock.TIMESYNC_EVERY_NS on a thread of its own, signed with the vehicle's key (SITL takes only signed
    messages there) on a link id of its own; the answers are picked out of the relay's datagrams from SITL
    (DelayRelay.tap) into clock.intake."""

    LINK_ID = 7

    def __init__(self, relay: Any, key: bytes, clock: SitlClock):
        from pymavlink.dialects.v20 import ardupilotmega as mav2

        self.relay = relay
        self.clock = clock
        self.enc = mav2.MAVLink(None, srcSystem=255, srcComponent=191)
        self.enc.signing.secret_key = key
        self.enc.signing.link_id = self.LINK_ID
        self.enc.signing.sign_outgoing = True
        self.enc.signing.timestamp = int((time.time() - 1420070400) * 1e5)  # 10 us since 2015-01-01
        self.rx = mav2.MAVLink(None)
        self.rx.robust_parsing = True
        self._pending: dict[int, int] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-intake-probe", daemon=True)

    def __enter__(self) -> "IntakeProbe":
        self.relay.tap = self.tap
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.relay.tap = None

    def _run(self) -> None:
        while not self._stop.wait(SitlClock.TIMESYNC_EVERY_NS * 1e-9):
            ts1 = time.monotonic_ns()  # an identifier: the send time is the relay's clock read at its write
            s1 = self.relay.send_to_autopilot(self.enc.timesync_encode(0, ts1).pack(self.enc))
            if s1 is not None:
                with self._lock:
                    self._pending[ts1] = s1
                    while len(self._pending) > 64:
                        self._pending.pop(next(iter(self._pending)))

    def tap(self, read_ns: int, data: bytes) -> None:
        if b"\x6f\x00\x00" not in data:  # TIMESYNC's message id (111, 3 bytes): parse only those datagrams
            return
        try:
            msgs = self.rx.parse_buffer(data) or []
        except Exception:  # noqa: BLE001  a datagram that is not MAVLink: not ours
            return
        for m in msgs:
            if m.get_type() == "TIMESYNC" and m.tc1 > 0:
                with self._lock:
                    s1 = self._pending.pop(m.ts1, None)
                if s1 is not None:
                    self.clock.intake.append((s1, int(m.tc1)))

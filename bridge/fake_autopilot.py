"""A simulated autopilot on a MAVLink link, for tests, benchmarks and `visionpos demo`.

It plays the vehicle's side of one bridge endpoint:
- endpoint 'udpout:HOST:PORT' sends to the bridge's udpin port (the usual
  "point the autopilot at the MAVLink port" set-up);
- 'udpin:HOST:PORT' listens for a bridge configured with udpout (port 0
  picks a free port: read .port after start());
- 'tcpin:HOST:PORT' listens for a bridge configured with tcp.
It sends HEARTBEAT as an autopilot and TIMESYNC requests (like PX4), signs
and verifies MAVLink2 signatures when given a key, and records every
VISION_POSITION_ESTIMATE, ODOMETRY and VISION_SPEED_ESTIMATE with its
receive time. report() says what an EKF would see.

    with FakeAutopilot("udpout:127.0.0.1:14561", sysid=1) as ap:
        ...
        print(ap.report())
"""

from __future__ import annotations

import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2
from scipy.spatial.transform import Rotation

POSE_TYPES = ("VISION_POSITION_ESTIMATE", "ODOMETRY")
RECORDED = POSE_TYPES + ("VISION_SPEED_ESTIMATE", "HEARTBEAT", "TIMESYNC", "SET_GPS_GLOBAL_ORIGIN", "SET_HOME_POSITION")
AUTOPILOTS = {"ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink2.MAV_AUTOPILOT_PX4}
SIGNING_EPOCH_S = 1420070400


@dataclass
class Received:
    """One message as the autopilot got it. fields: msg.to_dict() (incl. 'mavpackettype')."""

    type: str
    recv_ns: int
    src_system: int
    src_component: int
    signed: bool
    fields: dict = field(default_factory=dict)


def decode_pose(r: Received) -> dict:
    """What an EKF reads from one pose message.

    Returns usec, position_ned (3,), euler (3,) roll pitch yaw rad,
    quaternion_ned_frd (4,) xyzw, reset_counter; ODOMETRY adds
    velocity_frd (3,), angular_velocity_frd (3,).
    """
    f = r.fields
    if r.type == "VISION_POSITION_ESTIMATE":
        euler = np.array([f["roll"], f["pitch"], f["yaw"]])
        q = Rotation.from_euler("ZYX", euler[::-1]).as_quat()
        return dict(usec=f["usec"], position_ned=np.array([f["x"], f["y"], f["z"]]), euler=euler,
                    quaternion_ned_frd=q, reset_counter=f.get("reset_counter", 0))
    if r.type == "ODOMETRY":
        w, x, y, z = f["q"]
        q = np.array([x, y, z, w])
        euler = Rotation.from_quat(q).as_euler("ZYX")[::-1]
        return dict(usec=f["time_usec"], position_ned=np.array([f["x"], f["y"], f["z"]]), euler=euler,
                    quaternion_ned_frd=q, reset_counter=f["reset_counter"],
                    velocity_frd=np.array([f["vx"], f["vy"], f["vz"]]),
                    angular_velocity_frd=np.array([f["rollspeed"], f["pitchspeed"], f["yawspeed"]]))
    raise ValueError(f"{r.type} is not a pose message")


class FakeAutopilot:
    """Simulated autopilot (sysid, component 1) on one link; see the module docstring.

    signing_key: 32 bytes; when set, everything it sends is signed and
    anything unsigned or signed with another key is rejected (counted in
    rejected_signature, not recorded). duration_s: stop by itself after it.
    source_port (udpout): send from this local port (0: any free one), e.g. the
    port a bridge's `autopilot_address` names.
    """

    def __init__(self, endpoint: str, sysid: int = 1, *, autopilot: str = "ardupilot",
                 signing_key: bytes | None = None, heartbeat_hz: float = 1.0, timesync_hz: float = 1.0,
                 duration_s: float | None = None, clock_ns=time.monotonic_ns, source_port: int = 0):
        kind, _, rest = endpoint.partition(":")
        host, _, port = rest.rpartition(":")
        if kind not in ("udpout", "udpin", "tcpin") or not host or not port.isdigit():
            raise ValueError(
                f"fake autopilot endpoint {endpoint!r}: use udpout:HOST:PORT, udpin:HOST:PORT or tcpin:HOST:PORT"
            )
        if autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot {autopilot!r}: one of {sorted(AUTOPILOTS)}")
        self.kind, self.host, self.port = kind, host, int(port)
        self.sysid = sysid
        self.autopilot = autopilot
        self.clock_ns = clock_ns
        self.heartbeat_hz, self.timesync_hz = heartbeat_hz, timesync_hz
        self.duration_s = duration_s
        self.source_port = source_port
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            s = self.mav.signing
            s.secret_key, s.sign_outgoing, s.link_id = signing_key, True, 1
            s.allow_unsigned_callback = None
            s.timestamp = int((time.time() - SIGNING_EPOCH_S) * 1e5)
        self.received: list[Received] = []
        self.timesync_samples: list[tuple[int, int]] = []  # (rtt_ns, offset_ns: bridge clock - ours)
        self.rejected_signature = 0
        self.bad_packets = 0
        self.sent = 0
        self._sock: socket.socket | None = None
        self._listen: socket.socket | None = None
        self._peer = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ts_sent: set[int] = set()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "FakeAutopilot":
        if self.kind == "tcpin":
            ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            ls.bind((self.host, self.port))
            ls.listen(1)
            ls.setblocking(False)
            self.port = ls.getsockname()[1]
            self._listen = ls
        else:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if self.kind == "udpin":
                s.bind((self.host, self.port))
                self.port = s.getsockname()[1]
            else:
                s.bind(("127.0.0.1" if self.host.startswith("127.") else "0.0.0.0", self.source_port))
                self._peer = (socket.gethostbyname(self.host), self.port)
            s.setblocking(False)
            self._sock = s
        self._thread = threading.Thread(target=self._run, name=f"fake-autopilot-{self.sysid}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for s in (self._sock, self._listen):
            if s is not None:
                s.close()
        self._sock = self._listen = None

    def __enter__(self) -> "FakeAutopilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ I/O thread
    def write(self, buf: bytes) -> None:  # mav.send() writes here
        if self._sock is None or self._peer is None:
            return
        try:
            if self.kind == "tcpin":
                self._sock.sendall(buf)
            else:
                self._sock.sendto(buf, self._peer)
            self.sent += 1
        except OSError:
            pass

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        if self._listen is not None:
            sel.register(self._listen, selectors.EVENT_READ, "listen")
        else:
            sel.register(self._sock, selectors.EVENT_READ, "data")
        t_end = None if self.duration_s is None else self.clock_ns() + int(self.duration_s * 1e9)
        next_hb = next_ts = self.clock_ns()
        try:
            while not self._stop.is_set():
                now = self.clock_ns()
                if t_end is not None and now >= t_end:
                    break
                if self._peer is not None and self._sock is not None:
                    if self.heartbeat_hz > 0 and now >= next_hb:
                        self.mav.send(self.mav.heartbeat_encode(
                            mavlink2.MAV_TYPE_QUADROTOR, AUTOPILOTS[self.autopilot], 0, 0, mavlink2.MAV_STATE_STANDBY))
                        next_hb = now + int(1e9 / self.heartbeat_hz)
                    if self.timesync_hz > 0 and now >= next_ts:
                        ts1 = self.clock_ns()
                        self._ts_sent.add(ts1)
                        self.mav.send(self.mav.timesync_encode(0, ts1))
                        next_ts = now + int(1e9 / self.timesync_hz)
                for key, _ in sel.select(0.02):
                    if key.data == "listen":
                        self._accept(sel)
                    else:
                        self._read(sel)
        finally:
            sel.close()

    def _accept(self, sel: selectors.BaseSelector) -> None:
        try:
            conn, addr = self._listen.accept()
        except BlockingIOError:
            return
        if self._sock is not None:
            sel.unregister(self._sock)
            self._sock.close()
        conn.setblocking(False)
        self._sock, self._peer = conn, addr
        sel.register(conn, selectors.EVENT_READ, "data")

    def _read(self, sel: selectors.BaseSelector) -> None:
        while self._sock is not None:
            try:
                if self.kind == "tcpin":
                    data, addr = self._sock.recv(65536), self._peer
                    if not data:  # bridge went away: wait for the next connection
                        sel.unregister(self._sock)
                        self._sock.close()
                        self._sock = self._peer = None
                        return
                else:
                    data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if self.kind == "udpin":
                self._peer = addr  # answer the bridge where it sends from
            self._handle(data)

    def _handle(self, data: bytes) -> None:
        now = self.clock_ns()
        for m in self.mav.parse_buffer(data) or []:
            t = m.get_type()
            if t == "BAD_DATA":
                if "signature" in str(getattr(m, "reason", "")).lower():
                    self.rejected_signature += 1
                else:
                    self.bad_packets += 1
                continue
            if t == "TIMESYNC" and m.tc1 != 0 and m.ts1 in self._ts_sent:
                self._ts_sent.discard(m.ts1)
                self.timesync_samples.append((now - m.ts1, m.tc1 - (m.ts1 + now) // 2))
            if t in RECORDED:
                self.received.append(Received(t, now, m.get_srcSystem(), m.get_srcComponent(),
                                              bool(m.get_signed()), m.to_dict()))

    # ------------------------------------------------------------ queries
    def messages(self, type_: str | tuple[str, ...]) -> list[Received]:
        types = (type_,) if isinstance(type_, str) else type_
        return [r for r in list(self.received) if r.type in types]

    def wait_for(self, type_: str | tuple[str, ...], n: int = 1, timeout_s: float = 5.0) -> bool:
        """Block until n messages of the type(s) arrived or timeout_s passed."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if len(self.messages(type_)) >= n:
                return True
            time.sleep(0.002)
        return len(self.messages(type_)) >= n

    def report(self) -> dict:
        """What an EKF would see: rates, gaps, the last decoded NED pose, timesync, identities."""
        poses = self.messages(POSE_TYPES)
        out: dict = {"pose_messages": len(poses), "rejected_signature": self.rejected_signature,
                     "bad_packets": self.bad_packets}
        if len(poses) >= 2:
            recv = np.array([p.recv_ns for p in poses], dtype=np.int64)
            usec = np.array([decode_pose(p)["usec"] for p in poses], dtype=np.int64)
            gaps_ms = np.diff(recv) * 1e-6
            du_ms = np.diff(usec) * 1e-3
            out.update(
                rate_hz=(len(poses) - 1) / ((recv[-1] - recv[0]) * 1e-9) if recv[-1] > recv[0] else float("nan"),
                max_gap_ms=float(gaps_ms.max()),
                gaps_over_20ms=int((gaps_ms > 20.0).sum()),
                gaps_over_400ms=int((gaps_ms > 400.0).sum()),
                stamp_interval_min_ms=float(du_ms.min()),
                stamps_closer_than_20ms=int((du_ms < 20.0).sum()),  # ArduPilot EKF3 would drop these
                stamps_not_increasing=int((du_ms <= 0).sum()),
            )
        if poses:
            last = decode_pose(poses[-1])
            out["last_pose"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in last.items()}
        hbs = self.messages("HEARTBEAT")
        out["heartbeats"] = len(hbs)
        out["heartbeat_identities"] = sorted({(h.src_system, h.src_component, h.fields["type"], h.fields["autopilot"])
                                              for h in hbs})
        out["speed_messages"] = len(self.messages("VISION_SPEED_ESTIMATE"))
        if self.timesync_samples:
            a = np.array(self.timesync_samples, dtype=np.float64)
            out["timesync_replies"] = len(a)
            out["timesync_rtt_ms_median"] = float(np.median(a[:, 0]) * 1e-6)
            out["timesync_offset_ms_median"] = float(np.median(a[:, 1]) * 1e-6)
        else:
            out["timesync_replies"] = 0
        return out

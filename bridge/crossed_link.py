"""A crossed link: another of the bridge's autopilots answers on a vehicle's link.

Two vehicles' endpoints swapped (two radios' USB ports exchanged, two relay ports crossed) or a wrong
`vehicles[].sysid`: the poses on that link reach another drone, and a back-channel that only goes quiet (its
packets are another sysid's, ignored) would not stop them. So the first packet of another sysid's autopilot
(component 1) from the link's own peer that authenticates stops the poses (VehicleLink._handle_state), and they
resume by themselves once that autopilot has been silent here for CLEAR_NS and the vehicle's own sysid has been
heard since (the links put back). On a signed link the packet must verify with the key of the bridge's vehicle of
that sysid, or with this vehicle's (a fleet sharing one key), on its own streams: a refused packet changes
nothing. On an unsigned link a packet from the peer is as trusted as the vehicle's own.
"""

from __future__ import annotations

import logging

from bridge.link_stats import fmt_addr
from bridge.signing import SignatureCheck

log = logging.getLogger("visionpos.bridge")

CLEAR_NS = 2_000_000_000


class CrossedLink:
    """One vehicle's crossed-link state (its sender thread only). own_key: the vehicle's signing key or None;
    other_keys: sysid -> signing key of the bridge's other vehicles."""

    def __init__(self, name: str, sysid: int, own_key: bytes | None):
        self.name, self.sysid, self.own_key = name, sysid, own_key
        self.other_keys: dict[int, bytes] = {}
        self._checks: dict[int, list[SignatureCheck]] = {}
        self.other: int | None = None  # the sysid answering here while crossed
        self.last_ns = 0  # its newest packet here

    def verified(self, buf: bytearray, v2: bool, sysid: int, compid: int) -> bool:
        """Whether another sysid's packet authenticates (the module docstring)."""
        if self.own_key is None:
            return True
        checks = self._checks.get(sysid)
        if checks is None:
            keys = [k for k in (self.other_keys.get(sysid), self.own_key) if k is not None]
            checks = self._checks[sysid] = [SignatureCheck(k) for k in dict.fromkeys(keys)]
        return any(chk.check(buf, v2, compid)[0] >= 0 for chk in checks)

    def heard(self, sysid: int, addr: tuple | None, endpoint: object, now_ns: int) -> bool:
        """An authenticated packet of another sysid's autopilot from the peer: crossed from now; said loudly, once
        per episode. True when it starts an episode."""
        new = self.other != sysid
        if new:
            self.other = sysid
            log.error("vehicle %s: the autopilot of sysid %d answers on this link (%s), where sysid %d's should: "
                      "two vehicles' endpoints swapped (radios or ports exchanged), or vehicles[].sysid wrong? "
                      "Poses to it stopped until sysid %d answers here again and sysid %d has been silent for "
                      "%.0f s", self.name, sysid, fmt_addr(addr) if addr else endpoint, self.sysid, self.sysid,
                      sysid, CLEAR_NS * 1e-9)
        self.last_ns = now_ns
        return new

    def current(self, now_ns: int, own_last_rx_ns: int) -> int | None:
        """The other sysid while the link is crossed, else None (clearing once it is over)."""
        s = self.other
        if s is None:
            return None
        if now_ns - self.last_ns > CLEAR_NS and own_last_rx_ns > self.last_ns:
            self.other = None
            log.warning("vehicle %s: sysid %d answers on its link again and sysid %d has gone; poses resume",
                        self.name, self.sysid, s)
            return None
        return s

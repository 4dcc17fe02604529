"""Checks shared by the protocol tests."""

from __future__ import annotations

from visionpos import protocol as P


def assert_writes_and_reads(msg: P.WireMessage, data: bytes, key: bytes) -> None:
    """msg writes exactly `data` (bytes written by hand from docs/protocol.md's tables) and reads back from it,
    unsigned and signed with key (the same bytes with the signed flag and a 16-byte tag)."""
    assert msg.write() == data and P.encode(msg) == data
    assert type(msg).read(data) == msg and P.decode(data) == msg
    signed = msg.write(key)
    assert signed[:6] == data[:6] and signed[6] == P.HeaderFlag.SIGNED and signed[7:-16] == data[7:]
    assert type(msg).read(signed, key) == msg

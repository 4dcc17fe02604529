"""StationLink: the station's registration state and reply checks (pure, no sockets)."""

from __future__ import annotations

from stations.session import LinkEvent, StationLink
from visionpos import protocol as P

SERVER = ("127.0.0.1", 5600)


def _ack(link, echo, status=P.AckStatus.OK, session=None, cookie=P.NO_COOKIE):
    return P.HelloAck(link.station_id, link.camera_id, link.session if session is None else session, 10, 20, status,
                      0, echo, cookie)


def test_counters_increase_over_every_control_message_and_hello_carries_the_cookie():
    link = StationLink(3, 5, session=0xABC)
    h1 = link.hello(960, 640, 100.0)
    hb = link.heartbeat(status=1)
    sr = link.sync_request(123)
    bye = link.bye()
    assert [h1.counter, hb.counter, sr.counter, bye.counter] == [1, 2, 3, 4]
    assert {h1.session, hb.session, sr.session, bye.session} == {0xABC}
    assert h1.cookie == P.NO_COOKIE
    assert link.believe(_ack(link, 1, P.AckStatus.CHALLENGE, cookie=b"c" * 16), SERVER, SERVER)
    assert link.on_ack(_ack(link, 1, P.AckStatus.CHALLENGE, cookie=b"c" * 16)) is LinkEvent.CHALLENGED
    assert link.cookie_is_new
    h2 = link.hello(960, 640, 100.0)
    assert h2.cookie == b"c" * 16 and h2.counter == 5 and not link.cookie_is_new


def test_replies_are_believed_only_from_the_server_for_this_session_and_a_recent_newer_request():
    link = StationLink(3, 5, session=0xABC)
    for _ in range(3):
        link.heartbeat()
    assert not link.believe(_ack(link, 3), ("127.0.0.1", 9999), SERVER)  # another port
    assert not link.believe(_ack(link, 3), ("10.0.0.9", 5600), SERVER)  # another host
    assert not link.believe(_ack(link, 3, session=0), SERVER, SERVER)  # v1's "session 0" UNKNOWN_SESSION
    assert not link.believe(_ack(link, 3, session=0xABD), SERVER, SERVER)
    assert not link.believe(_ack(link, 7), SERVER, SERVER)  # never sent
    assert not link.believe(P.HelloAck(3, 6, 0xABC, 0, 0, echo=3), SERVER, SERVER)  # other camera
    assert link.believe(_ack(link, 3), SERVER, SERVER)
    assert not link.believe(_ack(link, 3), SERVER, SERVER)  # the same reply again (replayed)
    assert not link.believe(_ack(link, 2), SERVER, SERVER)  # older than the last believed
    assert link.refused_replies == 8
    for _ in range(100):
        link.heartbeat()
    assert not link.believe(_ack(link, 4), SERVER, SERVER)  # no longer recent
    assert link.believe(_ack(link, link.counter), SERVER, SERVER)


def test_ack_statuses_drive_registration():
    link = StationLink(1, 1, session=9)
    assert not link.registered
    assert link.on_ack(_ack(link, 1)) is LinkEvent.REGISTERED and link.registered and link.start_ns == 10
    assert link.on_ack(_ack(link, 2)) is LinkEvent.KEPT
    assert link.on_ack(_ack(link, 3, P.AckStatus.RESYNC)) is LinkEvent.RESYNC and link.registered
    assert link.on_ack(_ack(link, 4, P.AckStatus.UNKNOWN_SESSION)) is LinkEvent.LOST and not link.registered
    assert link.on_ack(_ack(link, 5, P.AckStatus.REJECTED)) is LinkEvent.REJECTED and link.rejected
    assert link.on_ack(_ack(link, 6, 77)) is LinkEvent.IGNORED

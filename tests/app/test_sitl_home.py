"""`visionpos sitl`'s home: MAV_CMD_DO_SET_HOME as COMMAND_INT, read back with HOME_POSITION within 1 cm of the origin,
against the fake autopilot (it keeps the int32 degE7 it gets; a COMMAND_LONG's float32 degrees are shown to miss)."""

from __future__ import annotations

import math

import pytest

from bridge.fake_autopilot import FakeAutopilot
from visionpos.app import sitl as S
from visionpos.app.sitl.preflight import _set_origin, home_offset_m

HOME = (-35.363261, 149.165230, 584.0, 0.0)  # SITL's default home: float32 steps of 1.5e-5 deg of longitude there


def _settings():
    return S.SitlSettings(S.SHARED_BINARY, None, "+", None, HOME, None, 0.01, 0.02, 0.05)


def test_sitl_home_goes_as_command_int_and_reads_back_within_a_centimetre():
    ap = FakeAutopilot("tcpin:127.0.0.1:0", sysid=1, heartbeat_hz=5).start()
    gcs = S.Gcs(ap.port, S.TruthTrack(HOME[:3]))
    said: list[str] = []
    try:
        gcs.connect(10.0)
        _set_origin(gcs, _settings(), said.append)
        assert ap.origin == (-353632610, 1491652300, 584000)
        assert ap.messages("COMMAND_INT") and not [m for m in ap.messages("COMMAND_LONG")
                                                    if m.fields["command"] == 179]
        north, east = home_offset_m(gcs.home[1], HOME[0], HOME[1])
        assert math.hypot(north, east) < 0.01
        assert any("home set and read back" in t for t in said), said
    finally:
        gcs.close()
        ap.close()


def test_a_command_long_home_would_miss_by_more_than_a_centimetre():
    """Why COMMAND_INT: the same home as COMMAND_LONG (float32 params) lands decimetres east at lon 149."""
    ap = FakeAutopilot("tcpin:127.0.0.1:0", sysid=1, heartbeat_hz=5).start()
    gcs = S.Gcs(ap.port, S.TruthTrack(HOME[:3]))
    try:
        gcs.connect(10.0)
        ap.origin = (-353632610, 1491652300, 584000)
        gcs.command(179, 0, 0, 0, 0, HOME[0], HOME[1], HOME[2])
        gcs.wait(lambda: gcs.home is not None, 5.0, "HOME_POSITION")
        north, east = home_offset_m(gcs.home[1], HOME[0], HOME[1])
        assert abs(east) > 0.5  # float32(149.16523) is 7.4e-6 deg off: 0.67 m
    finally:
        gcs.close()
        ap.close()


@pytest.mark.parametrize("lat,lon", [(47.397742, 8.545594), (-35.363261, 149.165230)])
def test_geodetic_offset_of_a_known_step(lat, lon):
    """1e-5 deg of latitude is 1.113 m everywhere (R = 6378137 m: 2 pi R / 360 * 1e-5); of longitude, that
    times cos(lat)."""
    from bridge.telemetry import geodetic_offset_m

    n, e = geodetic_offset_m(lat + 1e-5, lon + 1e-5, lat, lon)
    assert n == pytest.approx(1.1131949, abs=1e-6)
    assert e == pytest.approx(1.1131949 * math.cos(math.radians(lat)), abs=1e-6)

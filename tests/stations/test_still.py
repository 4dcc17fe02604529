"""Still images and mask updates on a real StationAgent, over loopback: only when the server asks, rate-limited,
authenticated; a mask update is applied to the running detector and saved in the station's YAML file."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from stations.agent import StationAgent
from stations.config import SourceConfig, load_station
from stations.sources import FrameSource
from stations.still import StillLimiter, save_mask
from visionpos import protocol as P

KEY = b"still-test-key-0123456789"
W, H = 320, 240
SPOTS = [(60, 50), (250, 180)]  # marker centres, px
SPOT_RADIUS_PX = 4
BACKGROUND_DN = 10


def _frame() -> np.ndarray:
    """A dark frame with a few brighter background pixels (a lit wall on the left) and two marker discs."""
    img = np.full((H, W), BACKGROUND_DN, np.uint8)
    img[:, :40] = 30  # 12.5 % of the pixels: above the 99th percentile's reach -> the level reads 30
    for x, y in SPOTS:
        cv2.circle(img, (x, y), SPOT_RADIUS_PX, 240, -1)
    return img


class StillCamera(FrameSource):
    kind = "fake"

    def __init__(self):
        super().__init__(SourceConfig(kind="images", width=W, height=H, fps=50.0))
        self.name = "still camera"

    def open(self) -> None:
        pass

    def read(self):
        return _frame(), self.clock()


STATION_YAML = """\
# camera 3 over the door
station_id: 2
camera_id: 3
server: {{host: 127.0.0.1, port: {port}}}
key_file: key
source:
  kind: sim
  fps: 50
detector:
  threshold: 120   # fixed, for the test
  min_area: 4
  ignore:
    - [0, 0, 2, 2]
clock: {{sync: false}}
image_min_interval_s: 0.5
"""


@pytest.fixture
def rig(tmp_path):
    """(agent, server socket, config path): an agent whose server is a plain socket of the test."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    srv.bind(("127.0.0.1", 0))
    srv.settimeout(0.5)
    (tmp_path / "key").write_bytes(KEY)
    path = tmp_path / "station.yaml"
    path.write_text(STATION_YAML.format(port=srv.getsockname()[1]))
    agent = StationAgent(load_station(path), source=StillCamera())
    agent._open_camera()
    agent._resolve()
    agent.process(_frame(), agent.clock())
    hb = agent.link.heartbeat()  # a control counter the server can echo
    agent._send(P.encode(hb, KEY))
    _, agent_addr = srv.recvfrom(2048)
    yield agent, srv, path, agent_addr, hb.counter
    agent.sock.close()
    srv.close()


def _ask(agent, srv, addr, msg, key=KEY) -> list:
    """Send msg to the agent, let it drain, return what it answered."""
    srv.sendto(P.encode(msg, key), addr)
    out = []
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        agent._drain()
        srv.settimeout(0.02)
        try:
            while True:
                out.append(P.decode(srv.recvfrom(2048)[0], KEY))
        except (socket.timeout, BlockingIOError):
            pass
        if out and time.monotonic() > end - 0.2:
            break
    return out


def test_limiter_allows_one_per_interval_and_counts_the_rest():
    lim = StillLimiter(1.0)
    assert lim.allow(0)
    assert not lim.allow(999_999_999)
    assert lim.allow(1_000_000_000)
    assert not lim.allow(1_500_000_000)
    assert (lim.sent, lim.refused) == (2, 2)


def test_image_request_answers_a_jpeg_with_the_background_level_once_per_interval(rig):
    agent, srv, _, addr, echo = rig
    req = P.ImageRequest(2, 3, agent.session, echo, 1, 160, 90)
    chunks = _ask(agent, srv, addr, req)
    assert chunks and all(isinstance(c, P.ImageChunk) and c.request_id == 1 for c in chunks)
    jpeg = b"".join(c.data for c in sorted(chunks, key=lambda c: c.index))
    assert len(jpeg) == chunks[0].total_bytes and len(chunks) == chunks[0].count
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (120, 160) == (chunks[0].height, chunks[0].width)  # downscaled to max_width
    for x, y in SPOTS:  # the markers are bright where they are, at half scale
        assert img[y // 2, x // 2] > 180
    # 12.5 % of the non-marker pixels are 30, the rest 10: the 99th percentile is 30
    assert chunks[0].background == pytest.approx(30.0)
    assert agent.stats.images_sent == 1
    # a second request inside image_min_interval_s: nothing comes back, counted
    assert _ask(agent, srv, addr, P.ImageRequest(2, 3, agent.session, echo, 2, 160, 90)) == []
    assert agent.stats.images_refused == 1


@pytest.mark.parametrize("what", ["unsigned", "wrong session", "replayed", "unsent echo", "wrong camera"])
def test_unauthenticated_or_stale_requests_get_no_image_and_change_nothing(rig, what):
    agent, srv, _, addr, echo = rig
    assert len(_ask(agent, srv, addr, P.ImageRequest(2, 3, agent.session, echo, 5, 160, 90))) > 0
    time.sleep(0.55)  # past image_min_interval_s: only the check under test can refuse
    before = (agent.stats.images_sent, agent.stats.images_refused, agent.link._last_command)
    msg = P.ImageRequest(2, 3, agent.session, echo, 6, 160, 90)
    key = KEY
    if what == "unsigned":
        key = None
    elif what == "wrong session":
        msg = P.ImageRequest(2, 3, agent.session ^ 1, echo, 6, 160, 90)
    elif what == "replayed":
        msg = P.ImageRequest(2, 3, agent.session, echo, 5, 160, 90)
    elif what == "unsent echo":
        msg = P.ImageRequest(2, 3, agent.session, echo + 100, 6, 160, 90)
    else:
        msg = P.ImageRequest(2, 4, agent.session, echo, 6, 160, 90)
    assert _ask(agent, srv, addr, msg, key) == []
    assert (agent.stats.images_sent, agent.stats.images_refused, agent.link._last_command) == before
    assert agent.stats.bad_packets + agent.stats.refused_replies >= 1


def test_mask_update_is_applied_to_the_detector_and_saved_keeping_the_file(rig):
    agent, srv, path, addr, echo = rig
    blobs, _ = agent.detector.detect(_frame())
    assert len(blobs) == 2
    rect = (40, 30, 80, 70)  # around the first marker
    acks = _ask(agent, srv, addr, P.MaskUpdate(2, 3, agent.session, echo, 7, int(P.MaskFlag.IGNORE), (rect,)))
    assert len(acks) == 1 and acks[0].status == P.MaskStatus.SAVED and acks[0].request_id == 7, acks
    # the running detector ignores the marker inside the rectangle and still finds the other
    blobs, _ = agent.detector.detect(_frame())
    assert len(blobs) == 1 and abs(blobs[0, 0] - SPOTS[1][0]) < 1 and abs(blobs[0, 1] - SPOTS[1][1]) < 1
    text = path.read_text()
    data = yaml.safe_load(text)
    assert data["detector"]["ignore"] == [list(rect)]
    # the rest of the file is kept: other keys, the comments
    assert data["detector"]["threshold"] == 120 and data["image_min_interval_s"] == 0.5
    assert "# camera 3 over the door" in text and "# fixed, for the test" in text
    assert load_station(path).ignore == (rect,)  # and it is still a valid station file


def test_mask_update_outside_the_image_is_refused_and_changes_nothing(rig):
    agent, srv, path, addr, echo = rig
    before, mask_before = path.read_text(), agent.detector.mask.copy()
    acks = _ask(agent, srv, addr, P.MaskUpdate(2, 3, agent.session, echo, 8, int(P.MaskFlag.IGNORE),
                                               ((10, 10, W + 1, 20),)))
    assert len(acks) == 1 and acks[0].status == P.MaskStatus.REFUSED and "inside" in acks[0].text
    assert path.read_text() == before and np.array_equal(agent.detector.mask, mask_before)
    # an unsigned one is not even answered
    assert _ask(agent, srv, addr, P.MaskUpdate(2, 3, agent.session, echo, 9, int(P.MaskFlag.IGNORE),
                                               ((10, 10, 20, 20),)), None) == []
    assert path.read_text() == before and np.array_equal(agent.detector.mask, mask_before)


@pytest.mark.parametrize("text", [
    "station_id: 1\ndetector: {threshold: 50}\n",  # flow style: rewritten whole
    "station_id: 1\n",  # no detector section yet
    "station_id: 1\ndetector:\n    ignore:\n    - [1, 2, 3, 4]\n    - [5, 6, 7, 8]\n    rois: [[0, 0, 9, 9]]\n",
])
def test_save_mask_sets_the_key_whatever_the_file_shape(tmp_path, text):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    save_mask(p, {"ignore": [(10, 20, 30, 40)]})
    data = yaml.safe_load(p.read_text())
    old = yaml.safe_load(text)
    assert data["detector"]["ignore"] == [[10, 20, 30, 40]]
    assert data["station_id"] == 1
    for k, v in (old.get("detector") or {}).items():
        if k != "ignore":
            assert data["detector"][k] == v
    assert [f for f in Path(tmp_path).iterdir()] == [p]  # no temporary file left


def test_commands_are_believed_in_echo_then_request_order_only():
    from stations.session import StationLink

    server = ("127.0.0.1", 5600)
    link = StationLink(2, 3, session=0xAB)
    for _ in range(3):
        link.heartbeat()  # counters 1..3

    def cmd(echo, rid, session=0xAB):
        return P.ImageRequest(2, 3, session, echo, rid)

    assert link.believe_command(cmd(2, 10), server, server)
    assert not link.believe_command(cmd(2, 10), server, server)  # the same again: a replay
    assert not link.believe_command(cmd(2, 9), server, server)  # older request of the same echo
    assert not link.believe_command(cmd(1, 11), server, server)  # older echo
    assert link.believe_command(cmd(3, 1), server, server)  # a newer echo (a restarted server counts from 1)
    assert not link.believe_command(cmd(3, 2), ("127.0.0.1", 5601), server)  # not from the server
    assert not link.believe_command(cmd(3, 2, session=0xAC), server, server)
    assert not link.believe_command(cmd(4, 2), server, server)  # a counter never sent
    assert link.refused_replies == 6

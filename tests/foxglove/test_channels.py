"""The Foxglove channels of recordings, checked with code this project did not write.

- Our schema declarations (visionpos/foxglove/protobuf.py) against the descriptors of Foxglove's
  official generated classes (foxglove-schemas-protobuf), file by file.
- Every Foxglove message of a `demo --record` recording parsed strictly by those classes: no
  unknown field, no byte left over (their re-encoding is our bytes), the fields Foxglove needs set.
- The file read back by the mcap library's reader, decoding with the schemas stored in the file
  (as Foxglove does) through mcap-protobuf-support.
- Names, frames and clocks: schema names as Foxglove expects them, frame ids that the transforms
  define, message timestamps equal to the log times, bodies' poses equal to the recorded outputs.
"""

from __future__ import annotations

import asyncio
import importlib
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from visionpos import protocol as P
from visionpos.foxglove import channels as C
from visionpos.foxglove import protobuf as pb
from visionpos.foxglove.protobuf import encode
from visionpos.messages import BlobFrame, BodyState, LoosePoints
from visionpos.recording import RecordingReader, RecordingWriter, foxglove_copy, state_from_dict

fox_pb = pytest.importorskip("foxglove_schemas_protobuf", reason="foxglove-schemas-protobuf (the [test] extra) "
                             "holds Foxglove's official schemas that the channels are checked against")
descriptor_pb2 = pytest.importorskip("google.protobuf.descriptor_pb2")
mcap_protobuf = pytest.importorskip("mcap_protobuf.decoder", reason="mcap-protobuf-support (the [test] extra) "
                                    "decodes the file with the schemas stored in it")


def official(type_name: str):
    """Foxglove's generated class of a foxglove.* type."""
    short = type_name.split(".", 1)[1]
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2"), short)


def strict_parse(type_name: str, data: bytes):
    """Parse with the official class; fail on unknown fields anywhere or bytes it would not write back."""
    msg = official(type_name).FromString(data)
    assert msg.SerializeToString(deterministic=True) == data, f"{type_name}: bytes the official class does not " \
                                                              "reproduce (unknown fields, wrong wire types)"
    return msg


# ---------------------------------------------------------------- the schemas


@pytest.mark.parametrize("type_name", [n for n in pb.MESSAGES if n.startswith("foxglove.")])
def test_declared_schema_is_the_published_one(type_name):
    """The FileDescriptorSet we store for a channel describes each file exactly as Foxglove's own."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(pb.file_descriptor_set(type_name))
    ours = {f.name: f for f in fds.file}
    theirs = {}

    def collect(fd):
        if fd.name not in theirs:
            theirs[fd.name] = fd
            for dep in fd.dependencies:
                collect(dep)

    collect(official(type_name).DESCRIPTOR.file)
    assert set(ours) == set(theirs)
    for name, fd in theirs.items():
        want = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(want)
        want.ClearField("options")  # language options (go_package, csharp_namespace ...): no meaning on the wire
        assert ours[name] == want, name
    # dependencies come before the files that import them, as descriptor pools need
    seen: set[str] = set()
    for f in fds.file:
        assert set(f.dependency) <= seen, f.name
        seen.add(f.name)


def test_encoder_matches_the_official_classes_on_every_field_kind():
    """Negative ints, packed doubles and fixed32, enums, strings, nested and repeated messages, proto3
    default omission: our bytes are what the official classes write for the same message."""
    cal = {"timestamp": pb.time_msg(-1_500_000_001), "frame_id": "camera_3", "width": 1280, "height": 0,
           "distortion_model": "plumb_bob", "D": [-0.25, 0.0, 1e-3, -2e-4, 0.5], "K": [600.0, 0, 640.5, 0, 601.0, 360,
                                                                                      0, 0, 1], "R": [], "P": [1.0]}
    want = official("foxglove.CameraCalibration")(
        timestamp={"seconds": -2, "nanos": 499_999_999}, frame_id="camera_3", width=1280, distortion_model="plumb_bob",
        D=[-0.25, 0.0, 1e-3, -2e-4, 0.5], K=[600.0, 0, 640.5, 0, 601.0, 360, 0, 0, 1], P=[1.0])
    assert encode("foxglove.CameraCalibration", cal) == want.SerializeToString(deterministic=True)
    line = {"type": 2, "pose": {"position": {"x": -1.0}, "orientation": {"w": 1.0}}, "thickness": 2.0,
            "points": [{"x": 1.0, "y": 2.0, "z": 3.0}, {}], "colors": [{"r": 1.0, "a": 1.0}], "indices": [0, 1, 4]}
    update = {"deletions": [{"timestamp": pb.time_msg(5), "type": 1, "id": "x"}],
              "entities": [{"id": "e", "frame_id": "world", "lifetime": pb.time_msg(10**9 + 7), "lines": [line],
                            "metadata": [{"key": "k", "value": "ü"}]}]}
    assert strict_parse("foxglove.SceneUpdate", encode("foxglove.SceneUpdate", update)).entities[0].lines[0].indices \
        == [0, 1, 4]
    with pytest.raises(KeyError, match="colour"):
        encode("foxglove.Color", {"colour": 1.0})


# ---------------------------------------------------------------- a demo recording


@pytest.fixture(scope="module")
def demo_log(tmp_path_factory) -> Path:
    """1.5 s of `visionpos demo --record` (simulated stations, server, bridge on loopback)."""
    from visionpos.app.demo import demo_arena, run_demo

    path = tmp_path_factory.mktemp("fox") / "demo.mcap"
    arena = demo_arena("thesis", 1.5, 3, [])
    asyncio.run(run_demo(arena, 1.5, None, record=str(path)))
    return path


def foxglove_messages(path: Path) -> list[tuple[str, str, int, bytes]]:
    """(topic, schema name, log time, data) of every Foxglove channel, read by the mcap library."""
    from mcap.reader import make_reader

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[mcap_protobuf.DecoderFactory()])
        topics = [ch.topic for ch in reader.get_summary().channels.values() if ch.topic.startswith("/foxglove/")]
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=topics, log_time_order=False):
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            # decoded with the schema stored in the file, as Foxglove decodes: the same message
            assert decoded.SerializeToString(deterministic=True) == message.data
            out.append((channel.topic, schema.name, message.log_time, message.data))
    return out


EXPECTED_SCHEMAS = {C.TOPIC_TF: "foxglove.FrameTransforms", C.TOPIC_ARENA: "foxglove.SceneUpdate",
                    C.TOPIC_BODIES: "foxglove.SceneUpdate", C.TOPIC_MARKERS: "foxglove.SceneUpdate",
                    C.TOPIC_LOG: "foxglove.Log"}


def stamp(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def test_every_foxglove_message_validates_and_is_consistent(demo_log):
    msgs = foxglove_messages(demo_log)
    reader = RecordingReader(demo_log)
    cam_ids = {c["id"] for c in reader.config["cameras"]}
    for cid in cam_ids:
        EXPECTED_SCHEMAS[C.calibration_topic(cid)] = "foxglove.CameraCalibration"
        EXPECTED_SCHEMAS[C.blobs_topic(cid)] = "foxglove.ImageAnnotations"
    by_topic = defaultdict(list)
    for topic, schema, t, data in msgs:
        assert EXPECTED_SCHEMAS.get(topic) == schema, topic
        by_topic[topic].append((t, strict_parse(schema, data)))
    assert set(by_topic) == set(EXPECTED_SCHEMAS), "a Foxglove channel is missing"

    frames = set()
    for t, m in by_topic[C.TOPIC_TF]:
        assert {tr.child_frame_id for tr in m.transforms} == {f"camera_{i}" for i in cam_ids}
        for tr in m.transforms:
            assert tr.parent_frame_id == "world" and stamp(tr.timestamp) == t
            assert tr.HasField("translation") and tr.HasField("rotation")
            q = tr.rotation
            assert abs(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2 - 1) < 1e-12
            frames.add(tr.child_frame_id)
    frames.add("world")

    def check_entity(e, t):
        assert e.frame_id in frames and e.id and stamp(e.timestamp) == t
        for prim in [*e.lines, *e.spheres, *e.texts]:
            assert prim.HasField("pose") and prim.pose.HasField("orientation")

    for topic in (C.TOPIC_ARENA, C.TOPIC_BODIES, C.TOPIC_MARKERS):
        for t, m in by_topic[topic]:
            for e in m.entities:
                check_entity(e, t)
    arena_ids = {e.id for e in by_topic[C.TOPIC_ARENA][0][1].entities}
    assert arena_ids == {"world", "floor"} | {f"camera/{i}" for i in cam_ids}
    for cid in cam_ids:
        for t, cal in by_topic[C.calibration_topic(cid)]:
            assert cal.frame_id == f"camera_{cid}" and stamp(cal.timestamp) == t
            assert cal.width > 0 and cal.height > 0 and len(cal.K) == 9 and len(cal.P) == 12 and len(cal.R) == 9
            assert cal.distortion_model in ("plumb_bob", "rational_polynomial", "kannala_brandt")
        for t, ann in by_topic[C.blobs_topic(cid)]:
            assert stamp(ann.timestamp) == t and ann.circles
            for c in ann.circles:
                assert stamp(c.timestamp) == t and c.diameter > 0 and c.HasField("position")
    for t, lg in by_topic[C.TOPIC_LOG]:
        assert stamp(lg.timestamp) == t and lg.level in (2, 3) and lg.message and lg.name.startswith("visionpos.")


def test_blob_annotations_are_the_recorded_frames_on_the_capture_clock(demo_log):
    """Each annotated frame is a recorded packet of that camera: its capture time, its blobs (+0.5 px:
    Foxglove's pixel origin is the corner of the first pixel), at most rate_hz per camera."""
    frames = {}
    for _, data in RecordingReader(demo_log).packets():
        if data[5] == P.MsgType.FRAME:
            f = P.decode(data)
            frames[(f.camera_id, f.capture_ns)] = f
    n = defaultdict(list)
    for topic, schema, t, data in foxglove_messages(demo_log):
        if schema != "foxglove.ImageAnnotations":
            continue
        cid = int(topic.split("/")[3])
        f = frames[(cid, t)]
        ann = strict_parse(schema, data)
        got = np.array([[c.position.x, c.position.y] for c in ann.circles])
        np.testing.assert_array_equal(got, f.blobs[:, :2].astype(np.float64) + 0.5)
        n[cid].append(t)
    assert set(n) == {c["id"] for c in RecordingReader(demo_log).config["cameras"]}
    for cid, ts in n.items():  # at most rate_hz (decimated on receive time: count over the camera's span)
        caps = [c for (i, c) in frames if i == cid]
        span_s = (max(caps) - min(caps)) * 1e-9
        assert 10 <= len(ts) <= span_s * C.DEFAULT_RATE_HZ + 2


def test_body_pose_is_the_recorded_output_pose(demo_log):
    """A body entity at time t carries exactly the pose the server output at t; a lost body has no entity."""
    states = {(s.name, s.time_ns): s for s in RecordingReader(demo_log).states()}
    seen = 0
    for topic, schema, t, data in foxglove_messages(demo_log):
        if topic != C.TOPIC_BODIES:
            continue
        for e in strict_parse(schema, data).entities:
            name = e.id.removeprefix("body/")
            s = states[(name, t)]
            assert s.tracked
            pose = e.lines[0].pose
            assert [pose.position.x, pose.position.y, pose.position.z] == s.position.tolist()
            assert [pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w] == \
                s.quaternion.tolist()
            assert 0 < stamp(e.lifetime) <= C.LIFETIME_PERIODS * 1e9 / C.DEFAULT_RATE_HZ + 1
            seen += 1
    assert seen > 20


def test_copy_of_an_old_recording_has_the_same_channels(demo_log, tmp_path):
    """`replay LOG --foxglove OUT`: a recording without Foxglove channels gets the ones the live writer makes."""
    old = tmp_path / "old.mcap"
    reader = RecordingReader(demo_log)
    with RecordingWriter(old, reader.config, reader.meta, foxglove_rate_hz=None) as w:
        for topic, t, data, ch in reader.messages():
            if topic == "/station/packets":
                w.write_packet(t, data, (ch.metadata["host"], int(ch.metadata["port"])))
            elif topic == "/fusion/states":
                w.write_state(state_from_dict(json.loads(data)))
            elif topic == "/fusion/markers":
                d = json.loads(data)
                w.publish_markers(LoosePoints(t, np.array(d["points"], dtype=float).reshape(-1, 3)))
            elif not topic.startswith("/foxglove/") and topic != "/sim/truth":
                w.write_json(topic, t, json.loads(data))
    assert not any(t.startswith("/foxglove/") for t in RecordingReader(old).topics())
    out = tmp_path / "fox.mcap"
    rep = foxglove_copy(old, out)
    live = sorted(foxglove_messages(demo_log))
    assert rep["foxglove_messages"] == len(live) > 0
    assert sorted(foxglove_messages(out)) == live
    assert RecordingReader(out).topics()["/station/packets"] == RecordingReader(old).topics()["/station/packets"]


# ---------------------------------------------------------------- FoxgloveChannels alone


def _state(name: str, t: int, tracked: bool, pos=(1.0, 2.0, 3.0)) -> BodyState:
    nan3 = np.full(3, np.nan)
    return BodyState(name=name, body_id=1, time_ns=t, capture_ns=t, position=np.array(pos) if tracked else nan3,
                     quaternion=np.array([0.0, 0.0, 0.0, 1.0]) if tracked else np.full(4, np.nan),
                     velocity=nan3, angular_velocity=nan3, covariance=np.eye(6), velocity_covariance=np.eye(3),
                     tracked=tracked)


def _bodies(out):
    return [strict_parse(s, d) for topic, s, t, d in out if topic == C.TOPIC_BODIES]


def test_lost_body_is_deleted_at_once_and_never_drawn():
    fox = C.FoxgloveChannels([], rate_hz=10)  # a period of 100 ms
    (u,) = _bodies(fox.states([_state("a", 1_000, True), _state("b", 1_000, True)]))
    assert [e.id for e in u.entities] == ["body/a", "body/b"] and not u.deletions
    # b lost within the period: deleted now, not at the next update
    (u,) = _bodies(fox.states([_state("a", 2_000, True), _state("b", 2_000, False)]))
    assert [e.id for e in u.entities] == ["body/a"]
    assert [(d.id, d.type, stamp(d.timestamp)) for d in u.deletions] == [("body/b", 0, 2_000)]
    assert fox.states([_state("a", 3_000, True), _state("b", 3_000, False)]) == []  # rate limit
    (u,) = _bodies(fox.states([_state("a", 100_002_000, True), _state("b", 100_002_000, False)]))
    assert [e.id for e in u.entities] == ["body/a"] and not u.deletions
    # tracked but with a NaN pose (never produced by the filter, but never drawn either)
    bad = _state("a", 300_000_000, True, pos=(np.nan, 0.0, 0.0))
    (u,) = _bodies(fox.states([bad]))
    assert not u.entities


def test_realtime_stamped_frames_are_put_on_the_capture_clock():
    """A station on PTP stamps CLOCK_REALTIME; the annotation must be on the server clock, as fusion has it."""
    rt = 1_700_000_000_000_000_000
    from visionpos.camera.model import Camera, CameraModel

    cam = Camera(7, "c", CameraModel("pinhole", 640, 480, 500.0, 500.0, 319.5, 239.5), np.eye(3), np.zeros(3))
    fox = C.FoxgloveChannels([cam], rate_hz=30, realtime_minus_monotonic_ns=rt)
    hello = P.encode(P.Hello(station_id=1, camera_id=7, session=99, width=640, height=480, fps=100.0,
                             timebase=P.Timebase.REALTIME, counter=1))
    assert fox.packet(10, hello) == []
    blobs = np.array([[10.0, 20.0, 12.0, 200.0]], dtype=np.float32)
    frame = P.encode_frame(BlobFrame(7, 1, rt + 5_000_000_000, blobs, 1, 0, 0, 99))
    out = fox.packet(5_000_100_000, frame)
    (ann,) = [(t, d) for topic, s, t, d in out if topic == C.blobs_topic(7)]
    assert ann[0] == 5_000_000_000
    assert stamp(strict_parse("foxglove.ImageAnnotations", ann[1]).timestamp) == 5_000_000_000
    assert fox.packet(5_000_200_000, frame) == []  # the next one is due a period later


def test_packets_of_unknown_cameras_and_garbage_give_nothing():
    fox = C.FoxgloveChannels([], rate_hz=30)
    frame = P.encode_frame(BlobFrame(3, 1, 5, np.zeros((0, 4), np.float32), 1, 0, 0, 1))
    assert fox.packet(10, frame) == [] and fox.packet(10, b"VPOS") == [] and fox.packet(10, bytes(40)) == []


def test_recording_puts_realtime_frames_on_the_clock_its_meta_states(tmp_path):
    """The writer converts with the realtime - monotonic difference of the recording's meta (what replay
    uses), and a frame that would land before the clock's origin is left out (MCAP times are unsigned)."""
    from visionpos.config.arena import load_arena

    arena = load_arena("thesis")
    rt = 1_700_000_000_000_000_000 - 1_000_000_000_000
    meta = {"wall_start_unix_ns": rt + 5_000_000_000, "monotonic_start_ns": 5_000_000_000}
    path = tmp_path / "rt.mcap"
    cam = arena.cameras[0].id
    with RecordingWriter(path, arena.raw, meta) as w:
        hello = P.Hello(station_id=1, camera_id=cam, session=9, width=640, height=480, fps=100.0,
                        timebase=P.Timebase.REALTIME, counter=1)
        w.write_packet(1, P.encode(hello))
        blobs = np.array([[100.0, 50.0, 9.0, 200.0]], dtype=np.float32)
        w.write_packet(6_000_000_000, P.encode_frame(BlobFrame(cam, 1, rt + 5_990_000_000, blobs, 1, 0, 0, 9)))
        w.write_packet(7_000_000_000, P.encode_frame(BlobFrame(cam, 2, rt - 10, blobs, 1, 0, 0, 9)))
    got = [(topic, t) for topic, s, t, d in foxglove_messages(path) if topic == C.blobs_topic(cam)]
    assert got == [(C.blobs_topic(cam), 5_990_000_000)]

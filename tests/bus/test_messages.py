"""Message catalogue, keys, encodings and (de)serialisation."""

from __future__ import annotations

import contextlib
import math

import pytest
from google.protobuf.descriptor import FieldDescriptor
from hypothesis import given
from hypothesis import strategies as st
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from services.bus import messages as m
from services.bus.messages import (
    ArmCommand,
    ArmState,
    CompressedImage,
    Goal,
    InvalidKeyError,
    Keys,
    MessageDecodeError,
    decode,
    encode,
    stamp_ns_of,
)


def test_keys_default_and_custom_prefix() -> None:
    k = Keys()
    assert k.arm_state.key == "psm/arm/state"
    assert k.arm_command.key == "psm/arm/command"
    assert k.goal("person").key == "psm/goals/person"
    assert k.goals_all.key == "psm/goals/*"
    assert k.vision_faces.key == "psm/vision/faces"
    assert k.camera_image("cam0").key == "psm/camera/cam0/image"
    assert k.obstacles.key == "psm/obstacles"
    assert k.collision.key == "psm/collision"
    assert k.planner_status.key == "psm/planner/status"
    assert k.task_events.key == "psm/task/events"
    assert k.status("arm").key == "psm/status/arm"
    assert k.liveliness("arm").key == "psm/alive/arm"
    assert k.arm_transforms.key == "psm/arm/transforms"
    assert k.all.key == "psm/**"
    cell = Keys("cell2/psm")
    assert cell.arm_state.key == "cell2/psm/arm/state"
    assert str(cell.goal("cup")) == "cell2/psm/goals/cup"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "x*", "$x", "a b", "q?", "#"])
def test_invalid_names_rejected(bad: str) -> None:
    with pytest.raises(InvalidKeyError):
        Keys().goal(bad)


@pytest.mark.parametrize("bad", ["", "psm/", "/psm", "psm/*", "a//b", "ps m"])
def test_invalid_prefix_rejected(bad: str) -> None:
    with pytest.raises(InvalidKeyError):
        Keys(bad)


def test_topic_for_key_inverts_catalogue() -> None:
    k = Keys("a/psm")
    for topic in k.catalogue("x_1"):
        assert k.topic_for_key(topic.key) == topic
    assert k.topic_for_key("a/psm/goals/x/y") is None
    assert k.topic_for_key("psm/arm/state") is None  # other prefix


def test_qos_per_stream_class() -> None:
    k = Keys()
    for t in (k.arm_state, k.arm_command):
        assert t.qos.express and t.qos.priority == "REAL_TIME"
        assert t.qos.congestion == "BLOCK"
    assert k.camera_image("c").qos.congestion == "DROP"
    for t in (k.goal("g"), k.obstacles, k.scene, k.goal_pose("g")):
        assert t.qos.history >= 1
    for sel in k.latched_selectors():
        assert sel.qos.history >= 1


def test_every_project_message_has_stamp_and_sequence() -> None:
    for name, cls in m.MESSAGE_TYPES.items():
        if not name.startswith("psm."):
            continue
        f1 = cls.DESCRIPTOR.fields_by_number[1]
        assert (f1.name, f1.type) == ("stamp_ns", FieldDescriptor.TYPE_INT64), name
        f2 = cls.DESCRIPTOR.fields_by_number[2]
        assert f2.name in ("seq", "tick") and f2.type == FieldDescriptor.TYPE_UINT64, name


def test_command_echoes_state_tick() -> None:
    assert ArmCommand.DESCRIPTOR.fields_by_name["tick"].type == FieldDescriptor.TYPE_UINT64
    assert set(ArmCommand.Mode.keys()) >= {"CARTESIAN_ACCELERATION", "JOINT_ACCELERATION"}


def test_encoding_names_schema() -> None:
    _payload, enc = encode(ArmState(stamp_ns=1, tick=2))
    assert enc == "application/protobuf;psm.ArmState"
    _, enc = encode(CompressedImage(format="jpeg"))
    assert enc == "application/protobuf;foxglove.CompressedImage"
    import zenoh

    assert str(zenoh.Encoding.APPLICATION_PROTOBUF.with_schema("psm.ArmState")) == (
        "application/protobuf;psm.ArmState"
    )


def test_roundtrip_all_types() -> None:
    for cls in m.MESSAGE_TYPES.values():
        msg = cls()
        if "stamp_ns" in cls.DESCRIPTOR.fields_by_name:
            msg.stamp_ns = 123
        payload, enc = encode(msg)
        assert decode(payload, enc, cls) == msg


@pytest.mark.parametrize(
    ("payload", "encoding", "expected", "needle"),
    [
        (b"\xff\xff\xff", "application/protobuf;psm.ArmState", None, "malformed psm.ArmState"),
        (b"\x0a\x05ab", "application/protobuf;psm.Goal", None, "malformed psm.Goal"),
        (b"", "text/plain", None, "unsupported encoding"),
        (b"", "application/protobuf;psm.Nope", None, "unknown schema"),
        (b"", "application/protobuf;psm.Goal", ArmState, "wrong message type psm.Goal"),
    ],
)
def test_decode_errors_are_clear(payload, encoding, expected, needle) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(MessageDecodeError) as ei:
        decode(payload, encoding, expected)
    assert needle in str(ei.value)
    assert "\n" not in str(ei.value)


@given(st.binary(max_size=64))
def test_decode_never_raises_anything_else(data: bytes) -> None:
    for cls in (ArmState, ArmCommand, Goal):
        with contextlib.suppress(MessageDecodeError):
            decode(data, m.encoding_for(cls))


@given(st.integers(min_value=-(2**63), max_value=2**63 - 1), st.integers(0, 2**64 - 1))
def test_stamp_ns_of_reads_int64_field(stamp: int, tick: int) -> None:
    payload, enc = encode(ArmState(stamp_ns=stamp, tick=tick, q=[1.0, 2.0]))
    # 0 is a valid stamp (sim time 0); a negative one cannot be an MCAP time
    assert stamp_ns_of(payload, enc) == (stamp if stamp >= 0 else None)


@given(st.integers(0, 18_000_000_000), st.integers(0, 999_999_999))
def test_stamp_ns_of_reads_foxglove_timestamp(sec: int, nanos: int) -> None:
    img = CompressedImage(format="jpeg", data=b"\xff\xd8" * 10)
    img.timestamp.seconds = sec
    img.timestamp.nanos = nanos
    payload, enc = encode(img)
    assert stamp_ns_of(payload, enc) == sec * 1_000_000_000 + nanos  # 0 included
    img.timestamp.seconds = 2**40  # beyond MCAP's uint64 ns: no usable stamp
    assert stamp_ns_of(*encode(img)) is None


def test_stamp_ns_of_foxglove_containers_and_absent_stamps() -> None:
    from services.bus.messages import FrameTransforms, PoseInFrame, SceneUpdate

    no_stamp = CompressedImage(format="jpeg", data=b"x")
    assert stamp_ns_of(*encode(no_stamp)) is None  # no timestamp field at all
    tf = FrameTransforms()
    assert stamp_ns_of(*encode(tf)) is None  # no transforms, no stamp
    for i, ns in enumerate((0, 3_000_000)):
        t = tf.transforms.add(parent_frame_id="base", child_frame_id=f"link{i}")
        t.timestamp.FromNanoseconds(ns)
    assert stamp_ns_of(*encode(tf)) == 0  # the first transform's stamp, 0 valid
    tf.transforms[0].timestamp.FromNanoseconds(7_000_000_001)
    assert stamp_ns_of(*encode(tf)) == 7_000_000_001
    pose = PoseInFrame(frame_id="base")
    pose.timestamp.FromNanoseconds(0)
    assert stamp_ns_of(*encode(pose)) == 0
    scene = SceneUpdate()
    assert stamp_ns_of(*encode(scene)) is None
    scene.deletions.add(id="old").timestamp.FromNanoseconds(5)
    assert stamp_ns_of(*encode(scene)) == 5
    scene.entities.add(id="box").timestamp.FromNanoseconds(9)
    assert stamp_ns_of(*encode(scene)) == 9  # entities first


def test_stamp_ns_of_garbage_is_none() -> None:
    assert stamp_ns_of(b"\x08\xff", "application/protobuf;psm.ArmState") is None
    assert stamp_ns_of(b"\x08\x05", "text/plain") is None


def test_file_descriptor_set_decodes_without_project() -> None:
    """The schema bytes alone (as stored in MCAP) let mcap_protobuf decode every type."""
    factory = DecoderFactory()
    for i, (name, cls) in enumerate(m.MESSAGE_TYPES.items(), start=1):
        schema = Schema(id=i, name=name, encoding="protobuf", data=m.file_descriptor_set(name))
        dec = factory.decoder_for("protobuf", schema)
        assert dec is not None
        msg = cls()
        if "stamp_ns" in cls.DESCRIPTOR.fields_by_name:
            msg.stamp_ns = 42
        out = dec(msg.SerializeToString())
        assert out.DESCRIPTOR.full_name == name
        assert out.SerializeToString() == msg.SerializeToString()


def test_helpers() -> None:
    assert m.vec3(1, 2, 3).z == 3.0
    assert m.quat(0, 0, 0, 1).w == 1.0
    assert m.all_finite([1.0, 2.0]) and not m.all_finite([1.0, math.nan])

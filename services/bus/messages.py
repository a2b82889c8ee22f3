"""Every message type, key expression and Zenoh encoding on the PSM bus — in one place.

Nothing else in the repository hard-codes a key string or an encoding: services build their keys
from :class:`Keys` and (de)serialise with :func:`encode` / :func:`decode`.

* Message types are protobuf: the project's own schemas (``services/bus/proto/psm.proto``,
  package ``psm``) and Foxglove's published schemas for images, transforms and 3-D scenes.
* The Zenoh encoding of every sample names its schema: ``application/protobuf;<full name>``,
  e.g. ``application/protobuf;psm.ArmState``. The recorder therefore needs no topic table: it maps
  the schema name to a protobuf ``FileDescriptorSet`` (:func:`file_descriptor_set`) that it
  stores in the MCAP channel's schema, so Foxglove and the ``mcap`` CLI decode without the project.
* Every project message has ``int64 stamp_ns = 1`` (nanoseconds) and a sequence/tick number;
  :func:`stamp_ns_of` reads the stamp (or a Foxglove message's ``timestamp``) straight from the
  bytes: it is the MCAP ``publish_time`` of a recording.
* Each :class:`Topic` carries its quality of service (:class:`QoS`): control-loop streams are
  express and real-time priority, camera frames are droppable, goals and obstacle sets are kept
  for late joiners.

Example::

    from services.bus.messages import ArmState, Keys, decode, encode

    keys = Keys("psm")
    topic = keys.arm_state                 # Topic(key='psm/arm/state', msg_type=ArmState, ...)
    payload, encoding = encode(ArmState(stamp_ns=2_000_000, tick=1, q=[0.0] * 7))
    msg = decode(payload, encoding, expected=ArmState)   # raises MessageDecodeError if malformed
    assert keys.goal("person").key == "psm/goals/person"
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum
from functools import cache
from typing import Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import DecodeError, Message

from services.bus.proto_gen.psm_pb2 import (
    ArmCommand,
    ArmState,
    CollisionPrediction,
    FaceBox,
    FaceDetections,
    Goal,
    GripperCommand,
    Obstacle,
    ObstacleCommand,
    ObstacleSet,
    PlannerStatus,
    Quat,
    ServiceStatus,
    TaskEvent,
    Vec3,
)

__all__ = [
    "DEFAULT_PREFIX",
    "ENCODING_PREFIX",
    "MESSAGE_TYPES",
    "ArmCommand",
    "ArmState",
    "CollisionPrediction",
    "CompressedImage",
    "FaceBox",
    "FaceDetections",
    "FrameTransforms",
    "Goal",
    "GripperCommand",
    "ImageAnnotations",
    "InvalidKeyError",
    "Keys",
    "MessageDecodeError",
    "Obstacle",
    "ObstacleCommand",
    "ObstacleSet",
    "PlannerStatus",
    "PoseInFrame",
    "QoS",
    "Quat",
    "SceneUpdate",
    "ServiceStatus",
    "StreamClass",
    "TaskEvent",
    "Topic",
    "Vec3",
    "clock_sampler_qos",
    "clock_sampler_zid",
    "decode",
    "encode",
    "encoding_for",
    "file_descriptor_set",
    "message_type_for_encoding",
    "schema_name_of",
    "stamp_ns_of",
    "validate_key_expr",
]

#: Default key-expression prefix; two cells on one network use two prefixes.
DEFAULT_PREFIX = "psm"

#: Every sample's encoding is this string followed by the message's full protobuf name.
ENCODING_PREFIX = "application/protobuf;"

#: Every message type that may appear on the bus, by full protobuf name.
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.DESCRIPTOR.full_name: cls
    for cls in (
        ArmState,
        ArmCommand,
        Goal,
        FaceDetections,
        ObstacleSet,
        ObstacleCommand,
        CollisionPrediction,
        PlannerStatus,
        TaskEvent,
        GripperCommand,
        ServiceStatus,
        CompressedImage,
        ImageAnnotations,
        FrameTransforms,
        SceneUpdate,
        PoseInFrame,
    )
}

# Where each type keeps its own stamp (see :func:`stamp_ns_of`): field 1 ``int64 stamp_ns`` (the
# project's convention), field 1 ``google.protobuf.Timestamp timestamp`` (Foxglove's
# CompressedImage, PoseInFrame), field 5 ``timestamp`` (ImageAnnotations), the timestamp of the
# first element of a repeated field 1 (FrameTransforms.transforms) or of SceneUpdate's entities
# (field 2), else its deletions (1).
_INT64_STAMP_TYPES = frozenset(
    name for name, cls in MESSAGE_TYPES.items() if name.startswith("psm.")
)
_TIMESTAMP_TYPES = frozenset({"foxglove.CompressedImage", "foxglove.PoseInFrame"})
_TIMESTAMP5_TYPES = frozenset({"foxglove.ImageAnnotations"})
_FIRST_ITEM_TIMESTAMP_TYPES = frozenset({"foxglove.FrameTransforms"})
_SCENE_TYPES = frozenset({"foxglove.SceneUpdate"})


class MessageDecodeError(ValueError):
    """A payload cannot be decoded: unknown/unsupported encoding, wrong type for the key, or
    malformed protobuf bytes. The message is one line naming the schema and the cause;
    :attr:`kind` is the rejection reason counted on a service's status (``encoding``,
    ``schema``, ``type`` or ``malformed``)."""

    def __init__(self, message: str, kind: str = "malformed") -> None:
        super().__init__(message)
        self.kind = kind


class InvalidKeyError(ValueError):
    """An invalid key-expression prefix or name (empty, wildcard, ``/`` inside a name, ...)."""


# --------------------------------------------------------------------------------------------
# Quality of service
# --------------------------------------------------------------------------------------------


class StreamClass(Enum):
    """How a stream is delivered; maps to Zenoh QoS in :mod:`services.bus.runtime`."""

    CONTROL = "control"
    """Control loop (arm state / command): express (no batching delay), real-time priority
    (never queued behind bulk data), reliable and blocking under congestion: lockstep runs must
    not lose a state or a command."""
    DROPPABLE = "droppable"
    """Bulk sensor data (camera frames): low priority, dropped under congestion."""
    LATCHED = "latched"
    """Sparse state (goals, obstacle sets): reliable, last sample cached by the publisher and
    delivered to late-joining subscribers (zenoh advanced publisher/subscriber)."""
    DATA = "data"
    """Everything else (status, detections, events): default priority, reliable, blocking."""


@dataclass(frozen=True)
class QoS:
    """Per-stream quality of service (Zenoh names; ``priority`` is a :class:`zenoh.Priority`
    member name).

    ``history`` is the number of samples the publisher keeps for late joiners (0 = none).
    """

    stream_class: StreamClass
    priority: str = "DATA"
    express: bool = False
    congestion: str = "BLOCK"  # "BLOCK" or "DROP"
    history: int = 0
    nominal_rate_hz: float = 0.0  # documentation: expected publication rate (0 = on change)


QOS_CONTROL = QoS(StreamClass.CONTROL, "REAL_TIME", True, "BLOCK", 0, 500.0)
QOS_CAMERA = QoS(StreamClass.DROPPABLE, "DATA_LOW", False, "DROP", 0, 30.0)
QOS_LATCHED = QoS(StreamClass.LATCHED, "DATA_HIGH", False, "BLOCK", 1, 0.0)
QOS_DATA = QoS(StreamClass.DATA, "DATA", False, "BLOCK", 0, 0.0)


def clock_sampler_zid(prefix: str) -> str:
    """The zenoh id of the session that samples ``<prefix>/arm/state`` as its clock (the
    synthetic camera on the arm's clock): 32 hex digits fixed by the prefix, so that the
    sessions sending it the state can name it in :func:`clock_sampler_qos`. One such session
    per prefix."""
    return "1" + hashlib.sha256(f"psm clock sampler {prefix}".encode()).hexdigest()[:31]


def clock_sampler_qos(keys: Keys) -> list[dict[str, Any]]:
    """zenoh ``qos/network`` rules of the sessions that send the arm's state (the arm, the
    router): to the clock sampler (:func:`clock_sampler_zid`) it goes droppable. The state is a
    control stream, blocking under congestion; a sampler that stalls or is cut off (a camera on
    another host) would otherwise block its sender for zenoh's ``wait_before_close`` (5 s), and
    with it the control loop, before zenoh closes the link. The sampler only ever uses the
    newest state (``"latest"`` delivery), so a dropped one costs it nothing."""
    return [{
        "zids": [clock_sampler_zid(keys.prefix)],
        "key_exprs": [keys.arm_state.key],
        "messages": ["put"],
        "flows": ["egress"],
        "overwrite": {"congestion_control": "drop"},
    }]


@dataclass(frozen=True)
class Topic:
    """One stream on the bus: its key expression, message type and QoS.

    ``msg_type`` is ``None`` for liveliness tokens (no payload) and for wildcard selectors
    that match several types (e.g. ``<prefix>/**``). ``commands`` names the service that acts
    on this stream's messages (``"arm"`` for the arm command topic; ``""`` for every stream
    that only informs): the replayer leaves command streams out unless asked, and refuses
    them while that service is alive (its liveliness token ``Keys.liveliness(commands)``).
    """

    key: str
    msg_type: type[Message] | None
    qos: QoS = QOS_DATA
    commands: str = ""

    @property
    def is_command(self) -> bool:
        """True if publishing on this topic makes a service act (e.g. moves the arm)."""
        return bool(self.commands)

    def __str__(self) -> str:
        return self.key

    @property
    def encoding(self) -> str | None:
        """The Zenoh encoding string of this topic's messages (``None`` if untyped)."""
        return encoding_for(self.msg_type) if self.msg_type is not None else None


_BAD_CHUNK = re.compile(r"[*$?#/\s]")


def _check_name(kind: str, name: str) -> str:
    if not isinstance(name, str) or not name or _BAD_CHUNK.search(name):
        raise InvalidKeyError(
            f"invalid {kind} {name!r}: must be one non-empty key chunk without '/', '*', '$', "
            "'?', '#' or whitespace"
        )
    return name


def validate_key_expr(expr: str) -> str:
    """Check a key expression given by a user (``psm echo KEYEXPR``, ``psm record -k``,
    ``psm replay --topics/--exclude``) before anything is declared with it; returns it.

    Raises :class:`InvalidKeyError` naming the expression and Zenoh's reason, e.g.
    ``invalid key expression 'bad//key': empty chunks are forbidden, ...``.
    """
    import zenoh

    from services.bus.errors import zenoh_reason

    if not isinstance(expr, str):
        raise InvalidKeyError(f"invalid key expression {expr!r}: not a string")
    try:
        zenoh.KeyExpr(expr)
    except zenoh.ZError as exc:
        reason = zenoh_reason(exc)
        reason = re.sub(r"^Invalid Key Expr `.*?`:\s*", "", reason)
        raise InvalidKeyError(f"invalid key expression {expr!r}: {reason}") from None
    return expr


def _check_prefix(prefix: str) -> str:
    if not isinstance(prefix, str) or not prefix:
        raise InvalidKeyError("invalid prefix '': must be non-empty, e.g. 'psm' or 'cell1/psm'")
    for chunk in prefix.split("/"):
        _check_name("prefix chunk", chunk)
    return prefix


class Keys:
    """Key expressions of one cell, all under ``prefix`` (default ``psm``).

    Fixed streams are properties, parametrised ones are methods; each returns a :class:`Topic`
    (``str(topic)`` / ``topic.key`` is the key expression).
    """

    def __init__(self, prefix: str = DEFAULT_PREFIX) -> None:
        self.prefix = _check_prefix(prefix)

    def __repr__(self) -> str:
        return f"Keys({self.prefix!r})"

    def _k(self, *chunks: str) -> str:
        return "/".join((self.prefix, *chunks))

    # -- arm ---------------------------------------------------------------------------------
    @property
    def arm_state(self) -> Topic:
        """``<prefix>/arm/state`` — :class:`ArmState` every control tick (500 Hz nominal)."""
        return Topic(self._k("arm", "state"), ArmState, QOS_CONTROL)

    @property
    def arm_command(self) -> Topic:
        """``<prefix>/arm/command`` — :class:`ArmCommand`, one per :class:`ArmState`."""
        return Topic(self._k("arm", "command"), ArmCommand, QOS_CONTROL, commands="arm")

    @property
    def arm_transforms(self) -> Topic:
        """``<prefix>/arm/transforms`` — foxglove ``FrameTransforms`` of the arm links
        (visualisation, throttled, e.g. 50 Hz)."""
        return Topic(
            self._k("arm", "transforms"),
            FrameTransforms,
            QoS(StreamClass.DATA, "DATA", False, "DROP", 0, 50.0),
        )

    @property
    def arm_model(self) -> Topic:
        """``<prefix>/viz/arm`` — foxglove ``SceneUpdate`` of the arm's link meshes (one entity
        per link, in that link's frame of ``arm_transforms``), once at the arm's start, latched."""
        return Topic(self._k("viz", "arm"), SceneUpdate, QOS_LATCHED)

    # -- goals ---------------------------------------------------------------------------------
    def goal(self, name: str) -> Topic:
        """``<prefix>/goals/<name>`` — :class:`Goal`, latched for late joiners."""
        return Topic(self._k("goals", _check_name("goal name", name)), Goal, QOS_LATCHED)

    @property
    def goals_all(self) -> Topic:
        """``<prefix>/goals/*`` — selector matching every goal."""
        return Topic(self._k("goals", "*"), Goal, QOS_LATCHED)

    def goal_pose(self, name: str) -> Topic:
        """``<prefix>/viz/goals/<name>`` — foxglove ``PoseInFrame`` of a goal (for the 3-D
        panel), latched."""
        return Topic(
            self._k("viz", "goals", _check_name("goal name", name)), PoseInFrame, QOS_LATCHED
        )

    # -- perception ----------------------------------------------------------------------------
    @property
    def vision_faces(self) -> Topic:
        """``<prefix>/vision/faces`` — :class:`FaceDetections` per analysed frame."""
        return Topic(
            self._k("vision", "faces"),
            FaceDetections,
            QoS(StreamClass.DATA, "DATA", False, "BLOCK", 0, 30.0),
        )

    def camera_image(self, cam_id: str) -> Topic:
        """``<prefix>/camera/<cam_id>/image`` — foxglove ``CompressedImage`` (JPEG),
        droppable."""
        return Topic(
            self._k("camera", _check_name("camera id", cam_id), "image"),
            CompressedImage,
            QOS_CAMERA,
        )

    def camera_annotations(self, cam_id: str) -> Topic:
        """``<prefix>/camera/<cam_id>/annotations`` — foxglove ``ImageAnnotations``: the face
        boxes of each analysed frame, stamped with the frame's stamp, drawn on the camera's
        images by Foxglove's Image panel."""
        return Topic(
            self._k("camera", _check_name("camera id", cam_id), "annotations"),
            ImageAnnotations,
            QoS(StreamClass.DATA, "DATA", False, "DROP", 0, 30.0),
        )

    @property
    def camera_annotations_all(self) -> Topic:
        """``<prefix>/camera/*/annotations`` — selector matching every camera's annotations."""
        return Topic(self._k("camera", "*", "annotations"), ImageAnnotations,
                     QoS(StreamClass.DATA, "DATA", False, "DROP", 0, 30.0))

    @property
    def camera_images_all(self) -> Topic:
        """``<prefix>/camera/*/image`` — selector matching every camera's images."""
        return Topic(self._k("camera", "*", "image"), CompressedImage, QOS_CAMERA)

    @property
    def obstacles(self) -> Topic:
        """``<prefix>/obstacles`` — :class:`ObstacleSet`, latched."""
        return Topic(self._k("obstacles"), ObstacleSet, QOS_LATCHED)

    @property
    def obstacles_command(self) -> Topic:
        """``<prefix>/obstacles/command`` — :class:`ObstacleCommand` (add, move, remove by id)."""
        return Topic(self._k("obstacles", "command"), ObstacleCommand, QOS_DATA)

    @property
    def scene(self) -> Topic:
        """``<prefix>/viz/scene`` — foxglove ``SceneUpdate`` (obstacles, goals as 3-D
        entities), latched."""
        return Topic(self._k("viz", "scene"), SceneUpdate, QOS_LATCHED)

    @property
    def collision(self) -> Topic:
        """``<prefix>/collision`` — :class:`CollisionPrediction` (on every check)."""
        return Topic(
            self._k("collision"),
            CollisionPrediction,
            QoS(StreamClass.DATA, "INTERACTIVE_HIGH", True, "BLOCK", 0, 0.0),
        )

    # -- planning ------------------------------------------------------------------------------
    @property
    def planner_status(self) -> Topic:
        """``<prefix>/planner/status`` — :class:`PlannerStatus` (e.g. 10-50 Hz)."""
        return Topic(self._k("planner", "status"), PlannerStatus, QOS_DATA)

    @property
    def planner_goal(self) -> Topic:
        """``<prefix>/planner/goal`` — :class:`Goal`: the goal the active step is heading to
        (offset included), on every change, latched (the obstacle monitor tests the segment to
        it)."""
        return Topic(self._k("planner", "goal"), Goal, QOS_LATCHED)

    @property
    def viz_plan(self) -> Topic:
        """``<prefix>/viz/plan`` — foxglove ``SceneUpdate`` of the task: the goal in use, the
        task's static goals, the segment from the end effector to the goal and the end
        effector's path so far (at the planner's status rate)."""
        return Topic(
            self._k("viz", "plan"), SceneUpdate, QoS(StreamClass.DATA, "DATA_LOW", False, "DROP", 0, 20.0)
        )

    @property
    def task_events(self) -> Topic:
        """``<prefix>/task/events`` — :class:`TaskEvent` on every sequencer transition."""
        return Topic(self._k("task", "events"), TaskEvent, QOS_DATA)

    @property
    def gripper_command(self) -> Topic:
        """``<prefix>/gripper/command`` — :class:`GripperCommand` (open / close, from the task)."""
        return Topic(self._k("gripper", "command"), GripperCommand, QOS_DATA)

    # -- health --------------------------------------------------------------------------------
    def status(self, service: str) -> Topic:
        """``<prefix>/status/<service>`` — :class:`ServiceStatus`, periodic (1 Hz default)."""
        return Topic(
            self._k("status", _check_name("service name", service)),
            ServiceStatus,
            QoS(StreamClass.DATA, "DATA_LOW", False, "DROP", 0, 1.0),
        )

    @property
    def status_all(self) -> Topic:
        """``<prefix>/status/*`` — selector matching every service's status."""
        return Topic(self._k("status", "*"), ServiceStatus, QOS_DATA)

    def liveliness(self, service: str) -> Topic:
        """``<prefix>/alive/<service>`` — liveliness token key of a service (no payload)."""
        return Topic(self._k("alive", _check_name("service name", service)), None, QOS_DATA)

    @property
    def liveliness_all(self) -> Topic:
        """``<prefix>/alive/*`` — selector matching every service's liveliness token."""
        return Topic(self._k("alive", "*"), None, QOS_DATA)

    @property
    def viz_goals_all(self) -> Topic:
        """``<prefix>/viz/goals/*`` — selector matching every goal pose."""
        return Topic(self._k("viz", "goals", "*"), PoseInFrame, QOS_LATCHED)

    def latched_selectors(self) -> list[Topic]:
        """Selectors covering every latched stream (one QoS class each), for subscribers that
        want late-joiner history for everything (the recorder)."""
        return [self.goals_all, self.viz_goals_all, self.obstacles, self.scene, self.planner_goal,
                self.arm_model]

    @property
    def all(self) -> Topic:
        """``<prefix>/**`` — everything in this cell (what the recorder subscribes to)."""
        return Topic(self._k("**"), None, QOS_DATA)

    def topic_for_key(self, key: str) -> Topic | None:
        """The catalogue :class:`Topic` a concrete key belongs to (``None`` if the key is not
        part of the catalogue), e.g. ``psm/goals/cup`` -> ``keys.goal("cup")``."""
        if not key.startswith(self.prefix + "/"):
            return None
        rest = key[len(self.prefix) + 1 :]
        for pattern, make in _KEY_PATTERNS:
            m = pattern.fullmatch(rest)
            if m is not None:
                return make(self, *m.groups())
        return None

    def remap(self, key: str, new_prefix: str) -> str:
        """Move ``key`` from this prefix to ``new_prefix`` (keys outside the prefix unchanged)."""
        _check_prefix(new_prefix)
        if key == self.prefix or key.startswith(self.prefix + "/"):
            return new_prefix + key[len(self.prefix) :]
        return key

    def catalogue(self, example_name: str = "<name>") -> Iterator[Topic]:
        """Every concrete stream of the cell (parametrised ones with ``example_name``), for
        documentation and tests."""
        yield self.arm_state
        yield self.arm_command
        yield self.arm_transforms
        yield self.arm_model
        yield self.goal(example_name)
        yield self.goal_pose(example_name)
        yield self.vision_faces
        yield self.camera_image(example_name)
        yield self.camera_annotations(example_name)
        yield self.obstacles
        yield self.obstacles_command
        yield self.scene
        yield self.collision
        yield self.planner_status
        yield self.planner_goal
        yield self.viz_plan
        yield self.task_events
        yield self.gripper_command
        yield self.status(example_name)


_NAME = r"([^/*$?#\s]+)"
_KEY_PATTERNS: list[tuple[re.Pattern[str], Any]] = [
    (re.compile("arm/state"), lambda k: k.arm_state),
    (re.compile("arm/command"), lambda k: k.arm_command),
    (re.compile("arm/transforms"), lambda k: k.arm_transforms),
    (re.compile("viz/arm"), lambda k: k.arm_model),
    (re.compile("goals/" + _NAME), lambda k, n: k.goal(n)),
    (re.compile("viz/goals/" + _NAME), lambda k, n: k.goal_pose(n)),
    (re.compile("vision/faces"), lambda k: k.vision_faces),
    (re.compile("camera/" + _NAME + "/image"), lambda k, n: k.camera_image(n)),
    (re.compile("camera/" + _NAME + "/annotations"), lambda k, n: k.camera_annotations(n)),
    (re.compile("obstacles"), lambda k: k.obstacles),
    (re.compile("obstacles/command"), lambda k: k.obstacles_command),
    (re.compile("viz/scene"), lambda k: k.scene),
    (re.compile("collision"), lambda k: k.collision),
    (re.compile("planner/status"), lambda k: k.planner_status),
    (re.compile("planner/goal"), lambda k: k.planner_goal),
    (re.compile("viz/plan"), lambda k: k.viz_plan),
    (re.compile("task/events"), lambda k: k.task_events),
    (re.compile("gripper/command"), lambda k: k.gripper_command),
    (re.compile("status/" + _NAME), lambda k, n: k.status(n)),
]

# --------------------------------------------------------------------------------------------
# Encodings, schemas, (de)serialisation
# --------------------------------------------------------------------------------------------


def schema_name_of(msg_or_type: Message | type[Message]) -> str:
    """Full protobuf name of a message or message type, e.g. ``psm.ArmState``."""
    return msg_or_type.DESCRIPTOR.full_name


def encoding_for(msg_type: type[Message]) -> str:
    """Zenoh encoding string for ``msg_type``: ``application/protobuf;<full name>``."""
    name = schema_name_of(msg_type)
    if name not in MESSAGE_TYPES:
        raise TypeError(f"{name} is not a bus message type (see messages.MESSAGE_TYPES)")
    return ENCODING_PREFIX + name


def message_type_for_encoding(encoding: str) -> type[Message]:
    """The message type named by a Zenoh encoding string; :class:`MessageDecodeError` if the
    encoding is not ``application/protobuf;<known type>``."""
    if not isinstance(encoding, str) or not encoding.startswith(ENCODING_PREFIX):
        raise MessageDecodeError(
            f"unsupported encoding {encoding!r}: expected '{ENCODING_PREFIX}<schema>'", "encoding"
        )
    name = encoding[len(ENCODING_PREFIX) :]
    try:
        return MESSAGE_TYPES[name]
    except KeyError:
        raise MessageDecodeError(f"unknown schema {name!r} in encoding {encoding!r}", "schema") from None


def encode(msg: Message) -> tuple[bytes, str]:
    """Serialise a bus message; returns ``(payload bytes, zenoh encoding string)``."""
    return msg.SerializeToString(), encoding_for(type(msg))


def decode(
    payload: bytes | bytearray | memoryview,
    encoding: str,
    expected: type[Message] | None = None,
) -> Message:
    """Parse ``payload`` as the type named by ``encoding``.

    Raises :class:`MessageDecodeError` (one line) if the encoding is unknown, is not the
    ``expected`` type, or the bytes are not a valid message of that type.
    """
    cls = message_type_for_encoding(encoding)
    if expected is not None and cls is not expected:
        raise MessageDecodeError(
            f"wrong message type {cls.DESCRIPTOR.full_name}: expected "
            f"{expected.DESCRIPTOR.full_name}",
            "type",
        )
    msg = cls()
    try:
        msg.ParseFromString(bytes(payload))
    except (DecodeError, RuntimeError, ValueError, TypeError) as exc:
        raise MessageDecodeError(
            f"malformed {cls.DESCRIPTOR.full_name} payload ({len(payload)} bytes): {exc}"
        ) from None
    return msg


def _stamp_readers() -> tuple[type[Message], ...]:
    """Tiny message types that read only where a payload keeps its stamp (everything else is
    kept as unknown fields): ``int64 stamp_ns = 1``; ``Ts timestamp = 1`` (seconds, nanos);
    ``Ts timestamp = 5`` (ImageAnnotations); ``repeated StampTs items = 1``; SceneUpdate's
    ``repeated StampTs deletions = 1`` and ``repeated StampTs entities = 2``."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    f = descriptor_pb2.FieldDescriptorProto
    fdp = descriptor_pb2.FileDescriptorProto(
        name="psm_internal/stamp_readers.proto", package="psm_internal", syntax="proto3"
    )
    m = fdp.message_type.add(name="StampNs")
    m.field.add(name="stamp_ns", number=1, type=f.TYPE_INT64, label=f.LABEL_OPTIONAL)
    ts = fdp.message_type.add(name="Ts")
    ts.field.add(name="seconds", number=1, type=f.TYPE_INT64, label=f.LABEL_OPTIONAL)
    ts.field.add(name="nanos", number=2, type=f.TYPE_INT32, label=f.LABEL_OPTIONAL)
    m = fdp.message_type.add(name="StampTs5")
    m.field.add(name="timestamp", number=5, type=f.TYPE_MESSAGE, label=f.LABEL_OPTIONAL,
                type_name=".psm_internal.Ts")
    m = fdp.message_type.add(name="StampTs")
    m.field.add(name="timestamp", number=1, type=f.TYPE_MESSAGE, label=f.LABEL_OPTIONAL,
                type_name=".psm_internal.Ts")
    m = fdp.message_type.add(name="FirstItem")
    m.field.add(name="items", number=1, type=f.TYPE_MESSAGE, label=f.LABEL_REPEATED,
                type_name=".psm_internal.StampTs")
    m = fdp.message_type.add(name="Scene")
    m.field.add(name="deletions", number=1, type=f.TYPE_MESSAGE, label=f.LABEL_REPEATED,
                type_name=".psm_internal.StampTs")
    m.field.add(name="entities", number=2, type=f.TYPE_MESSAGE, label=f.LABEL_REPEATED,
                type_name=".psm_internal.StampTs")
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)

    def get(name: str) -> type[Message]:
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"psm_internal.{name}"))

    return get("StampNs"), get("StampTs"), get("StampTs5"), get("FirstItem"), get("Scene")


_STAMP_NS, _STAMP_TS, _STAMP_TS5, _FIRST_ITEM, _SCENE = _stamp_readers()
_MAX_STAMP_NS = (1 << 64) - 1  # MCAP times are uint64 ns


def _ts_ns(holder: Any) -> int | None:
    """``holder.timestamp`` in ns, ``None`` if the field is absent."""
    if not holder.HasField("timestamp"):
        return None
    return holder.timestamp.seconds * 1_000_000_000 + holder.timestamp.nanos


def stamp_ns_of(payload: bytes, encoding: str) -> int | None:
    """The message's own time stamp in ns, read from the bytes without decoding the rest (cheap
    enough for the recorder's hot path).

    * project messages (``psm.*``): ``int64 stamp_ns = 1``; 0 is a valid stamp (sim time 0);
    * Foxglove ``CompressedImage``, ``PoseInFrame``, ``ImageAnnotations``: ``timestamp`` (0
      valid when present);
    * Foxglove ``FrameTransforms``: the ``timestamp`` of its first transform;
    * Foxglove ``SceneUpdate``: the ``timestamp`` of its first entity, else first deletion.

    Returns ``None`` — the recorder then uses the receive time — only when the message carries
    no stamp: a type without one (unknown encodings), an absent Foxglove timestamp or an empty
    transform list, bytes that do not parse, or a stamp outside MCAP's ``[0, 2**64)`` ns.
    """
    name = encoding[len(ENCODING_PREFIX) :] if encoding.startswith(ENCODING_PREFIX) else ""
    stamp: int | None = None
    try:
        if name in _INT64_STAMP_TYPES:
            stamp = _STAMP_NS.FromString(payload).stamp_ns
        elif name in _TIMESTAMP_TYPES:
            stamp = _ts_ns(_STAMP_TS.FromString(payload))
        elif name in _TIMESTAMP5_TYPES:
            stamp = _ts_ns(_STAMP_TS5.FromString(payload))
        elif name in _FIRST_ITEM_TIMESTAMP_TYPES:
            items = _FIRST_ITEM.FromString(payload).items
            stamp = _ts_ns(items[0]) if items else None
        elif name in _SCENE_TYPES:
            scene = _SCENE.FromString(payload)
            first = scene.entities or scene.deletions
            stamp = _ts_ns(first[0]) if first else None
    except (DecodeError, RuntimeError, ValueError, TypeError):
        return None
    if stamp is None or not 0 <= stamp <= _MAX_STAMP_NS:
        return None
    return stamp


@cache
def file_descriptor_set(schema_name: str) -> bytes:
    """Serialized ``google.protobuf.FileDescriptorSet`` for a bus message type: its file and
    every dependency, dependencies first — what an MCAP ``protobuf`` schema record holds."""
    try:
        cls = MESSAGE_TYPES[schema_name]
    except KeyError:
        raise MessageDecodeError(f"unknown schema {schema_name!r}", "schema") from None
    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(cls.DESCRIPTOR.file)
    return fds.SerializeToString()


# --------------------------------------------------------------------------------------------
# Small constructors used by several services
# --------------------------------------------------------------------------------------------


def vec3(x: float, y: float, z: float) -> Vec3:
    """A :class:`Vec3` from three floats."""
    return Vec3(x=float(x), y=float(y), z=float(z))


def quat(x: float, y: float, z: float, w: float) -> Quat:
    """A :class:`Quat` (x, y, z, w) from four floats."""
    return Quat(x=float(x), y=float(y), z=float(z), w=float(w))


def all_finite(values: Any) -> bool:
    """True if every number in ``values`` (an iterable of floats) is finite."""
    return all(math.isfinite(v) for v in values)

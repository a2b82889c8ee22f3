"""docs/foxglove/psm-layout.json cannot rot silently: every topic it names is a key of the
catalogue (Keys) with the type its panel shows, and every message path walks real fields of that
type's protobuf descriptor, ending on a number where a plot needs one."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from google.protobuf.descriptor import Descriptor, FieldDescriptor

from services.arm.config import ArmSection
from services.bus.messages import (
    CompressedImage,
    FrameTransforms,
    ImageAnnotations,
    Keys,
    PoseInFrame,
    SceneUpdate,
)

ROOT = Path(__file__).resolve().parents[2]
LAYOUT = ROOT / "docs" / "foxglove" / "psm-layout.json"
KEYS = Keys("psm")

#: A message path: an unquoted topic name (Foxglove's grammar: [a-zA-Z0-9_/-]+), then fields,
#: each with an optional array index.
_PATH = re.compile(r"(?P<topic>[A-Za-z0-9_/-]+)(?P<fields>(?:\.[A-Za-z0-9_]+(?:\[-?\d+\])?)*)")
_FIELD = re.compile(r"\.([A-Za-z0-9_]+)(?:\[(-?\d+)\])?")
_NUMERIC = {
    FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT, FieldDescriptor.TYPE_INT64,
    FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_INT32, FieldDescriptor.TYPE_UINT32,
    FieldDescriptor.TYPE_SINT32, FieldDescriptor.TYPE_SINT64, FieldDescriptor.TYPE_BOOL,
    FieldDescriptor.TYPE_ENUM,
}


def _layout() -> dict[str, Any]:
    return json.loads(LAYOUT.read_text())


def _descriptor(topic: str) -> Descriptor:
    t = KEYS.topic_for_key(topic)
    assert t is not None and t.msg_type is not None, f"{topic}: not a key of the catalogue"
    return t.msg_type.DESCRIPTOR


def check_path(path: str, numeric: bool) -> Descriptor:
    """Walk ``path`` through the descriptors; returns the topic's descriptor. A numeric path
    must end on a scalar number (a repeated one indexed)."""
    m = _PATH.fullmatch(path)
    assert m is not None, f"{path!r}: not a message path"
    desc = root = _descriptor(m["topic"])
    fields = _FIELD.findall(m["fields"])
    last: FieldDescriptor | None = None
    for i, (name, index) in enumerate(fields):
        assert desc is not None, f"{path}: {fields[i - 1][0]} has no fields"
        assert name in desc.fields_by_name, f"{path}: {desc.full_name} has no field {name!r}"
        last = desc.fields_by_name[name]
        repeated = last.is_repeated
        assert not index or repeated, f"{path}: {name} is not repeated, it cannot be indexed"
        assert not repeated or index or i == len(fields) - 1, f"{path}: index {name} to go on"
        desc = last.message_type
    if numeric:
        assert last is not None and last.type in _NUMERIC, f"{path}: does not end on a number"
        indexed = bool(fields[-1][1])
        assert not last.is_repeated or indexed, f"{path}: an array, not a number"
    return root


def _panels(layout: dict[str, Any]) -> list[str]:
    """The panel ids of the mosaic tree."""
    node = layout
    if isinstance(node, str):
        return [node]
    return _panels(node["first"]) + _panels(node["second"])


def test_the_layout_has_the_format_foxglove_exports() -> None:
    doc = _layout()
    assert set(doc) == {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    assert sorted(_panels(doc["layout"])) == sorted(doc["configById"])  # every panel placed once
    kinds = {pid.split("!")[0] for pid in doc["configById"]}
    assert kinds == {"3D", "Image", "Plot", "RawMessages", "StateTransitions", "Table"}


def test_every_topic_and_message_path_exists() -> None:
    checked = 0
    for pid, cfg in _layout()["configById"].items():
        kind = pid.split("!")[0]
        if kind == "3D":
            types = {_descriptor(t).full_name for t in cfg["topics"]}
            assert types <= {c.DESCRIPTOR.full_name for c in (FrameTransforms, SceneUpdate, PoseInFrame)}
            assert cfg["followTf"] == ArmSection.model_fields["frame_id"].default
            checked += len(cfg["topics"])
        elif kind == "Image":
            assert _descriptor(cfg["imageMode"]["imageTopic"]) is CompressedImage.DESCRIPTOR
            annotations = cfg["imageMode"]["annotations"]
            assert annotations and all(a["visible"] for a in annotations.values())
            for topic in annotations:
                assert _descriptor(topic) is ImageAnnotations.DESCRIPTOR, topic
            checked += 1 + len(annotations)
        elif kind == "Plot":
            for p in cfg["paths"]:
                check_path(p["value"], numeric=True)
                checked += 1
            if cfg["xAxisVal"] == "custom":
                check_path(cfg["xAxisPath"]["value"], numeric=True)
                checked += 1
        elif kind == "StateTransitions":
            for p in cfg["paths"]:
                check_path(p["value"], numeric=True)  # an enum: one row of states per series
                checked += 1
        else:
            check_path(cfg["topicPath"], numeric=False)
            checked += 1
    assert checked >= 20


def test_the_state_panel_shows_every_service_of_the_shipped_stack() -> None:
    from services.stack import load_stack

    stack = load_stack(ROOT / "configs" / "stack.toml")
    paths = [p["value"] for p in _layout()["configById"]["StateTransitions!services"]["paths"]]
    assert paths == [f"{KEYS.status(p.service_name).key}.state" for p in stack.processes]


def test_the_3d_panel_shows_the_arm_its_model_and_the_task() -> None:
    topics = set(_layout()["configById"]["3D!arm"]["topics"])
    assert {KEYS.arm_transforms.key, KEYS.arm_model.key, KEYS.scene.key, KEYS.viz_plan.key} <= topics


@pytest.mark.parametrize(
    ("path", "numeric", "why"),
    [
        ("psm/planner/status.time_to_go", True, "no field 'time_to_go'"),
        ("psm/planner/status.time_to_go_s", True, "an array"),
        ("psm/arm/state.ee_position", True, "does not end on a number"),
        ("psm/arm/state.ee_position[0].x", True, "not repeated"),
        ("psm/arm/nope.q[0]", True, "not a key"),
        ("psm/planner/status.goal.w", True, "no field 'w'"),
    ],
)
def test_the_checker_catches_bad_paths(path: str, numeric: bool, why: str) -> None:
    with pytest.raises(AssertionError, match=re.escape(why)):
        check_path(path, numeric)

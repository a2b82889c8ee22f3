"""The face boxes as Foxglove ImageAnnotations: what the Image panel draws on the camera's frames."""

from __future__ import annotations

import numpy as np

from services.bus.messages import Keys, decode, encode, stamp_ns_of
from services.goal_tracker.selection import Detection
from services.goal_tracker.service import OTHER_RGBA, TARGET_RGBA, annotations_message
from services.goal_tracker.tracker import TrackOutput, TrackState

NAN3 = np.full(3, np.nan)


def _out(detections: list[Detection], target: int, stamp_ns: int) -> TrackOutput:
    return TrackOutput(stamp_ns, detections, target, "full", next(iter(TrackState)), NAN3, NAN3,
                       np.full((3, 3), np.nan), False, "no face")


def test_each_box_is_a_closed_outline_with_its_confidence_at_the_frames_stamp() -> None:
    out = _out([Detection(10.0, 20.0, 30.0, 40.0, 0.25), Detection(100.0, 50.0, 60.0, 70.0, 0.9)],
               target=1, stamp_ns=12_345_678_901)
    msg = annotations_message(out)
    payload, encoding = encode(msg)
    assert encoding == Keys().camera_annotations("cam0").encoding
    assert stamp_ns_of(payload, encoding) == 12_345_678_901  # the recording's publish time
    back = decode(payload, encoding)
    assert len(back.points) == 2 and len(back.texts) == 2
    first, target = back.points
    assert [(p.x, p.y) for p in first.points] == [(10, 20), (40, 20), (40, 60), (10, 60)]
    assert first.type == first.LINE_LOOP and first.thickness > 0
    for ann in (*back.points, *back.texts):
        assert ann.timestamp.seconds == 12 and ann.timestamp.nanos == 345_678_901
    rgba = lambda c: (c.r, c.g, c.b, c.a)  # noqa: E731
    assert rgba(target.outline_color) == TARGET_RGBA and rgba(first.outline_color) == OTHER_RGBA
    assert back.texts[0].text == "0.25" and back.texts[1].text == "target 0.90"
    assert (back.texts[1].position.x, back.texts[1].position.y) == (100.0, 46.0)


def test_a_frame_without_faces_clears_the_boxes() -> None:
    msg = annotations_message(_out([], target=-1, stamp_ns=0))
    payload, encoding = encode(msg)
    back = decode(payload, encoding)
    assert not back.points and not back.texts
    assert stamp_ns_of(payload, encoding) == 0  # sim time 0 is a stamp

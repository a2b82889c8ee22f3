"""Detectors and the reduced-resolution + ROI pipeline."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from psm.errors import ParameterError
from services.goal_tracker.detectors import (
    DetectionPipeline,
    HaarDetector,
    PipelineParams,
    YuNetDetector,
    make_detector,
)
from services.goal_tracker.selection import Detection, iou
from services.goal_tracker.synthetic import SyntheticCamera


@pytest.fixture(scope="module")
def cam() -> SyntheticCamera:
    return SyntheticCamera()


def test_pipeline_full_then_roi_then_full_again(cam: SyntheticCamera) -> None:
    pipe = DetectionPipeline(HaarDetector(), PipelineParams(full_every=3))
    modes = []
    for k in range(7):
        frame = cam.render(k / 30)
        truth = cam.truth(k / 30)[0].box
        hint = Detection(*truth) if k else None
        res = pipe.process(frame, hint)
        modes.append(res.mode)
        assert len(res.detections) == 1
        assert iou(res.detections[0].box, truth) > 0.8
        assert 0.0 <= res.detections[0].confidence <= 1.0
    assert modes == ["full", "roi", "roi", "full", "roi", "roi", "full"]


def test_roi_miss_falls_back_to_full_detection(cam: SyntheticCamera) -> None:
    pipe = DetectionPipeline(HaarDetector())
    frame = cam.render(0.0)
    pipe.process(frame, None)
    wrong = Detection(20, 20, 60, 60)  # prediction far from the face
    res = pipe.process(frame, wrong)
    assert res.mode == "full"
    assert iou(res.detections[0].box, cam.truth(0.0)[0].box) > 0.8


def test_yunet_without_model_is_one_clear_error(tmp_path) -> None:
    missing = tmp_path / "face_detection_yunet.onnx"
    with pytest.raises(FileNotFoundError, match="YuNet model file not found"):
        YuNetDetector(str(missing))
    with pytest.raises(FileNotFoundError):
        make_detector("yunet", "")


def test_bad_detector_settings(tmp_path) -> None:
    with pytest.raises(ParameterError):
        make_detector("dnn")
    with pytest.raises(FileNotFoundError, match="Haar cascade file not found"):
        HaarDetector(str(tmp_path / "nope.xml"))
    bad = tmp_path / "bad.xml"
    bad.write_text("<opencv_storage></opencv_storage>")
    with pytest.raises(ParameterError, match="could not be loaded"):
        HaarDetector(str(bad))
    with pytest.raises(ValidationError, match="roi_size_range"):
        PipelineParams(roi_size_range=(1.2, 1.5))


def test_roi_measurement_does_not_follow_the_predicted_size(cam: SyntheticCamera) -> None:
    # The ROI window and its face-size range come from the hint's width snapped to a geometric
    # grid: hints a few percent apart in size (same centre) measure the same box, so a lagging
    # prediction cannot drag the measured size.
    detector = HaarDetector()
    frame = cam.render(0.0)
    x, y, w, h = cam.truth(0.0)[0].box
    step = PipelineParams().roi_size_step
    ref = step ** round(np.log(w) / np.log(step))
    boxes = [  # a fresh pipeline each: the same ROI grid offset
        DetectionPipeline(detector).roi(frame, Detection(x + (w - s) / 2, y + (h - s) / 2, s, s))
        for s in (ref / step**0.4, ref, ref * step**0.4)
    ]
    assert all(b is not None for b in boxes)
    assert len({tuple(b.box) for b in boxes}) == 1
    assert iou(boxes[0].box, cam.truth(0.0)[0].box) > 0.8

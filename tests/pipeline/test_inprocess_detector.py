"""The in-process driver detects as the detector service does: with `detector.input_size` set, the packaged model
resized to that letterbox (were it to run the model at its own 640x480 whatever was set, in-process figures for
a smaller letterbox would be 640x480's)."""

from __future__ import annotations

from pathlib import Path

import pytest

from semmap.algorithms.detector import create_detector
from semmap.core.config import load_config
from semmap.datasets import open_dataset
from semmap.runtime.models.detector_choice import load_detector_model, resolve_setup
from semmap.runtime.pipeline.inprocess import detect_recording
from semmap.runtime.pipeline.stages import frame_message


@pytest.mark.needs_data
@pytest.mark.needs_model
def test_inprocess_detections_use_the_letterbox_that_is_set(tmp_path: Path, data_root: Path) -> None:
    data = str(data_root / "7scenes-redkitchen")
    small = load_config(None, ["detector.input_size=416x320"])
    full = load_config(None, [])
    rec_small = detect_recording(data, 1, small, tmp_path, verbose=False)
    rec_full = detect_recording(data, 1, full, tmp_path, verbose=False)
    # what the detector service builds for the same settings (lockstep), on the same frame
    setup = resolve_setup("auto", 0, "416x320", realtime=False)
    service = create_detector("onnx", small.detector, load_detector_model(setup))
    frame = frame_message("robot1", open_dataset(data)[0])
    expected = [(b.class_name, round(b.x1, 3), round(b.y1, 3)) for b in service.detect_frame(frame)]
    got = [(d.class_name, round(d.box[0], 3), round(d.box[1], 3)) for d in rec_small.detections[0].detections]
    assert got == expected and got  # (the depth gate keeps every box of this frame)
    full_boxes = [(d.class_name, round(d.box[0], 3)) for d in rec_full.detections[0].detections]
    assert full_boxes != [(c, x) for c, x, _ in got]  # 640x480 sees it otherwise
    assert len(list(tmp_path.glob("detections-*.msgpack"))) == 2  # cached apart

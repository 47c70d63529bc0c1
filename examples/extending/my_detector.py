"""A detector back end (docs/EXTENDING.md): boxes around saturated red regions, reported as COCO's `stop sign`.

    python examples/extending/my_detector.py        # registers it, builds it by name, detects on a test frame

A back end is a factory `create(section, model) -> object with detect_frame(frame)`, registered under a name;
`--set detector.kind=red-blobs` then selects it. It needs no model file (`needs_model=False`).
"""

from __future__ import annotations

import sys

import cv2
import numpy as np

from semmap.algorithms.detector import create_detector, register, resolve_kind
from semmap.algorithms.detector.onnx_detector import DetectedBox
from semmap.core.config import DetectorConfig, load_config
from semmap.core.messages import Frame, Intrinsics

NAME = "red-blobs"
CLASS_NAME, CLASS_ID = "stop sign", 11  # the COCO name and index semmap's other back ends use


class RedBlobDetector:
    """Each 8-connected region where red exceeds green and blue by `MARGIN` is one box."""

    MARGIN = 80  # of 255
    MIN_PIXELS = 200
    SCORE = 0.9

    def __init__(self, section: DetectorConfig, model: object = None) -> None:
        self.allow, self.deny = set(section.classes), set(section.exclude)  # honour the allow and deny lists

    def detect_frame(self, frame: Frame) -> list[DetectedBox]:
        rgb = frame.rgb().astype(np.int16)  # HxWx3, RGB order, decoded once per frame
        red = (rgb[..., 0] - np.maximum(rgb[..., 1], rgb[..., 2]) > self.MARGIN).astype(np.uint8)
        count, _, stats, _ = cv2.connectedComponentsWithStats(red, connectivity=8)
        boxes = []
        for x, y, w, h, area in stats[1:count]:  # (row 0 is the background)
            if area >= self.MIN_PIXELS:
                boxes.append(
                    DetectedBox(float(x), float(y), float(x + w), float(y + h), CLASS_ID, CLASS_NAME, self.SCORE)
                )
        if self.allow:
            boxes = [b for b in boxes if b.class_name in self.allow]
        return [b for b in boxes if b.class_name not in self.deny]


register(NAME, RedBlobDetector, "boxes of saturated red regions, as `stop sign` (examples/extending)")


def main() -> int:
    section = load_config(None, [f"detector.kind={NAME}"]).detector  # validated like `semmap run --set ...`
    detector = create_detector(resolve_kind(section.kind, synthetic=False), section)
    rgb = np.full((120, 160, 3), 200, np.uint8)
    rgb[40:80, 60:100] = (230, 20, 20)  # a red square, 40 x 40 px
    depth = np.full((120, 160), 1500, np.uint16)  # 1.5 m in millimetres
    frame = Frame.from_arrays("robot1", 0, 0.0, rgb, depth, 0.001, Intrinsics(100.0, 100.0, 80.0, 60.0, 160, 120))
    boxes = detector.detect_frame(frame)
    print(boxes)
    assert len(boxes) == 1 and boxes[0].class_name == CLASS_NAME
    assert abs(boxes[0].x1 - 60) <= 2 and abs(boxes[0].x2 - 100) <= 2  # (JPEG blurs the edges a little)
    return 0


if __name__ == "__main__":
    sys.exit(main())

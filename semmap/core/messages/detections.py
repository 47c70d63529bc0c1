"""The detector's answer per frame: `Detections` (key `detections`), each `Detection` with its `DepthPatch`."""

from __future__ import annotations

from typing import Annotated

import msgspec
import numpy as np

from .base import (
    Box,
    Finite,
    Message,
    NonNegativeInt,
    Part,
    RobotName,
    Timings,
    array_map,
    decoding,
    expect_array,
    settle_box,
)
from .frames import Intrinsics


class DepthPatch(Part):
    """The depth pixels under a box, subsampled by `stride`, so the associator can back-project them."""

    x0: int
    y0: int
    stride: Annotated[int, msgspec.Meta(ge=1, le=64)]
    depth: array_map("uint16", 2, "the depth under the box, every stride-th pixel")

    def __post_init__(self) -> None:
        if decoding():
            expect_array(self.depth, "depth_patch", 2, "uint16")

    @classmethod
    def from_depth(cls, depth: np.ndarray, box: tuple[float, float, float, float], stride: int) -> DepthPatch:
        """The depth pixels under `box` (clipped to the image), every `stride`-th in x and y."""
        h, w = depth.shape
        x0 = int(np.clip(np.floor(box[0]), 0, w - 1))
        y0 = int(np.clip(np.floor(box[1]), 0, h - 1))
        x1 = int(np.clip(np.ceil(box[2]), x0 + 1, w))
        y1 = int(np.clip(np.ceil(box[3]), y0 + 1, h))
        return cls(x0, y0, stride, np.ascontiguousarray(depth[y0:y1:stride, x0:x1:stride]))


class Detection(Part):
    box: Box
    class_name: str = msgspec.field(name="class")
    score: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    depth_m: Finite  # median depth inside the box
    depth_patch: DepthPatch | None = None

    def __post_init__(self) -> None:
        settle_box(self)


class Detections(Message, tag="semmap.detections/1"):
    """The detector's answer for one frame. Every frame gets one, `skipped` ones too, so consumers never wait."""

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    intrinsics: Intrinsics
    depth_scale: Finite
    detections: list[Detection] = msgspec.field(default_factory=list)
    skipped: str = ""  # why this frame was not detected ("" = it was): "dropped", "stride", "bad_frame"
    detector: str = ""
    timing_ms: Timings = msgspec.field(default_factory=dict)
    frame_sent_at: Finite = 0.0
    sent_at: Finite = 0.0

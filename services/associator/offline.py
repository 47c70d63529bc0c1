"""Tracker + mapper over a dataset in one process, without the bus: for tests, benchmarks and evaluation.

It builds each frame's `Detection`s the way the detector service does (boxes, the median depth of the box's
central half with the paper's depth range, and the strided depth patch under the box), feeds the IOU tracker
and the landmark mapper, and records every stage's time. Detections come from a callable, so the oracle
(synthetic ground truth) and the ONNX detector (real images) plug in alike.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from semmap.datasets.base import CameraIntrinsics, FrameData, ObjectTruth
from semmap.messages import DepthPatch, Detection, Intrinsics
from services.detector.onnx_detector import DetectedBox, depth_gate
from services.tracker.iou_tracker import IouTracker, TrackerParams

from .mapper import LandmarkMapper, MapperParams, MapperStep

DetectFn = Callable[[FrameData], Sequence[DetectedBox]]


def to_intrinsics(k: CameraIntrinsics) -> Intrinsics:
    return Intrinsics(float(k.fx), float(k.fy), float(k.cx), float(k.cy), int(k.width), int(k.height))


def make_detections(
    frame: FrameData,
    boxes: Iterable[DetectedBox],
    stride: int = 2,
    depth_min_m: float = 0.2,
    depth_max_m: float = 25.0,
) -> list[Detection]:
    """Detections with depth and depth patch; boxes without valid depth in range are dropped."""
    out = []
    for b, d in depth_gate(boxes, frame.depth, frame.depth_scale, depth_min_m, depth_max_m):
        box = (b.x1, b.y1, b.x2, b.y2)
        out.append(
            Detection(box, b.class_name, float(b.score), float(d), DepthPatch.from_depth(frame.depth, box, stride))
        )
    return out


@dataclass
class OfflineRun:
    """Everything an offline run produced."""

    tracker: IouTracker
    mapper: LandmarkMapper
    steps: list[MapperStep] = field(default_factory=list)
    tracker_ms: list[float] = field(default_factory=list)
    detections: int = 0
    frames: int = 0


def run_offline(
    frames: Iterable[FrameData],
    detect: DetectFn,
    poses: dict[int, np.ndarray],
    tracker_params: TrackerParams | None = None,
    mapper_params: MapperParams | None = None,
    stride: int = 2,
) -> OfflineRun:
    """Feed every frame (its index is the frame id) through detection, tracking and mapping."""
    run = OfflineRun(IouTracker(tracker_params), LandmarkMapper(mapper_params))
    lookup = poses.get
    for frame in frames:
        dets = make_detections(frame, detect(frame), stride)
        t0 = time.perf_counter()
        out = run.tracker.update(
            frame.index, frame.stamp, dets, to_intrinsics(frame.intrinsics), frame.depth_scale
        )
        run.tracker_ms.append((time.perf_counter() - t0) * 1e3)
        run.steps.append(
            run.mapper.process(frame.index, frame.stamp, out.candidates, out.ended, lookup, out.boxes)
        )
        run.detections += len(dets)
        run.frames += 1
    return run


@dataclass
class MapScore:
    """A map against ground-truth objects (synthetic scenes)."""

    recall: float  # static objects with exactly one or more landmark of their class nearby
    mapped: int
    static_objects: int
    duplicates: int  # extra same-class landmarks on an already mapped object
    false_landmarks: int  # landmarks on no object of their class (includes moving objects)
    on_moving: int  # unmatched landmarks of a moving object's class (a person: no static ones here)
    errors: dict[int, float]  # instance id -> centroid error of its landmark (metres)

    @property
    def median_error(self) -> float:
        return float(np.median(list(self.errors.values()))) if self.errors else float("inf")


def score_map(landmarks: Sequence, objects: Sequence[ObjectTruth], max_dist: float = 0.5) -> MapScore:
    """Match landmarks to static objects of the same class (each landmark to its nearest object within
    max(max_dist, object half-diagonal)); count duplicates, false landmarks and those of a moving class."""
    static = [o for o in objects if not o.moving]
    moving_classes = {o.class_name for o in objects if o.moving}
    assigned: dict[int, list[tuple[float, int]]] = {o.instance_id: [] for o in static}
    false_lms = on_moving = 0
    for lm in landmarks:
        c = np.asarray(lm.centroid)
        best, best_d = None, float("inf")
        for o in static:
            if o.class_name != lm.class_name:
                continue
            d = float(np.linalg.norm(c - np.asarray(o.centroid)))
            if d < best_d and d <= max(max_dist, 0.5 * float(np.linalg.norm(o.extent))):
                best, best_d = o, d
        if best is None:
            false_lms += 1
            on_moving += lm.class_name in moving_classes
            continue
        assigned[best.instance_id].append((best_d, lm.id))
    errors = {i: min(v)[0] for i, v in assigned.items() if v}
    duplicates = sum(max(0, len(v) - 1) for v in assigned.values())
    return MapScore(
        len(errors) / max(1, len(static)), len(errors), len(static), duplicates, false_lms, on_moving, errors
    )

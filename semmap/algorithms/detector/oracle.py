"""Oracle detector: ground-truth instance boxes turned into realistic, seeded, noisy detections.

Why: on synthetic scenes the mapping pipeline must be testable without a CNN, yet a perfect detector hides
the failure modes (missed objects, jittery boxes, spurious boxes, wrong labels) the back end has to survive.
Every random draw comes from a generator seeded by (seed, frame_index[, instance_id]), so a frame's
detections are the same whatever order frames are asked for and whatever order the instances are listed in.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from semmap.algorithms.detector.onnx_detector import DetectedBox
from semmap.datasets.base import InstanceBox

COCO_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
    "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
    "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
    "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard",
    "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip

_TRUE_SCORE = (0.5, 0.95)
_FALSE_SCORE = (0.4, 0.7)  # spurious boxes are usually the less confident ones
_STREAM_INSTANCE, _STREAM_FP = 0, 1  # separate random streams per frame


class OracleDetector:
    """Noisy detections from ground truth.

    miss_rate: chance that a visible instance is not detected.
    false_positive_rate: expected spurious boxes per frame (Poisson).
    confusion_rate: chance that a detected instance gets another class label.
    box_noise_px: std-dev of the Gaussian noise added to each box corner coordinate.
    min_visible_pixels: instances with fewer visible pixels are never detected (not counted as misses).
    class_names: label vocabulary; class_id is the index in it (-1 for a name outside it). Confusions and
    false positives draw their labels from `confusion_classes` if given, else from the vocabulary.
    """

    def __init__(
        self,
        seed: int,
        miss_rate: float = 0.05,
        false_positive_rate: float = 0.02,
        confusion_rate: float = 0.02,
        box_noise_px: float = 2.0,
        min_visible_pixels: int = 300,
        class_names: Sequence[str] = COCO_NAMES,
        confusion_classes: Sequence[str] | None = None,
    ) -> None:
        for name, rate in (("miss_rate", miss_rate), ("confusion_rate", confusion_rate)):
            if not 0.0 <= rate <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {rate}")
        if false_positive_rate < 0 or box_noise_px < 0:
            raise ValueError("false_positive_rate and box_noise_px must be >= 0")
        if int(seed) < 0:
            raise ValueError("seed must be >= 0")
        self.seed = int(seed)
        self.miss_rate = float(miss_rate)
        self.false_positive_rate = float(false_positive_rate)
        self.confusion_rate = float(confusion_rate)
        self.box_noise_px = float(box_noise_px)
        self.min_visible_pixels = int(min_visible_pixels)
        self.class_names = tuple(class_names)
        self._ids = {n: i for i, n in enumerate(self.class_names)}
        self.confusion_classes = tuple(confusion_classes) if confusion_classes else self.class_names
        if not self.confusion_classes:
            raise ValueError("need at least one class name")

    def _rng(self, frame_index: int, *stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, int(frame_index), *stream])

    def _box(self, rng: np.random.Generator, box: Sequence[float], width: int, height: int) -> np.ndarray:
        b = np.asarray(box, dtype=np.float64) + rng.normal(0.0, self.box_noise_px, 4)
        b[[0, 2]] = np.sort(b[[0, 2]]).clip(0, width)
        b[[1, 3]] = np.sort(b[[1, 3]]).clip(0, height)
        return b

    def _make(self, b: np.ndarray, name: str, score: float) -> DetectedBox:
        return DetectedBox(float(b[0]), float(b[1]), float(b[2]), float(b[3]), self._ids.get(name, -1), name, score)

    def detect(self, frame_index: int, instances: Sequence[InstanceBox], width: int, height: int) -> list[DetectedBox]:
        """Detections for one frame, best score first."""
        out: list[DetectedBox] = []
        for inst in instances:
            if inst.visible_pixels < self.min_visible_pixels:
                continue
            rng = self._rng(frame_index, _STREAM_INSTANCE, int(inst.instance_id))
            # Always draw every variate, in a fixed order, so one setting never shifts another's outcomes.
            missed = rng.random() < self.miss_rate
            confused = rng.random() < self.confusion_rate
            pick = int(rng.integers(1 << 30))
            score = float(rng.uniform(*_TRUE_SCORE))
            b = self._box(rng, inst.box, width, height)
            if missed or b[2] - b[0] < 1 or b[3] - b[1] < 1:
                continue
            name = inst.class_name
            others = [c for c in self.confusion_classes if c != inst.class_name]
            if confused and others:
                name = others[pick % len(others)]
            out.append(self._make(b, name, score))
        out.extend(self._false_positives(frame_index, width, height))
        out.sort(key=lambda d: -d.score)
        return out

    def _false_positives(self, frame_index: int, width: int, height: int) -> list[DetectedBox]:
        rng = self._rng(frame_index, _STREAM_FP)
        fps = []
        for _ in range(int(rng.poisson(self.false_positive_rate))):
            bw = rng.uniform(0.05, 0.35) * width
            bh = rng.uniform(0.05, 0.35) * height
            x1, y1 = rng.uniform(0, width - bw), rng.uniform(0, height - bh)
            name = self.confusion_classes[int(rng.integers(len(self.confusion_classes)))]
            score = float(rng.uniform(*_FALSE_SCORE))
            fps.append(self._make(np.array([x1, y1, x1 + bw, y1 + bh]), name, score))
        return fps

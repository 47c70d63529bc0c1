"""YOLO object detection on ONNX Runtime, plus the depth gate that turns 2-D boxes into usable observations.

Why ONNX Runtime: it runs the converted YOLOv5s (and any YOLOv8/11 export) on CPU, CUDA or TensorRT with one
code path, without torch. Two output layouts are understood, told apart by the output shape:
- YOLOv5: `[1, N, 5 + nc]` = cx, cy, w, h, objectness, class probabilities; score = objectness x class prob.
- YOLOv8/11: `[1, 4 + nc, N]` = cx, cy, w, h, class probabilities (no objectness).
Boxes are in model-input pixels; they are mapped back through the letterbox to original-image pixels.
"""

from __future__ import annotations

import ast
import json
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

LETTERBOX_GREY = 114
MAX_CANDIDATES = 30000  # boxes entering NMS, best first (YOLOv5's max_nms)
MAX_DETECTIONS = 300
_GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")


@dataclass(frozen=True)
class DetectedBox:
    """One detection in original-image pixels (x2, y2 exclusive-style corners, as floats)."""

    x1: float
    y1: float
    x2: float
    y2: float
    class_id: int
    class_name: str
    score: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# ----------------------------------------------------------------------------------------------------------
# Geometry


def letterbox(
    img: np.ndarray, new_hw: tuple[int, int], color: int = LETTERBOX_GREY
) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Resize keeping aspect and pad with grey to `new_hw`; returns (image, scale, (pad_x, pad_y))."""
    h, w = img.shape[:2]
    nh_t, nw_t = int(new_hw[0]), int(new_hw[1])
    r = min(nh_t / h, nw_t / w)
    nw, nh = round(w * r), round(h * r)
    if (nw, nh) != (w, h):
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_LINEAR)
    dw, dh = (nw_t - nw) / 2, (nh_t - nh) / 2
    top, bottom = round(dh - 0.1), round(dh + 0.1)
    left, right = round(dw - 0.1), round(dw + 0.1)
    if top or bottom or left or right:
        img = cv2.copyMakeBorder(img, top, bottom, left, right, cv2.BORDER_CONSTANT, value=(color,) * 3)
    return img, r, (left, top)


def unletterbox(boxes_xyxy: np.ndarray, scale: float, pad: tuple[int, int], image_hw: tuple[int, int]) -> np.ndarray:
    """Map xyxy boxes from letterboxed model-input pixels back to the original image, clipped to it."""
    out = np.asarray(boxes_xyxy, dtype=np.float64).copy()
    out[:, [0, 2]] = (out[:, [0, 2]] - pad[0]) / scale
    out[:, [1, 3]] = (out[:, [1, 3]] - pad[1]) / scale
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, image_hw[1])
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, image_hw[0])
    return out


def xywh_to_xyxy(xywh: np.ndarray) -> np.ndarray:
    half = xywh[:, 2:4] / 2
    return np.concatenate([xywh[:, 0:2] - half, xywh[:, 0:2] + half], axis=1)


def nms(
    boxes_xyxy: np.ndarray,
    scores: np.ndarray,
    iou_threshold: float = 0.45,
    class_ids: np.ndarray | None = None,
) -> np.ndarray:
    """Greedy NMS, vectorised per kept box; class-wise when class_ids is given. Kept indices, best first."""
    boxes = np.asarray(boxes_xyxy, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float64)
    if boxes.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    if class_ids is not None:
        # Shift each class to its own far-away region so boxes of different classes never overlap.
        span = float(boxes.max() - min(boxes.min(), 0.0)) + 1.0
        boxes = boxes + (np.asarray(class_ids, dtype=np.float64) * span)[:, None]
    areas = (boxes[:, 2] - boxes[:, 0]).clip(0) * (boxes[:, 3] - boxes[:, 1]).clip(0)
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    while order.size:
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        if rest.size == 0:
            break
        iw = (np.minimum(boxes[i, 2], boxes[rest, 2]) - np.maximum(boxes[i, 0], boxes[rest, 0])).clip(0)
        ih = (np.minimum(boxes[i, 3], boxes[rest, 3]) - np.maximum(boxes[i, 1], boxes[rest, 1])).clip(0)
        inter = iw * ih
        iou = inter / np.maximum(areas[i] + areas[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


# ----------------------------------------------------------------------------------------------------------
# Class names


def parse_names(text: str) -> list[str]:
    """Class names from a JSON list/dict or the ultralytics dict-string form "{0: 'person', 1: 'bicycle'}"."""
    try:
        value: Any = json.loads(text)
    except json.JSONDecodeError:
        try:
            value = ast.literal_eval(text)  # literals only: safe on untrusted metadata
        except (ValueError, SyntaxError) as exc:
            raise ValueError(f"cannot parse class names: {text[:60]!r}") from exc
    if isinstance(value, dict):
        try:
            items = sorted((int(k), v) for k, v in value.items())
        except (TypeError, ValueError) as exc:
            raise ValueError("class-name dict keys must be integers") from exc
        if [k for k, _ in items] != list(range(len(items))):
            raise ValueError("class-name dict keys must be 0..n-1")
        value = [v for _, v in items]
    if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
        raise ValueError("class names must be a list of strings")
    return list(value)


def load_names_file(path: Path | str) -> list[str]:
    """Names from a .json file (list or dict) or a text file with one name per line."""
    p = Path(path)
    text = p.read_text(encoding="utf-8")
    if p.suffix.lower() == ".json":
        return parse_names(text)
    return [line.strip() for line in text.splitlines() if line.strip()]


# ----------------------------------------------------------------------------------------------------------
# Detector


def choose_providers(available: Iterable[str]) -> list[str]:
    """TensorRT, then CUDA where present; CPU always last as the fallback."""
    avail = list(available)
    return [p for p in _GPU_PROVIDERS if p in avail] + ["CPUExecutionProvider"]


class OnnxDetector:
    """YOLO detector over an ONNX model; `detect(rgb)` returns boxes in original-image pixels."""

    def __init__(
        self,
        model_path: Path | str | bytes,
        conf: float = 0.4,
        iou: float = 0.45,
        threads: int = 2,
        allow: set[str] | None = None,
        deny: set[str] | None = None,
        providers: str | Sequence[Any] = "auto",
        names: Sequence[str] | Path | str | None = None,
        imgsz: int = 640,
        spin: bool = False,
        class_confidence: dict[str, float] | None = None,
    ) -> None:
        """model_path: an ONNX file, or a serialized model (bytes, e.g. one resized in memory).

        spin: let ORT's worker threads busy-wait between ops. Slightly faster on an idle machine, but
        with other services on the same cores it steals their CPU and made detection ~1.5x slower here; off by default.
        """
        import onnxruntime as ort  # late: the oracle and CLI help must not pay for it

        model_bytes = model_path if isinstance(model_path, bytes) else None
        self.model_path = Path("<in memory>") if model_bytes is not None else Path(model_path)  # type: ignore[arg-type]
        if model_bytes is None and not self.model_path.is_file():
            raise FileNotFoundError(f"ONNX model not found: {self.model_path}")
        self.iou = float(iou)
        self.imgsz = int(imgsz)
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
        so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        if providers == "auto":
            providers = [
                ("TensorrtExecutionProvider", self._trt_options()) if p == "TensorrtExecutionProvider" else p
                for p in choose_providers(ort.get_available_providers())
            ]
        self.session = ort.InferenceSession(
            model_bytes if model_bytes is not None else str(self.model_path), so, providers=list(providers)
        )
        self.providers: list[str] = self.session.get_providers()

        inp = self.session.get_inputs()[0]
        self._input_name = inp.name
        self._input_dtype = np.float16 if inp.type == "tensor(float16)" else np.float32
        shape = list(inp.shape)
        if len(shape) != 4 or shape[1] not in (3, "3"):
            raise ValueError(f"{self.model_path}: expected an image input [1,3,H,W], got {shape}")
        h, w = shape[2], shape[3]
        self.input_hw: tuple[int, int] | None = (h, w) if isinstance(h, int) and isinstance(w, int) else None

        given = self._given_names(names)
        self.layout, nc = self._layout_from_shape(list(self.session.get_outputs()[0].shape), given)
        if given is not None and len(given) != nc:
            raise ValueError(f"{self.model_path}: model has {nc} classes but {len(given)} names were given")
        self.names: list[str] = given if given is not None else [f"class{i}" for i in range(nc)]
        self.num_classes = nc
        self._class_ok = self._class_mask(allow, deny)
        # classes given a threshold that this model cannot detect (a typo, or a model of other classes): the
        # threshold is moot, the service says so at start (not an error: the default names `person`)
        self._class_confidence = dict(class_confidence or {})
        self.unknown_confidence_classes = sorted(set(self._class_confidence) - set(self.names))
        self.conf = conf  # (sets the per-class thresholds)

    @property
    def conf(self) -> float:
        """The common confidence threshold."""
        return self._conf

    @conf.setter
    def conf(self, value: float) -> None:
        """Why a setter: the per-class thresholds are derived from `conf` once, not per detection, so a change of
        `conf` after construction must re-derive them (`semmap models doctor` lowers it to see the ties at the
        threshold; when it did not reach the thresholds, every tie read as a disagreement). A class given its own
        threshold keeps it."""
        self._conf = float(value)
        # per class, the score a detection must exceed: `conf`, or that class's own threshold
        self._threshold = np.array([float(self._class_confidence.get(n, self._conf)) for n in self.names])
        self._prefilter = float(self._threshold.min())

    # -- set-up helpers ----------------------------------------------------------------------------------

    def _trt_options(self) -> dict[str, Any]:
        """Cache TensorRT engines beside the model: building one takes minutes, loading it a second."""
        return {"trt_engine_cache_enable": True, "trt_engine_cache_path": str(self.model_path.parent / "trt_cache")}

    def _given_names(self, names: Sequence[str] | Path | str | None) -> list[str] | None:
        """Explicit names (list or file) win over the model's `names` metadata; None if neither exists."""
        if isinstance(names, str | Path):
            return load_names_file(names)
        if names is not None:
            return list(names)
        meta = self.session.get_modelmeta().custom_metadata_map
        return parse_names(meta["names"]) if "names" in meta else None

    def _layout_from_shape(self, shape: list[Any], names: list[str] | None) -> tuple[str, int]:
        """'yolov5' for [1, N, 5+nc] (channels last), 'yolov8' for [1, 4+nc, N] (channels first).

        With known names the channel count decides; without, the channel axis is the smaller fixed one.
        """
        expected = "expected YOLOv5 [1, N, 5+nc] or YOLOv8 [1, 4+nc, N]"
        if len(shape) != 3:
            raise ValueError(f"{self.model_path}: unsupported output shape {shape}; {expected}")
        d1, d2 = shape[1], shape[2]
        if names is not None:
            if d2 == len(names) + 5:
                return "yolov5", d2 - 5
            if d1 == len(names) + 4:
                return "yolov8", d1 - 4
        if isinstance(d2, int) and (not isinstance(d1, int) or d2 < d1) and d2 >= 6:
            return "yolov5", d2 - 5
        if isinstance(d1, int) and (not isinstance(d2, int) or d1 < d2) and d1 >= 5:
            return "yolov8", d1 - 4
        raise ValueError(f"{self.model_path}: unsupported output layout {shape}; {expected}")

    def _class_mask(self, allow: set[str] | None, deny: set[str] | None) -> np.ndarray | None:
        known = set(self.names)
        for label, group in (("allow", allow), ("deny", deny)):
            unknown = sorted(set(group or ()) - known)
            if unknown:
                raise ValueError(f"{label} list has classes this model does not know: {unknown}")
        if allow is None and not deny:
            return None
        return np.array([(allow is None or n in allow) and n not in (deny or ()) for n in self.names])

    # -- inference ---------------------------------------------------------------------------------------

    def _target_hw(self, h: int, w: int) -> tuple[int, int]:
        if self.input_hw is not None:
            return self.input_hw
        r = self.imgsz / max(h, w)  # dynamic model: smallest rectangle of multiples of 32 (YOLOv5 "rect")
        return (int(np.ceil(h * r / 32) * 32), int(np.ceil(w * r / 32) * 32))

    def raw(self, rgb: np.ndarray) -> tuple[np.ndarray, float, tuple[int, int]]:
        """Run the network on one RGB image; returns (output[0], letterbox scale, letterbox pad)."""
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"expected an HxWx3 uint8 RGB image, got {rgb.shape} {rgb.dtype}")
        img, scale, pad = letterbox(rgb, self._target_hw(*rgb.shape[:2]))
        blob = cv2.dnn.blobFromImage(img, scalefactor=1.0 / 255.0)  # HWC uint8 -> NCHW float32, no swap
        if self._input_dtype is not np.float32:
            blob = blob.astype(self._input_dtype)
        out = self.session.run(None, {self._input_name: blob})[0]
        return np.asarray(out[0], dtype=np.float32), scale, pad

    def decode(
        self, out: np.ndarray, scale: float, pad: tuple[int, int], image_hw: tuple[int, int]
    ) -> list[DetectedBox]:
        """Scores, confidence threshold, class filter, class-wise NMS and letterbox undo on one raw output."""
        if self.layout == "yolov8":
            out = out.T  # [4+nc, N] -> [N, 4+nc]
            cls = out[:, 4:]
        else:
            out = out[out[:, 4] > self._prefilter]  # score <= objectness: cheap prefilter
            cls = out[:, 5:] * out[:, 4:5]
        if cls.shape[1] != self.num_classes:
            raise ValueError(f"model output has {cls.shape[1]} classes, expected {self.num_classes}")
        class_ids = cls.argmax(axis=1)
        scores = cls[np.arange(cls.shape[0]), class_ids]
        keep = scores > self._threshold[class_ids]
        if self._class_ok is not None:
            keep &= self._class_ok[class_ids]
        boxes, scores, class_ids = out[keep, :4], scores[keep], class_ids[keep]
        if scores.size > MAX_CANDIDATES:
            top = np.argsort(-scores, kind="stable")[:MAX_CANDIDATES]
            boxes, scores, class_ids = boxes[top], scores[top], class_ids[top]
        xyxy = xywh_to_xyxy(boxes.astype(np.float64))
        idx = nms(xyxy, scores, self.iou, class_ids)[:MAX_DETECTIONS]
        xyxy = unletterbox(xyxy[idx], scale, pad, image_hw)
        return [
            DetectedBox(float(b[0]), float(b[1]), float(b[2]), float(b[3]), int(c), self.names[int(c)], float(s))
            for b, c, s in zip(xyxy, class_ids[idx], scores[idx], strict=True)
            if b[2] > b[0] and b[3] > b[1]  # a box wholly in the letterbox padding clips to nothing
        ]

    def detect(self, rgb: np.ndarray) -> list[DetectedBox]:
        """Detect objects in an HxWx3 uint8 RGB image; boxes best first, in original-image pixels."""
        out, scale, pad = self.raw(rgb)
        return self.decode(out, scale, pad, rgb.shape[:2])


def depth_gate(
    boxes: Iterable[DetectedBox],
    depth_u16: np.ndarray,
    depth_scale: float,
    min_m: float = 0.2,
    max_m: float = 25.0,
) -> list[tuple[DetectedBox, float]]:
    """Keep boxes whose median valid depth (central half of the box) lies in [min_m, max_m] metres.

    The central half (half the width and half the height, centred) avoids the background that a box's
    corners always contain. depth_u16 must be registered to the image the boxes refer to; 0 means invalid;
    metres = raw * depth_scale.
    """
    h, w = depth_u16.shape[:2]
    kept: list[tuple[DetectedBox, float]] = []
    for b in boxes:
        qw, qh = (b.x2 - b.x1) / 4.0, (b.y2 - b.y1) / 4.0
        x1 = int(np.clip(np.floor(b.x1 + qw), 0, w - 1))
        y1 = int(np.clip(np.floor(b.y1 + qh), 0, h - 1))
        x2 = int(np.clip(np.ceil(b.x2 - qw), x1 + 1, w))
        y2 = int(np.clip(np.ceil(b.y2 - qh), y1 + 1, h))
        patch = depth_u16[y1:y2, x1:x2]
        valid = patch[patch > 0]
        if valid.size == 0:
            continue
        d = float(np.median(valid)) * float(depth_scale)
        if min_m <= d <= max_m:
            kept.append((b, d))
    return kept

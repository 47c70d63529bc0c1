"""Detector back ends, picked by name (`detector.kind`) the way datasets are (semmap/datasets/__init__.py).

`create_detector(kind, section, model)` builds a back end from its section; each one answers
`detect_frame(frame) -> list[DetectedBox]` for a `Frame` message. `resolve_kind` is the one place `auto` is
decided: the oracle where frames carry ground-truth instances (the synthetic scene), ONNX otherwise. New back ends
join via `register`; their modules are imported only when one is built (ONNX Runtime and OpenCV are heavy).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from semmap.core.config import ConfigError, DetectorConfig

if TYPE_CHECKING:
    from semmap.algorithms.detector.onnx_detector import DetectedBox
    from semmap.core.messages import Frame

__all__ = ["AUTO", "FrameDetector", "available", "create_detector", "needs_model", "register", "resolve_kind"]


class FrameDetector(Protocol):
    def detect_frame(self, frame: Frame) -> list[DetectedBox]: ...


@dataclass(frozen=True)
class _Backend:
    name: str
    description: str
    create: Callable[[DetectorConfig, Path | bytes | None], FrameDetector]
    needs_model: bool  # reads `detector.model` (or the packaged model of `detector.precision`)


_REGISTRY: dict[str, _Backend] = {}
AUTO = "auto"


def register(
    name: str,
    create: Callable[[DetectorConfig, Path | bytes | None], FrameDetector],
    description: str,
    needs_model: bool = False,
) -> None:
    """Add a back end: `create(section, model_path)` builds it (model_path None unless `needs_model`)."""
    _REGISTRY[name] = _Backend(name, description, create, needs_model)


def available() -> dict[str, str]:
    """{name: description} of every registered back end."""
    return {b.name: b.description for b in _REGISTRY.values()}


def resolve_kind(kind: str, synthetic: bool) -> str:
    """The back end `detector.kind` names; `auto`: the oracle on synthetic data, ONNX otherwise. A name nobody
    registered is a ConfigError that lists the known ones."""
    if kind == AUTO:
        return "oracle" if synthetic else "onnx"
    if kind not in _REGISTRY:
        known = ", ".join([AUTO, *_REGISTRY])
        raise ConfigError(f"detector.kind: expected one of {known} (registered detector back ends), got {kind!r}")
    return kind


def needs_model(kind: str) -> bool:
    """Whether back end `kind` (resolved) reads a model file."""
    return _REGISTRY[kind].needs_model


def create_detector(kind: str, section: DetectorConfig, model: Path | bytes | None = None) -> FrameDetector:
    """Back end `kind` (as `resolve_kind` gives it) built from the `detector` section."""
    backend = _REGISTRY[resolve_kind(kind, synthetic=False)]
    return backend.create(section, model if backend.needs_model else None)


def known_classes(kind: str, section: DetectorConfig, model: Path | None) -> list[str] | None:
    """The class names the back end `kind` can report (None where they cannot be told without running it): the
    oracle's vocabulary, a names file, or the ONNX model's `names` metadata."""
    if kind == "oracle":
        from .oracle import COCO_NAMES

        return list(COCO_NAMES)
    if kind != "onnx":
        return None
    from .onnx_detector import load_names_file, parse_names

    if section.names:
        return load_names_file(section.names)
    if model is None or not Path(model).is_file():
        return None
    import onnxruntime as ort

    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    return parse_names(meta["names"]) if "names" in meta else None


def check_classes(kind: str, section: DetectorConfig, model: Path | None) -> None:
    """`detector.classes` and `detector.exclude` name classes the detector knows (a ConfigError naming the key and
    listing the known ones otherwise): a class it cannot report would give an empty map, silently."""
    if not section.classes and not section.exclude:
        return
    known = known_classes(kind, section, model)
    if known is None:
        return
    for key, names in (("detector.classes", section.classes), ("detector.exclude", section.exclude)):
        unknown = [n for n in names if n not in set(known)]
        if unknown:
            source = f"the model {model}" if kind == "onnx" and not section.names else (
                f"the names file {section.names}" if kind == "onnx" else f"the {kind} detector")
            raise ConfigError(f"{key}: {', '.join(repr(n) for n in unknown)} not among the classes {source} "
                              f"knows: {', '.join(known)}")


class _OracleFrames:
    """The oracle on a frame's ground-truth instances, with the section's allow and deny lists."""

    def __init__(self, section: DetectorConfig, model: Path | bytes | None) -> None:
        from .oracle import OracleDetector

        self.oracle = OracleDetector(
            seed=section.oracle_seed,
            miss_rate=section.oracle_miss_rate,
            false_positive_rate=section.oracle_false_positive_rate,
            confusion_rate=section.oracle_confusion_rate,
        )
        self.allow, self.deny = set(section.classes), set(section.exclude)

    def detect_frame(self, frame: Frame) -> list[DetectedBox]:
        boxes = self.oracle.detect(frame.frame_id, frame.instances, frame.intrinsics.width, frame.intrinsics.height)
        if self.allow:
            boxes = [b for b in boxes if b.class_name in self.allow]
        return [b for b in boxes if b.class_name not in self.deny]


class _OnnxFrames:
    """A YOLO ONNX model on the frame's colour image."""

    def __init__(self, section: DetectorConfig, model: Path | bytes | None) -> None:
        from .onnx_detector import OnnxDetector

        if model is None:
            raise ConfigError("detector.model: the onnx back end needs a model file")
        self.onnx = OnnxDetector(
            model,
            conf=section.confidence,
            iou=section.iou,
            threads=section.threads or 2,
            allow=set(section.classes) or None,
            deny=set(section.exclude) or None,
            names=section.names or None,
            class_confidence=dict(section.class_confidence) or None,
        )
        self.providers = self.onnx.providers
        self.unknown_confidence_classes = self.onnx.unknown_confidence_classes

    def detect_frame(self, frame: Frame) -> list[DetectedBox]:
        return self.onnx.detect(frame.rgb())


register("oracle", _OracleFrames, "noisy detections from the frames' ground-truth instances (synthetic data)")
register("onnx", _OnnxFrames, "a YOLO model in ONNX (detector.model, or the packaged YOLOv5s)", needs_model=True)

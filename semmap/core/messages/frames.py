"""Sensor data: `Frame` (RGB-D, key `frames`), its `Intrinsics` and ground-truth boxes, and the image codec seam.

Why an image codec seam: a frame carries its colour image as JPEG (and may carry its depth as 16-bit PNG), yet
core must not depend on OpenCV: the light client, the bus and every tool that only routes or stores frames never
touch pixels. `Frame.rgb()`, `depth()`, `from_arrays()` and `depth_as_png()` ask `image_codec()`, which is the
codec installed with `use_image_codec()` or, the first time pixels are needed, the default one that
`DEFAULT_IMAGE_CODEC` names (`semmap.imaging.opencv`, in the layer just above core). Looking the default up by
name keeps `frame.rgb()` working in every process without each one remembering to install a codec, and keeps
OpenCV out of every process that never decodes an image.
"""

from __future__ import annotations

import importlib
from typing import Annotated, Any, ClassVar, Protocol

import msgspec
import numpy as np

from .base import (
    Box,
    Finite,
    Message,
    MessageError,
    NonNegativeInt,
    Part,
    PngImage,
    Pose,
    Positive,
    RobotName,
    as_matrix,
    decode_array,
    decoding,
    settle_box,
    validate_pose,
)

DEFAULT_IMAGE_CODEC = "semmap.imaging.opencv"
ImageSide = Annotated[int, msgspec.Meta(gt=0, le=16384, description="pixels")]
DepthScale = Annotated[float, msgspec.Meta(gt=0.0, lt=1.0, description="metres per depth unit")]


class ImageCodec(Protocol):
    """JPEG for colour, 16-bit PNG for depth; `None` from a decoder or encoder means it failed."""

    def encode_jpeg(self, rgb: np.ndarray, quality: int) -> bytes | None: ...

    def decode_jpeg(self, data: bytes) -> np.ndarray | None: ...  # HxWx3 uint8 RGB

    def encode_png16(self, image: np.ndarray) -> bytes | None: ...

    def decode_png16(self, data: bytes) -> np.ndarray | None: ...  # HxW uint16


_codec: ImageCodec | None = None


def use_image_codec(codec: ImageCodec | None) -> None:
    """Install the codec frames use (None: back to the default, found again on first use)."""
    global _codec
    _codec = codec


def image_codec() -> ImageCodec:
    """The installed codec, else the default one (module docstring); MessageError when it cannot load."""
    global _codec
    if _codec is None:
        try:
            _codec = importlib.import_module(DEFAULT_IMAGE_CODEC).OpenCVImageCodec()
        except ImportError as exc:
            raise MessageError(f"frame images need an image codec: {exc} (install opencv-python-headless, "
                               "or call semmap.core.messages.use_image_codec)") from None
    return _codec


class Intrinsics(Part):
    fx: Positive
    fy: Positive
    cx: Finite
    cy: Finite
    width: ImageSide
    height: ImageSide

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


class GroundTruthInstance(Part):
    """A ground-truth object box (synthetic data): lets the oracle detector run anywhere in the pipeline."""

    instance_id: int
    class_name: str = msgspec.field(name="class")
    box: Box
    visible_pixels: int
    moving: bool

    def __post_init__(self) -> None:
        settle_box(self)


DEPTH_SCHEMA = {
    "description": "depth registered to the colour image, 0 = invalid: a uint16 HxW array map, or a 16-bit PNG",
    "anyOf": [
        {"type": "object", "properties": {"dtype": {"const": "uint16"},
                                          "shape": {"type": "array", "items": {"type": "integer"}, "minItems": 2,
                                                    "maxItems": 2},
                                          "data": {"type": "string", "contentEncoding": "base64"}},
         "required": ["dtype", "shape", "data"]},
        {"type": "object", "properties": {"png": {"type": "string", "contentEncoding": "base64"}},
         "required": ["png"]},
    ],
}
# an ndarray (uint16 HxW) or PngImage; Frame.__post_init__ decodes either wire form (msgspec has no union of them)
DepthField = Annotated[Any, msgspec.Meta(extra_json_schema=DEPTH_SCHEMA)]


# 65535, the saturated value of 16-bit depth, is 7-Scenes' "no reading" marker: a depth PNG's 65535 reads as 0
# (invalid), so a dataset's depth files can travel as they are stored (semmap.datasets.images.read_depth_file)
DEPTH_NO_READING = 65535


class Frame(Message, tag="semmap.frame/1"):
    """One RGB-D frame. Images stay encoded until a consumer asks (`rgb()`, `depth()`), then are cached."""

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    rgb_jpeg: bytes
    depth_raw: DepthField = msgspec.field(name="depth")  # uint16 HxW array, or 16-bit PNG bytes
    depth_scale: DepthScale
    intrinsics: Intrinsics
    gt_pose: Pose | None = None
    instances: list[GroundTruthInstance] = msgspec.field(default_factory=list)
    sent_at: Finite = 0.0

    _rgb: ClassVar[np.ndarray | None] = None  # the decoded image, cached per instance (class default: none yet)

    def __post_init__(self) -> None:
        if type(self.depth_raw) is bytes:
            self.depth_raw = PngImage(self.depth_raw)
        if decoding():
            self._check()
        elif self.gt_pose is not None:
            self.gt_pose = as_matrix(self.gt_pose, 4, "gt_pose")

    def _check(self) -> None:
        depth = self.depth_raw
        if isinstance(depth, dict) and set(depth) == {"png"} and isinstance(depth["png"], bytes):
            self.depth_raw = PngImage(depth["png"])
        else:
            self.depth_raw = decode_array(depth, "depth", ndim=2, dtype="uint16")
            k = self.intrinsics
            if self.depth_raw.shape != (k.height, k.width):
                raise MessageError(f"depth shape {self.depth_raw.shape} does not match intrinsics "
                                   f"{k.height}x{k.width}")
        if self.gt_pose is not None:
            self.gt_pose = validate_pose(self.gt_pose, "gt_pose")

    @classmethod
    def from_arrays(cls, robot: str, frame_id: int, stamp: float, rgb: np.ndarray | bytes,
                    depth: np.ndarray | PngImage, depth_scale: float, intrinsics: Intrinsics,
                    gt_pose: np.ndarray | None = None, instances: list[GroundTruthInstance] | None = None,
                    jpeg_quality: int = 90) -> Frame:
        """Build a frame from an RGB uint8 image and a uint16 depth image (what a SLAM front end has). Either may
        instead be a file's bytes to send as they are: `rgb` a JPEG, `depth` a 16-bit PNG (`PngImage`); their
        size is the caller's to have checked against `intrinsics` (receivers check it when they decode)."""
        if isinstance(rgb, bytes):
            jpeg, size = rgb, (intrinsics.height, intrinsics.width)
        else:
            if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
                raise MessageError("rgb must be an HxWx3 uint8 array")
            jpeg, size = cls.encode_rgb(rgb, jpeg_quality), rgb.shape[:2]
        if not isinstance(depth, PngImage):
            if depth.dtype != np.uint16 or depth.shape != size:
                raise MessageError("depth must be a uint16 array of the RGB image's size")
            depth = np.ascontiguousarray(depth)
        frame = cls(robot, frame_id, stamp, jpeg, depth, depth_scale, intrinsics,
                    None if gt_pose is None else np.asarray(gt_pose, np.float64), list(instances or []))
        if not isinstance(rgb, bytes):
            frame._rgb = rgb
        return frame

    @staticmethod
    def encode_rgb(rgb: np.ndarray, quality: int = 90) -> bytes:
        jpeg = image_codec().encode_jpeg(rgb, quality)
        if jpeg is None:
            raise MessageError("JPEG encoding failed")
        return jpeg

    def encode(self) -> bytes:
        if type(self.depth_raw) is bytes:  # PNG bytes assigned after construction
            self.depth_raw = PngImage(self.depth_raw)
        return super().encode()

    def depth_as_png(self) -> None:
        """Carry the depth as a 16-bit PNG from now on (~3.5x smaller, ~10 ms to encode: for slow links);
        left raw if encoding fails."""
        png = image_codec().encode_png16(self.depth())
        if png is not None:
            self.depth_raw = PngImage(png)

    def rgb(self) -> np.ndarray:
        """The HxWx3 uint8 RGB image (decoded once)."""
        if self._rgb is None:
            rgb = image_codec().decode_jpeg(self.rgb_jpeg)
            if rgb is None or rgb.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
                raise MessageError(f"frame {self.frame_id}: RGB is not a decodable JPEG of the stated size")
            self._rgb = rgb
        return self._rgb

    def depth(self) -> np.ndarray:
        """The HxW uint16 depth image (0 = invalid; a PNG's `DEPTH_NO_READING` reads as 0 too)."""
        if isinstance(self.depth_raw, bytes):
            img = image_codec().decode_png16(bytes(self.depth_raw))
            if img is None or img.dtype != np.uint16 or img.shape != (self.intrinsics.height, self.intrinsics.width):
                raise MessageError(f"frame {self.frame_id}: depth is not a 16-bit PNG of the stated size")
            img[img == DEPTH_NO_READING] = 0
            self.depth_raw = img
        return self.depth_raw

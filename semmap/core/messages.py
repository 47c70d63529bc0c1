"""Every message semmap sends, in one place: msgpack maps with a `schema` version and strict validation.

Why one module: an external SLAM (or a service in another language) needs a single page to read, and every
service must reject a malformed or wrong-version message the same way (`MessageError`), never crash on it.

Conventions
- A message is a msgpack map; key `schema` is `semmap.<kind>/<version>`.
- Poses are 4x4 camera-to-world matrices, flattened row-major to 16 floats (metres).
- Boxes are `[x1, y1, x2, y2]` pixels. Times are seconds (`stamp`: dataset time; `sent_at`: wall clock).
- Arrays travel as `{"dtype", "shape", "data"}` with raw little-endian bytes; RGB images as JPEG, depth as
  raw uint16 (or 16-bit PNG) with `depth_scale` metres per unit, 0 = invalid.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, TypeVar

import cv2
import msgpack
import numpy as np

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
ROBOT_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_ALLOWED_DTYPES = {"uint8", "uint16", "int32", "int64", "float32", "float64"}

M = TypeVar("M", bound="Message")


class MessageError(ValueError):
    """A payload that is not a valid semmap message of the expected kind and version."""


# ---------------------------------------------------------------------------------------------------------
# small validation helpers


def _get(d: dict, key: str, kind: type | tuple[type, ...], optional: bool = False) -> Any:
    if key not in d or d[key] is None:
        if optional:
            return None
        raise MessageError(f"missing field '{key}'")
    value = d[key]
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(value, bool) and kind is not bool and bool not in (kind if isinstance(kind, tuple) else ()):
        raise MessageError(f"field '{key}' must be {kind}, got bool")
    if not isinstance(value, kind):
        raise MessageError(f"field '{key}' must be {kind}, got {type(value).__name__}")
    if isinstance(value, float) and not math.isfinite(value):
        raise MessageError(f"field '{key}' must be finite, got {value}")
    return value


def _finite_floats(values: Any, n: int | None, name: str) -> list[float]:
    if not isinstance(values, list | tuple):
        raise MessageError(f"field '{name}' must be a list of numbers")
    if n is not None and len(values) != n:
        raise MessageError(f"field '{name}' must have {n} numbers, got {len(values)}")
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise MessageError(f"field '{name}' must hold numbers")
        f = float(v)
        if not math.isfinite(f):
            raise MessageError(f"field '{name}' holds a non-finite number")
        out.append(f)
    return out


def _robot(d: dict) -> str:
    robot = _get(d, "robot", str)
    if not ROBOT_NAME.match(robot):
        raise MessageError(f"invalid robot name {robot!r}: use letters, digits, '_' or '-'")
    return robot


def _non_negative_int(d: dict, key: str) -> int:
    value = _get(d, key, int)
    if value < 0:
        raise MessageError(f"field '{key}' must be >= 0")
    return value


def validate_pose(values: Any, name: str = "pose") -> np.ndarray:
    """A 4x4 rigid transform from 16 floats: finite, orthonormal rotation, det +1, last row 0 0 0 1."""
    pose = np.asarray(_finite_floats(values, 16, name), dtype=np.float64).reshape(4, 4)
    if np.abs(pose).max() > 1e9:
        raise MessageError(f"'{name}' holds implausibly large numbers")
    rot = pose[:3, :3]
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise MessageError(f"'{name}' last row must be 0 0 0 1")
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-3) or np.linalg.det(rot) < 0.0:
        raise MessageError(f"'{name}' rotation is not orthonormal with det +1")
    return pose


def _non_rigid(poses: np.ndarray) -> np.ndarray:
    """Indices of the Nx4x4 poses that are not rigid transforms (vectorised: trajectories are long)."""
    sane = np.abs(poses).reshape(len(poses), -1).max(axis=1, initial=0.0) <= 1e9
    poses = np.where(sane[:, None, None], poses, np.eye(4))
    rot = poses[:, :3, :3]
    ortho = np.abs(rot @ np.transpose(rot, (0, 2, 1)) - np.eye(3)).max(axis=(1, 2)) <= 1e-3
    rows = np.abs(poses[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1) <= 1e-6
    return np.flatnonzero(~(sane & ortho & rows & (np.linalg.det(rot) > 0)))


def pose_to_wire(pose: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(pose, dtype=np.float64).reshape(16)]


def encode_array(array: np.ndarray) -> dict:
    array = np.ascontiguousarray(array)
    if array.dtype.name not in _ALLOWED_DTYPES:
        raise MessageError(f"dtype {array.dtype} cannot travel")
    data = array.astype(array.dtype.newbyteorder("<")).tobytes()
    return {"dtype": array.dtype.name, "shape": list(array.shape), "data": data}


def decode_array(d: Any, name: str, ndim: int | None = None, dtype: str | None = None) -> np.ndarray:
    if not isinstance(d, dict):
        raise MessageError(f"field '{name}' must be an array map")
    kind = _get(d, "dtype", str)
    shape = _get(d, "shape", list)
    data = _get(d, "data", bytes)
    if kind not in _ALLOWED_DTYPES or (dtype is not None and kind != dtype):
        raise MessageError(f"field '{name}' has dtype {kind!r}, expected {dtype or sorted(_ALLOWED_DTYPES)}")
    if ndim is not None and len(shape) != ndim:
        raise MessageError(f"field '{name}' must have {ndim} dimensions, got {len(shape)}")
    if not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 1 << 20 for s in shape):
        raise MessageError(f"field '{name}' has an invalid shape {shape}")
    dt = np.dtype(kind).newbyteorder("<")
    if math.prod(shape) * dt.itemsize != len(data):
        raise MessageError(f"field '{name}': {len(data)} bytes do not fit shape {shape} of {kind}")
    array = np.frombuffer(data, dtype=dt).reshape(shape)
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise MessageError(f"field '{name}' holds non-finite numbers")
    if sys.byteorder == "little":  # a native dtype: some libraries (Open3D) refuse an explicit '<' byte order
        return array.view(np.dtype(kind))
    return array.astype(np.dtype(kind))


def _box(values: Any, name: str = "box") -> tuple[float, float, float, float]:
    x1, y1, x2, y2 = _finite_floats(values, 4, name)
    if x2 <= x1 or y2 <= y1:
        raise MessageError(f"'{name}' must have x2 > x1 and y2 > y1")
    return (x1, y1, x2, y2)


# ---------------------------------------------------------------------------------------------------------
# the message base class


class Message:
    """Base of all messages: `encode()` to bytes, `decode(bytes)` with validation.

    Every message may carry `run`: the id of the `semmap run` that sent it (optional; absent or "" from peers
    that do not know it, so older peers keep working). Receivers in a run reject messages of another run.
    `sender` is not on the wire: the bus sets it on receipt to the role the message was signed by.
    """

    SCHEMA: ClassVar[str] = ""
    run: str = ""  # not a dataclass field of the kinds: handled here, for every kind alike
    sender: str = ""

    def to_dict(self) -> dict:
        raise NotImplementedError

    @classmethod
    def from_dict(cls: type[M], d: dict) -> M:
        raise NotImplementedError

    def encode(self) -> bytes:
        body = self.to_dict()
        body["schema"] = self.SCHEMA
        if self.run:
            body["run"] = self.run
        return msgpack.packb(body, use_bin_type=True)

    @classmethod
    def decode(cls: type[M], payload: bytes | bytearray | memoryview) -> M:
        if len(payload) > MAX_MESSAGE_BYTES:
            raise MessageError(f"message of {len(payload)} bytes exceeds the limit of {MAX_MESSAGE_BYTES}")
        try:
            d = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES)
        except Exception as exc:  # msgpack raises several unrelated types on garbage
            raise MessageError(f"not a msgpack message: {type(exc).__name__}: {exc}") from None
        if not isinstance(d, dict):
            raise MessageError("a message must be a msgpack map")
        schema = d.get("schema")
        if schema != cls.SCHEMA:
            kind, _, _ = cls.SCHEMA.partition("/")
            if isinstance(schema, str) and schema.partition("/")[0] == kind:
                raise MessageError(f"unsupported version {schema!r}: this build reads {cls.SCHEMA!r}")
            raise MessageError(f"expected schema {cls.SCHEMA!r}, got {schema!r}")
        run = d.get("run", "")
        if not isinstance(run, str) or (run and not ROBOT_NAME.match(run)):
            raise MessageError("field 'run' must be 1-64 letters, digits, '_' or '-'")
        try:
            message = cls.from_dict(d)
        except MessageError:
            raise
        except (TypeError, ValueError, KeyError, IndexError, AttributeError, OverflowError, cv2.error) as exc:
            raise MessageError(f"invalid {cls.SCHEMA} message: {type(exc).__name__}: {exc}") from None
        if run:
            message.run = run
        return message


# ---------------------------------------------------------------------------------------------------------
# sensor data


@dataclass
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: Any) -> Intrinsics:
        if not isinstance(d, dict):
            raise MessageError("field 'intrinsics' must be a map")
        k = cls(_get(d, "fx", float), _get(d, "fy", float), _get(d, "cx", float), _get(d, "cy", float),
                _get(d, "width", int), _get(d, "height", int))
        if k.fx <= 0 or k.fy <= 0 or not (0 < k.width <= 16384 and 0 < k.height <= 16384):
            raise MessageError("intrinsics must have positive focal lengths and image size")
        return k

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass
class GroundTruthInstance:
    """A ground-truth object box (synthetic data): lets the oracle detector run anywhere in the pipeline."""

    instance_id: int
    class_name: str
    box: tuple[float, float, float, float]
    visible_pixels: int
    moving: bool

    def to_dict(self) -> dict:
        return {"instance_id": self.instance_id, "class": self.class_name, "box": list(self.box),
                "visible_pixels": self.visible_pixels, "moving": self.moving}

    @classmethod
    def from_dict(cls, d: Any) -> GroundTruthInstance:
        if not isinstance(d, dict):
            raise MessageError("an instance must be a map")
        return cls(_get(d, "instance_id", int), _get(d, "class", str), _box(d.get("box")),
                   _get(d, "visible_pixels", int), _get(d, "moving", bool))


@dataclass
class Frame(Message):
    """One RGB-D frame. Images stay encoded until a consumer asks (`rgb()`, `depth()`), then are cached."""

    SCHEMA: ClassVar[str] = "semmap.frame/1"
    robot: str
    frame_id: int
    stamp: float
    rgb_jpeg: bytes
    depth_raw: np.ndarray | bytes  # uint16 HxW array, or 16-bit PNG bytes
    depth_scale: float
    intrinsics: Intrinsics
    gt_pose: np.ndarray | None = None
    instances: list[GroundTruthInstance] = field(default_factory=list)
    sent_at: float = 0.0
    _rgb: np.ndarray | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_arrays(cls, robot: str, frame_id: int, stamp: float, rgb: np.ndarray, depth: np.ndarray,
                    depth_scale: float, intrinsics: Intrinsics, gt_pose: np.ndarray | None = None,
                    instances: list[GroundTruthInstance] | None = None, jpeg_quality: int = 90) -> Frame:
        """Build a frame from an RGB uint8 image and a uint16 depth image (what a SLAM front end has)."""
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise MessageError("rgb must be an HxWx3 uint8 array")
        if depth.dtype != np.uint16 or depth.shape != rgb.shape[:2]:
            raise MessageError("depth must be a uint16 array of the RGB image's size")
        frame = cls(robot, frame_id, stamp, cls.encode_rgb(rgb, jpeg_quality), np.ascontiguousarray(depth),
                    depth_scale, intrinsics, gt_pose, list(instances or []))
        frame._rgb = rgb
        return frame

    @staticmethod
    def encode_rgb(rgb: np.ndarray, quality: int = 90) -> bytes:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise MessageError("JPEG encoding failed")
        return buf.tobytes()

    def depth_as_png(self) -> None:
        """Carry the depth as a 16-bit PNG from now on (~3.5x smaller, ~10 ms to encode: for slow links);
        left raw if encoding fails."""
        ok, png = cv2.imencode(".png", self.depth())
        if ok:
            self.depth_raw = png.tobytes()

    def rgb(self) -> np.ndarray:
        """The HxWx3 uint8 RGB image (decoded once)."""
        if self._rgb is None:
            bgr = cv2.imdecode(np.frombuffer(self.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
            if bgr is None or bgr.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
                raise MessageError(f"frame {self.frame_id}: RGB is not a decodable JPEG of the stated size")
            self._rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return self._rgb

    def depth(self) -> np.ndarray:
        """The HxW uint16 depth image (0 = invalid)."""
        if isinstance(self.depth_raw, bytes):
            img = cv2.imdecode(np.frombuffer(self.depth_raw, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None or img.dtype != np.uint16 or img.shape != (self.intrinsics.height, self.intrinsics.width):
                raise MessageError(f"frame {self.frame_id}: depth is not a 16-bit PNG of the stated size")
            self.depth_raw = img
        return self.depth_raw

    def to_dict(self) -> dict:
        depth = self.depth_raw
        return {
            "robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp, "sent_at": self.sent_at,
            "rgb_jpeg": self.rgb_jpeg,
            "depth": {"png": depth} if isinstance(depth, bytes) else encode_array(depth),
            "depth_scale": self.depth_scale, "intrinsics": self.intrinsics.to_dict(),
            "gt_pose": None if self.gt_pose is None else pose_to_wire(self.gt_pose),
            "instances": [i.to_dict() for i in self.instances],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Frame:
        intr = Intrinsics.from_dict(d.get("intrinsics"))
        depth_field = _get(d, "depth", dict)
        if "png" in depth_field:
            depth: np.ndarray | bytes = _get(depth_field, "png", bytes)
        else:
            depth = decode_array(depth_field, "depth", ndim=2, dtype="uint16")
            if depth.shape != (intr.height, intr.width):
                raise MessageError(f"depth shape {depth.shape} does not match intrinsics {intr.height}x{intr.width}")
        scale = _get(d, "depth_scale", float)
        if not 0.0 < scale < 1.0:
            raise MessageError("depth_scale must be in (0, 1) metres per unit")
        gt = d.get("gt_pose")
        return cls(
            robot=_robot(d), frame_id=_non_negative_int(d, "frame_id"), stamp=_get(d, "stamp", float),
            rgb_jpeg=_get(d, "rgb_jpeg", bytes), depth_raw=depth, depth_scale=scale, intrinsics=intr,
            gt_pose=None if gt is None else validate_pose(gt, "gt_pose"),
            instances=[GroundTruthInstance.from_dict(i) for i in _get(d, "instances", list)],
            sent_at=_get(d, "sent_at", float),
        )


@dataclass
class OdometryPose(Message):
    """A camera pose from the SLAM front end (ours or an external one) for one frame.

    sigma_translation / sigma_rotation: the front end's 1-sigma uncertainty of the motion since the previous
    frame (metres, radians); the backend scales them by sqrt(frames) between two of its nodes.
    """

    SCHEMA: ClassVar[str] = "semmap.odometry/1"
    robot: str
    frame_id: int
    stamp: float
    pose: np.ndarray
    keyframe: bool = True
    sigma_translation: float = 0.01
    sigma_rotation: float = 0.005
    source: str = "external"
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp, "pose": pose_to_wire(self.pose),
                "keyframe": self.keyframe, "sigma_translation": self.sigma_translation,
                "sigma_rotation": self.sigma_rotation, "source": self.source, "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> OdometryPose:
        st, sr = _get(d, "sigma_translation", float), _get(d, "sigma_rotation", float)
        if st <= 0 or sr <= 0:
            raise MessageError("odometry sigmas must be positive")
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float), validate_pose(d.get("pose")),
                   _get(d, "keyframe", bool), st, sr, _get(d, "source", str), _get(d, "sent_at", float))


# ---------------------------------------------------------------------------------------------------------
# detections and tracklets


@dataclass
class DepthPatch:
    """The depth pixels under a box, subsampled by `stride`, so the associator can back-project them."""

    x0: int
    y0: int
    stride: int
    depth: np.ndarray  # uint16

    @classmethod
    def from_depth(cls, depth: np.ndarray, box: tuple[float, float, float, float], stride: int) -> DepthPatch:
        """The depth pixels under `box` (clipped to the image), every `stride`-th in x and y."""
        h, w = depth.shape
        x0 = int(np.clip(np.floor(box[0]), 0, w - 1))
        y0 = int(np.clip(np.floor(box[1]), 0, h - 1))
        x1 = int(np.clip(np.ceil(box[2]), x0 + 1, w))
        y1 = int(np.clip(np.ceil(box[3]), y0 + 1, h))
        return cls(x0, y0, stride, np.ascontiguousarray(depth[y0:y1:stride, x0:x1:stride]))

    def to_dict(self) -> dict:
        return {"x0": self.x0, "y0": self.y0, "stride": self.stride, "depth": encode_array(self.depth)}

    @classmethod
    def from_dict(cls, d: Any) -> DepthPatch:
        if not isinstance(d, dict):
            raise MessageError("field 'depth_patch' must be a map")
        stride = _get(d, "stride", int)
        if not 1 <= stride <= 64:
            raise MessageError("depth patch stride must be in 1..64")
        return cls(_get(d, "x0", int), _get(d, "y0", int), stride,
                   decode_array(d.get("depth"), "depth_patch", ndim=2, dtype="uint16"))


@dataclass
class Detection:
    box: tuple[float, float, float, float]
    class_name: str
    score: float
    depth_m: float  # median depth inside the box
    depth_patch: DepthPatch | None = None

    def to_dict(self) -> dict:
        return {"box": list(self.box), "class": self.class_name, "score": self.score, "depth_m": self.depth_m,
                "depth_patch": None if self.depth_patch is None else self.depth_patch.to_dict()}

    @classmethod
    def from_dict(cls, d: Any) -> Detection:
        if not isinstance(d, dict):
            raise MessageError("a detection must be a map")
        score = _get(d, "score", float)
        if not 0.0 <= score <= 1.0:
            raise MessageError("detection score must be in [0, 1]")
        patch = d.get("depth_patch")
        return cls(_box(d.get("box")), _get(d, "class", str), score, _get(d, "depth_m", float),
                   None if patch is None else DepthPatch.from_dict(patch))


@dataclass
class Detections(Message):
    """The detector's answer for one frame. Every frame gets one, `skipped` ones too, so consumers never wait."""

    SCHEMA: ClassVar[str] = "semmap.detections/1"
    robot: str
    frame_id: int
    stamp: float
    intrinsics: Intrinsics
    depth_scale: float
    detections: list[Detection] = field(default_factory=list)
    skipped: str = ""  # why this frame was not detected ("" = it was): "dropped", "stride", "bad_frame"
    detector: str = ""
    timing_ms: dict[str, float] = field(default_factory=dict)
    frame_sent_at: float = 0.0
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp,
                "intrinsics": self.intrinsics.to_dict(), "depth_scale": self.depth_scale,
                "detections": [x.to_dict() for x in self.detections], "skipped": self.skipped,
                "detector": self.detector, "timing_ms": dict(self.timing_ms), "frame_sent_at": self.frame_sent_at,
                "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> Detections:
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   Intrinsics.from_dict(d.get("intrinsics")), _get(d, "depth_scale", float),
                   [Detection.from_dict(x) for x in _get(d, "detections", list)], _get(d, "skipped", str),
                   _get(d, "detector", str), _timings(d), _get(d, "frame_sent_at", float), _get(d, "sent_at", float))


def _timings(d: dict, key: str = "timing_ms") -> dict[str, float]:
    t = _get(d, key, dict)
    return {str(k): float(v) for k, v in zip(t.keys(), _finite_floats(list(t.values()), None, key), strict=True)}


@dataclass
class Measurement:
    """One detection of a tracklet: what the associator back-projects."""

    frame_id: int
    stamp: float
    detection: Detection
    intrinsics: Intrinsics
    depth_scale: float
    # a box of a dynamic class (a person) covers part of this one in the same frame: its depth may show the
    # person, so the associator's motion tests leave it out (optional on the wire: absent reads False)
    occluded: bool = False

    def to_dict(self) -> dict:
        return {"frame_id": self.frame_id, "stamp": self.stamp, "detection": self.detection.to_dict(),
                "intrinsics": self.intrinsics.to_dict(), "depth_scale": self.depth_scale, "occluded": self.occluded}

    @classmethod
    def from_dict(cls, d: Any) -> Measurement:
        if not isinstance(d, dict):
            raise MessageError("a measurement must be a map")
        occluded = d.get("occluded", False)
        if not isinstance(occluded, bool):
            raise MessageError("field 'occluded' must be a bool")
        return cls(_non_negative_int(d, "frame_id"), _get(d, "stamp", float), Detection.from_dict(d.get("detection")),
                   Intrinsics.from_dict(d.get("intrinsics")), _get(d, "depth_scale", float), occluded)


@dataclass
class CandidateUpdate:
    """A tracklet that reached the minimum size: its first proposal carries all measurements, later ones new."""

    track_id: int
    class_name: str
    measurements: list[Measurement]
    first: bool  # True on the proposal, False when feeding an already proposed tracklet

    def to_dict(self) -> dict:
        return {"track_id": self.track_id, "class": self.class_name, "first": self.first,
                "measurements": [m.to_dict() for m in self.measurements]}

    @classmethod
    def from_dict(cls, d: Any) -> CandidateUpdate:
        if not isinstance(d, dict):
            raise MessageError("a candidate must be a map")
        return cls(_non_negative_int(d, "track_id"), _get(d, "class", str),
                   [Measurement.from_dict(m) for m in _get(d, "measurements", list)], _get(d, "first", bool))


@dataclass
class TrackedBox:
    """A tracklet's box in this frame, for display (state: tentative / candidate)."""

    track_id: int
    class_name: str
    box: tuple[float, float, float, float]
    length: int
    candidate: bool

    def to_dict(self) -> dict:
        return {"track_id": self.track_id, "class": self.class_name, "box": list(self.box), "length": self.length,
                "candidate": self.candidate}

    @classmethod
    def from_dict(cls, d: Any) -> TrackedBox:
        if not isinstance(d, dict):
            raise MessageError("a tracked box must be a map")
        return cls(_non_negative_int(d, "track_id"), _get(d, "class", str), _box(d.get("box")),
                   _get(d, "length", int), _get(d, "candidate", bool))


@dataclass
class Tracks(Message):
    """The tracker's output for one frame (one per frame, always): candidates to associate and ended tracklets."""

    SCHEMA: ClassVar[str] = "semmap.tracks/1"
    robot: str
    frame_id: int
    stamp: float
    candidates: list[CandidateUpdate] = field(default_factory=list)
    ended: list[int] = field(default_factory=list)
    boxes: list[TrackedBox] = field(default_factory=list)
    skipped: str = ""
    timing_ms: dict[str, float] = field(default_factory=dict)
    frame_sent_at: float = 0.0
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp,
                "candidates": [c.to_dict() for c in self.candidates], "ended": list(self.ended),
                "boxes": [b.to_dict() for b in self.boxes], "skipped": self.skipped,
                "timing_ms": dict(self.timing_ms), "frame_sent_at": self.frame_sent_at, "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> Tracks:
        ended = _get(d, "ended", list)
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in ended):
            raise MessageError("field 'ended' must hold track ids")
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   [CandidateUpdate.from_dict(c) for c in _get(d, "candidates", list)], ended,
                   [TrackedBox.from_dict(b) for b in _get(d, "boxes", list)], _get(d, "skipped", str),
                   _timings(d), _get(d, "frame_sent_at", float), _get(d, "sent_at", float))


@dataclass
class DynamicBox:
    """An object in a frame that is dynamic: by class (`associator.dynamic_classes`) or seen moving.

    depth_min_m..depth_max_m: the depth range of the object's surface in the box (metres; 0, 0 when the box
    held no valid depth): a consumer can leave out only the pixels in that range (the background behind a
    person stays usable) or the whole box.
    """

    track_id: int
    class_name: str
    box: tuple[float, float, float, float]
    depth_min_m: float
    depth_max_m: float
    reason: str  # "class" | "moving"

    REASONS: ClassVar[tuple[str, ...]] = ("class", "moving")

    def to_dict(self) -> dict:
        return {"track_id": self.track_id, "class": self.class_name, "box": list(self.box),
                "depth_min_m": self.depth_min_m, "depth_max_m": self.depth_max_m, "reason": self.reason}

    @classmethod
    def from_dict(cls, d: Any) -> DynamicBox:
        if not isinstance(d, dict):
            raise MessageError("a dynamic box must be a map")
        lo, hi = _get(d, "depth_min_m", float), _get(d, "depth_max_m", float)
        if not 0.0 <= lo <= hi:
            raise MessageError("a dynamic box needs 0 <= depth_min_m <= depth_max_m")
        reason = _get(d, "reason", str)
        if reason not in cls.REASONS:
            raise MessageError(f"dynamic box reason must be one of {cls.REASONS}, got {reason!r}")
        return cls(_non_negative_int(d, "track_id"), _get(d, "class", str), _box(d.get("box")), lo, hi, reason)


@dataclass
class DynamicObjects(Message):
    """The tracker's dynamic objects of one frame, one message per frame (an empty list too, so a front end in
    lockstep can wait for it). `skipped`: the frame was not detected; the boxes are then those of the last
    detected frame of tracklets still alive."""

    SCHEMA: ClassVar[str] = "semmap.dynamic/1"
    robot: str
    frame_id: int
    stamp: float
    boxes: list[DynamicBox] = field(default_factory=list)
    skipped: str = ""
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp,
                "boxes": [b.to_dict() for b in self.boxes], "skipped": self.skipped, "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> DynamicObjects:
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   [DynamicBox.from_dict(b) for b in _get(d, "boxes", list)], _get(d, "skipped", str),
                   _get(d, "sent_at", float))


# ---------------------------------------------------------------------------------------------------------
# the map and the pose graph


LANDMARK_STATUSES = ("present", "prior", "missing")


@dataclass
class Landmark:
    """A mapped object. `centroid` and `extent` in the world frame (metres); `radius` is its sphere's."""

    id: int
    class_name: str
    centroid: tuple[float, float, float]
    radius: float
    extent: tuple[float, float, float]
    observations: int
    first_seen: float
    last_seen: float
    # "present" (mapped or seen again this session), "prior" (from a loaded map, not seen again yet) or
    # "missing" (from a loaded map, in plain view for several frames and not detected); see docs/MAPS.md
    status: str = "present"

    def to_dict(self) -> dict:
        return {"id": self.id, "class": self.class_name, "centroid": list(self.centroid), "radius": self.radius,
                "extent": list(self.extent), "observations": self.observations, "first_seen": self.first_seen,
                "last_seen": self.last_seen, "status": self.status}

    @classmethod
    def from_dict(cls, d: Any) -> Landmark:
        if not isinstance(d, dict):
            raise MessageError("a landmark must be a map")
        c = _finite_floats(d.get("centroid"), 3, "centroid")
        e = _finite_floats(d.get("extent"), 3, "extent")
        status = _get(d, "status", str, optional=True) or "present"
        if status not in LANDMARK_STATUSES:
            raise MessageError(f"landmark status must be one of {', '.join(LANDMARK_STATUSES)}, got {status!r}")
        return cls(_non_negative_int(d, "id"), _get(d, "class", str), (c[0], c[1], c[2]), _get(d, "radius", float),
                   (e[0], e[1], e[2]), _non_negative_int(d, "observations"), _get(d, "first_seen", float),
                   _get(d, "last_seen", float), status)


@dataclass
class Observation:
    """A landmark seen from one frame: its centroid in that camera's frame, for the backend."""

    landmark_id: int
    class_name: str
    point_camera: tuple[float, float, float]
    sigma: float  # 1-sigma isotropic, metres
    size: float

    def to_dict(self) -> dict:
        return {"landmark_id": self.landmark_id, "class": self.class_name, "point_camera": list(self.point_camera),
                "sigma": self.sigma, "size": self.size}

    @classmethod
    def from_dict(cls, d: Any) -> Observation:
        if not isinstance(d, dict):
            raise MessageError("an observation must be a map")
        p = _finite_floats(d.get("point_camera"), 3, "point_camera")
        sigma = _get(d, "sigma", float)
        if sigma <= 0:
            raise MessageError("observation sigma must be positive")
        return cls(_non_negative_int(d, "landmark_id"), _get(d, "class", str), (p[0], p[1], p[2]), sigma,
                   _get(d, "size", float))


@dataclass
class MapAlignment:
    """A session relocalised against a prior map (docs/MAPS.md): from the frame that carries it on, the session's
    poses belong in the prior map's frame. `transform` takes the session's (odometry) frame to the prior frame;
    `anchors` are prior landmarks (id, position in the prior frame) that the backend holds within `anchor_sigma_m`;
    the fit's own figures (`inliers`, `rms_m`) travel along for the record."""

    transform: np.ndarray
    anchors: list[tuple[int, tuple[float, float, float]]]
    anchor_sigma_m: float
    inliers: int
    rms_m: float

    def to_dict(self) -> dict:
        return {"transform": [float(v) for v in np.asarray(self.transform).reshape(16)],
                "anchors": [[i, list(p)] for i, p in self.anchors], "anchor_sigma_m": self.anchor_sigma_m,
                "inliers": self.inliers, "rms_m": self.rms_m}

    @classmethod
    def from_dict(cls, d: Any) -> MapAlignment:
        if not isinstance(d, dict):
            raise MessageError("an alignment must be a map")
        anchors = []
        for a in _get(d, "anchors", list):
            if not (isinstance(a, list) and len(a) == 2 and isinstance(a[0], int) and not isinstance(a[0], bool)
                    and a[0] >= 0):
                raise MessageError("an anchor must be [landmark_id, [x, y, z]]")
            x = _finite_floats(a[1], 3, "anchor")
            anchors.append((a[0], (x[0], x[1], x[2])))
        sigma = _get(d, "anchor_sigma_m", float)
        if sigma <= 0:
            raise MessageError("anchor_sigma_m must be positive")
        return cls(validate_pose(d.get("transform"), "transform"), anchors, sigma,
                   _non_negative_int(d, "inliers"), _get(d, "rms_m", float))


@dataclass
class Observations(Message):
    """The associator's landmark observations for one frame (at most one per landmark every 2 s), and merges.

    `merges` are (absorbed id, surviving id): the backend joins the two landmark variables. `alignment` (once per
    session, optional): the session relocalised against a prior map at this frame. `retired` are landmarks whose
    object was seen moving: the backend drops their factors (they must stop pulling the trajectory towards where
    the object was). Optional on the wire (absent = none).
    """

    SCHEMA: ClassVar[str] = "semmap.observations/1"
    robot: str
    frame_id: int
    stamp: float
    observations: list[Observation] = field(default_factory=list)
    merges: list[tuple[int, int]] = field(default_factory=list)
    sent_at: float = 0.0
    alignment: MapAlignment | None = None
    retired: list[int] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp,
                "observations": [o.to_dict() for o in self.observations],
                "merges": [list(m) for m in self.merges], "sent_at": self.sent_at,
                "alignment": None if self.alignment is None else self.alignment.to_dict(),
                "retired": list(self.retired)}

    @classmethod
    def from_dict(cls, d: dict) -> Observations:
        alignment = d.get("alignment")
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   [Observation.from_dict(o) for o in _get(d, "observations", list)],
                   _merges(_get(d, "merges", list)), _get(d, "sent_at", float),
                   alignment=None if alignment is None else MapAlignment.from_dict(alignment),
                   retired=_ids(_get(d, "retired", list, optional=True) or [], "retired"))


def _ids(raw: list, name: str) -> list[int]:
    if not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in raw):
        raise MessageError(f"field '{name}' must hold non-negative integer ids")
    return list(raw)


def _merges(raw: list) -> list[tuple[int, int]]:
    out = []
    for m in raw:
        if not (isinstance(m, list) and len(m) == 2 and all(isinstance(i, int) and i >= 0 for i in m)):
            raise MessageError("a merge must be [absorbed_id, surviving_id]")
        out.append((m[0], m[1]))
    return out


@dataclass
class TagDetection:
    """An observation in the AprilTag-like form RTAB-Map consumes: id, size, camera-frame pose, 6x6 covariance.

    Objects carry no orientation: the rotation is identity and its covariance large (rotation unconstrained).
    """

    id: int
    size: float
    pose: np.ndarray  # 4x4 in the camera frame
    covariance: np.ndarray  # 6x6, (x, y, z, roll, pitch, yaw)

    @classmethod
    def from_observation(cls, obs: Observation, rotation_sigma_rad: float = 1e3) -> TagDetection:
        pose = np.eye(4)
        pose[:3, 3] = obs.point_camera
        cov = np.diag([obs.sigma**2] * 3 + [rotation_sigma_rad**2] * 3)
        return cls(obs.landmark_id, obs.size, pose, cov)

    def to_dict(self) -> dict:
        return {"id": self.id, "size": self.size, "pose": pose_to_wire(self.pose),
                "covariance": [float(v) for v in np.asarray(self.covariance, float).reshape(36)]}

    @classmethod
    def from_dict(cls, d: Any) -> TagDetection:
        if not isinstance(d, dict):
            raise MessageError("a tag detection must be a map")
        cov = np.asarray(_finite_floats(d.get("covariance"), 36, "covariance")).reshape(6, 6)
        if np.any(np.diag(cov) < 0):
            raise MessageError("covariance must have a non-negative diagonal")
        return cls(_non_negative_int(d, "id"), _get(d, "size", float), validate_pose(d.get("pose")), cov)


@dataclass
class TagDetections(Message):
    """The frame's landmark observations as tag detections (key `observations/tags`)."""

    SCHEMA: ClassVar[str] = "semmap.landmark_tags/1"
    robot: str
    frame_id: int
    stamp: float
    detections: list[TagDetection] = field(default_factory=list)
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "frame_id": self.frame_id, "stamp": self.stamp,
                "detections": [t.to_dict() for t in self.detections], "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> TagDetections:
        return cls(_robot(d), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   [TagDetection.from_dict(t) for t in _get(d, "detections", list)], _get(d, "sent_at", float))


@dataclass
class MapUpdate(Message):
    """Landmarks that changed (or all, when `full`), removed ids and merges, after processing `frame_id`."""

    SCHEMA: ClassVar[str] = "semmap.map_update/1"
    robot: str
    seq: int
    frame_id: int
    stamp: float
    landmarks: list[Landmark] = field(default_factory=list)
    removed: list[int] = field(default_factory=list)
    merges: list[tuple[int, int]] = field(default_factory=list)
    full: bool = False
    rejected_candidates: list[int] = field(default_factory=list)
    timing_ms: dict[str, float] = field(default_factory=dict)
    frame_sent_at: float = 0.0
    sent_at: float = 0.0
    moved: list[int] = field(default_factory=list)  # of `removed`: retired because their object was seen moving
    moving_tracks: list[int] = field(default_factory=list)  # of `rejected_candidates`: rejected as moving

    def to_dict(self) -> dict:
        return {"robot": self.robot, "seq": self.seq, "frame_id": self.frame_id, "stamp": self.stamp,
                "landmarks": [lm.to_dict() for lm in self.landmarks], "removed": list(self.removed),
                "merges": [list(m) for m in self.merges], "full": self.full,
                "rejected_candidates": list(self.rejected_candidates), "timing_ms": dict(self.timing_ms),
                "frame_sent_at": self.frame_sent_at, "sent_at": self.sent_at, "moved": list(self.moved),
                "moving_tracks": list(self.moving_tracks)}

    @classmethod
    def from_dict(cls, d: dict) -> MapUpdate:
        removed = _get(d, "removed", list)
        rejected = _get(d, "rejected_candidates", list)
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in removed + rejected):
            raise MessageError("removed / rejected_candidates must hold integer ids")
        return cls(_robot(d), _non_negative_int(d, "seq"), _non_negative_int(d, "frame_id"), _get(d, "stamp", float),
                   [Landmark.from_dict(x) for x in _get(d, "landmarks", list)], removed,
                   _merges(_get(d, "merges", list)), _get(d, "full", bool), rejected, _timings(d),
                   _get(d, "frame_sent_at", float), _get(d, "sent_at", float),
                   _ids(_get(d, "moved", list, optional=True) or [], "moved"),
                   _ids(_get(d, "moving_tracks", list, optional=True) or [], "moving_tracks"))


@dataclass
class CorrectedPoses(Message):
    """The backend's estimate after processing `frame_id`, as a delta: the frames whose corrected pose moved by
    more than the backend's tolerance since its previous message (new frames always), and the landmarks whose
    position did. Every `full` message (the first, then periodically, for late joiners) carries every frame and
    landmark instead. `num_frames`: how many frames the backend holds, so a consumer can tell it is complete.

    Why deltas: the whole trajectory every frame grows without bound (an hour at 30 fps is 108,000 poses, 14 MB
    a message); a consumer keeps a pose per frame and applies each message with `apply_to`.
    """

    SCHEMA: ClassVar[str] = "semmap.corrected_poses/2"
    robot: str
    seq: int
    frame_id: int
    frame_ids: np.ndarray  # int64 (N,), ascending
    stamps: np.ndarray  # float64 (N,)
    poses: np.ndarray  # float64 (N, 4, 4)
    landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    landmark_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    timing_ms: dict[str, float] = field(default_factory=dict)
    sent_at: float = 0.0
    full: bool = True
    num_frames: int = 0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "seq": self.seq, "frame_id": self.frame_id, "full": self.full,
                "num_frames": int(self.num_frames or len(self.frame_ids)),
                "frame_ids": encode_array(np.asarray(self.frame_ids, np.int64)),
                "stamps": encode_array(np.asarray(self.stamps, np.float64)),
                "poses": encode_array(np.asarray(self.poses, np.float64)),
                "landmark_ids": encode_array(np.asarray(self.landmark_ids, np.int64)),
                "landmark_positions": encode_array(np.asarray(self.landmark_positions, np.float64).reshape(-1, 3)),
                "timing_ms": dict(self.timing_ms), "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> CorrectedPoses:
        ids = decode_array(d.get("frame_ids"), "frame_ids", ndim=1, dtype="int64")
        stamps = decode_array(d.get("stamps"), "stamps", ndim=1, dtype="float64")
        poses = decode_array(d.get("poses"), "poses", ndim=3, dtype="float64")
        lids = decode_array(d.get("landmark_ids"), "landmark_ids", ndim=1, dtype="int64")
        lpos = decode_array(d.get("landmark_positions"), "landmark_positions", ndim=2, dtype="float64")
        if not (len(ids) == len(stamps) == len(poses)) or poses.shape[1:] != (4, 4):
            raise MessageError("frame_ids, stamps and poses must have the same length and poses be Nx4x4")
        if len(ids) > 1 and not np.all(np.diff(ids) > 0):
            raise MessageError("frame_ids must be strictly ascending")
        if len(lids) != len(lpos) or lpos.shape[1] != 3:
            raise MessageError("landmark_ids and landmark_positions must match (Nx3)")
        bad = _non_rigid(poses)
        if bad.size:
            raise MessageError(f"poses[{int(bad[0])}] is not a rigid transform")
        full = _get(d, "full", bool)
        num_frames = _non_negative_int(d, "num_frames")
        if num_frames < len(ids) or (full and num_frames != len(ids)):
            raise MessageError(f"num_frames {num_frames} does not fit {len(ids)} poses (full: {full})")
        return cls(_robot(d), _non_negative_int(d, "seq"), _non_negative_int(d, "frame_id"), ids, stamps, poses,
                   lids, lpos, _timings(d), _get(d, "sent_at", float), full, num_frames)

    def apply_to(self, poses: dict[int, np.ndarray], landmarks: dict[int, np.ndarray] | None = None) -> list[int]:
        """Bring a consumer's pose per frame (and landmark positions) up to this message: a `full` one replaces
        them, a delta overwrites the frames it carries. Returns the frame ids that changed, ascending."""
        if self.full:
            poses.clear()
            if landmarks is not None:
                landmarks.clear()
        changed = [int(f) for f in self.frame_ids]
        poses.update(zip(changed, self.poses, strict=True))
        if landmarks is not None:
            landmarks.update((int(i), p) for i, p in zip(self.landmark_ids, self.landmark_positions, strict=True))
        return changed


# ---------------------------------------------------------------------------------------------------------
# control, progress and health


@dataclass
class Control(Message):
    """Run control from the player / CLI: `end_of_stream` after the last frame, `stop` to shut down,
    `frame_unreadable` for a dataset frame that could not be read (`last_frame_id`: that frame; it never comes)."""

    SCHEMA: ClassVar[str] = "semmap.control/1"
    COMMANDS: ClassVar[tuple[str, ...]] = ("end_of_stream", "stop", "frame_unreadable")
    robot: str
    command: str
    last_frame_id: int = 0
    frames: int = 0
    sent_at: float = 0.0
    # end_of_stream from an external source (the ROS 2 bridge): what it counted on its side, e.g. frames lost
    # before semmap by reason; the run keeps them in stats.json ("source"). Optional: absent when empty.
    counters: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {"robot": self.robot, "command": self.command, "last_frame_id": self.last_frame_id,
             "frames": self.frames, "sent_at": self.sent_at}
        if self.counters:
            d["counters"] = dict(self.counters)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Control:
        command = _get(d, "command", str)
        if command not in cls.COMMANDS:
            raise MessageError(f"unknown control command {command!r}; known: {', '.join(cls.COMMANDS)}")
        counters = _get(d, "counters", dict, optional=True) or {}
        if not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) for k, v in counters.items()):
            raise MessageError("counters must map names to integers")
        return cls(_robot(d), command, _get(d, "last_frame_id", int), _get(d, "frames", int), _get(d, "sent_at", float),
                   counters)


@dataclass
class Progress(Message):
    """A service finished everything that `frame_id` caused: lockstep playback waits on these."""

    SCHEMA: ClassVar[str] = "semmap.progress/1"
    robot: str
    service: str
    frame_id: int
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {"robot": self.robot, "service": self.service, "frame_id": self.frame_id, "sent_at": self.sent_at}

    @classmethod
    def from_dict(cls, d: dict) -> Progress:
        return cls(_robot(d), _get(d, "service", str), _get(d, "frame_id", int), _get(d, "sent_at", float))


@dataclass
class ServiceStatus(Message):
    """A service's health and counters, sent periodically and once more when it finishes."""

    SCHEMA: ClassVar[str] = "semmap.status/1"
    STATES: ClassVar[tuple[str, ...]] = ("starting", "running", "finished", "failed", "stopped")
    robot: str
    service: str
    instance: str
    state: str
    last_frame_id: int = -1
    counters: dict[str, int] = field(default_factory=dict)
    timings: dict[str, dict[str, float]] = field(default_factory=dict)
    rss_mb: float = 0.0
    cpu_s: float = 0.0
    message: str = ""
    sent_at: float = 0.0

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> ServiceStatus:
        state = _get(d, "state", str)
        if state not in cls.STATES:
            raise MessageError(f"unknown service state {state!r}")
        counters = _get(d, "counters", dict)
        if not all(isinstance(k, str) and isinstance(v, int) for k, v in counters.items()):
            raise MessageError("counters must map names to integers")
        timings = _get(d, "timings", dict)
        clean_timings = {}
        for k, v in timings.items():
            if not isinstance(v, dict):
                raise MessageError("timings must map names to maps")
            clean_timings[str(k)] = _timings({"t": v}, "t")
        return cls(_robot(d), _get(d, "service", str), _get(d, "instance", str), state, _get(d, "last_frame_id", int),
                   counters, clean_timings, _get(d, "rss_mb", float), _get(d, "cpu_s", float), _get(d, "message", str),
                   _get(d, "sent_at", float))


ALL_MESSAGES: tuple[type[Message], ...] = (
    Frame, OdometryPose, Detections, Tracks, Observations, TagDetections, MapUpdate, CorrectedPoses, Control, Progress,
    ServiceStatus, DynamicObjects,
)

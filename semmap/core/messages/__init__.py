"""Every message semmap sends: typed msgspec Structs, msgpack on the wire, a `schema` version and strict validation.

Why one package with one import point: an external SLAM (or a service in another language) needs one place to
read, and every service must reject a malformed or wrong-version message the same way (`MessageError`), never
crash on it. The kinds live in modules by topic (`frames`, `poses`, `detections`, `tracks`, `map`, `control`);
`docs/interface.schema.json` is their JSON Schema (`python -m semmap.core.messages.schema`).

Conventions
- A message is a msgpack map; key `schema` is `semmap.<kind>/<version>`.
- Poses are 4x4 camera-to-world matrices, flattened row-major to 16 floats (metres).
- Boxes are `[x1, y1, x2, y2]` pixels. Times are seconds (`stamp`: dataset time; `sent_at`: wall clock).
- Arrays travel as `{"dtype", "shape", "data"}` with raw little-endian bytes; RGB images as JPEG, depth as
  raw uint16 (or 16-bit PNG) with `depth_scale` metres per unit, 0 = invalid.
"""

from __future__ import annotations

from .base import (
    MAX_MESSAGE_BYTES,
    ROBOT_NAME,
    Message,
    MessageError,
    Part,
    PngImage,
    decode_array,
    encode_array,
    peek_frame_id,
    pose_to_wire,
    validate_pose,
)
from .control import Control, Progress, ServiceStatus
from .detections import DepthPatch, Detection, Detections
from .frames import (
    DEFAULT_IMAGE_CODEC,
    DEPTH_NO_READING,
    Frame,
    GroundTruthInstance,
    ImageCodec,
    Intrinsics,
    image_codec,
    use_image_codec,
)
from .map import (
    LANDMARK_STATUSES,
    Landmark,
    MapAlignment,
    MapUpdate,
    Observation,
    Observations,
    TagDetection,
    TagDetections,
)
from .poses import CorrectedPoses, OdometryPose, OdometryRefinement
from .tracks import CandidateUpdate, DynamicBox, DynamicObjects, Measurement, TrackedBox, Tracks

ALL_MESSAGES: tuple[type[Message], ...] = (
    Frame, OdometryPose, Detections, Tracks, Observations, TagDetections, MapUpdate, CorrectedPoses, Control, Progress,
    ServiceStatus, DynamicObjects, OdometryRefinement,
)

__all__ = [
    "ALL_MESSAGES", "DEFAULT_IMAGE_CODEC", "DEPTH_NO_READING", "LANDMARK_STATUSES", "MAX_MESSAGE_BYTES", "ROBOT_NAME",
    "CandidateUpdate", "Control", "CorrectedPoses", "DepthPatch", "Detection", "Detections", "DynamicBox",
    "DynamicObjects", "Frame", "GroundTruthInstance", "ImageCodec", "Intrinsics", "Landmark", "MapAlignment",
    "MapUpdate", "Measurement", "Message", "MessageError", "Observation", "Observations", "OdometryPose",
    "OdometryRefinement", "Part",
    "PngImage", "Progress", "ServiceStatus", "TagDetection", "TagDetections", "TrackedBox", "Tracks",
    "decode_array", "encode_array", "image_codec", "peek_frame_id", "pose_to_wire", "use_image_codec", "validate_pose",
]

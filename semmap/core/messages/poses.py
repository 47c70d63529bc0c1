"""Poses: the front end's `OdometryPose` (key `odometry`), its `OdometryRefinement` at the end of a run (key
`odometry/refined`) and the backend's `CorrectedPoses` (key `poses/corrected`)."""

from __future__ import annotations

import msgspec
import numpy as np

from .base import (
    Finite,
    Message,
    MessageError,
    NonNegativeInt,
    Pose,
    Positive,
    RobotName,
    Timings,
    array_map,
    as_matrix,
    decoding,
    expect_array,
    non_rigid,
    validate_pose,
)


class OdometryPose(Message, tag="semmap.odometry/1"):
    """A camera pose from the SLAM front end (ours or an external one) for one frame.

    sigma_translation / sigma_rotation: the front end's 1-sigma uncertainty of the motion since the previous
    frame (metres, radians); the backend scales them by sqrt(frames) between two of its nodes. `bridged`: the
    front end measured nothing of this frame (its SLAM had lost track) and the pose is a stand-in (the motion
    model's); the backend places such frames between their measured neighbours once the next measured frame comes.
    `step`: whose step this pose took, where semmap checked a SLAM (slam | semmap | motion | copied).
    """

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    pose: Pose
    keyframe: bool = True
    sigma_translation: Positive = 0.01
    sigma_rotation: Positive = 0.005
    source: str = "external"
    sent_at: Finite = 0.0
    bridged: bool = False
    step: str = ""

    def __post_init__(self) -> None:
        self.pose = validate_pose(self.pose) if decoding() else as_matrix(self.pose, 4, "pose")


class OdometryRefinement(Message, tag="semmap.odometry_refinement/1"):
    """The front end's odometry poses of earlier frames again, after its SLAM refined its own trajectory at its end
    (ORB-SLAM3: semmap/algorithms/odometry/refinement.py), sent once, after the stream's last pose. They replace
    the poses of the `odometry` messages of the same frames in the backend's graph, which is optimised again before
    the run's trajectory is written. No poses and `withheld`: why the refinement was not taken (the backend waits
    for this message from such a front end either way, so a run ends when it knows)."""

    robot: RobotName
    source: str
    frame_ids: array_map("int64", 1, "frame ids, strictly ascending")
    poses: array_map("float64", 3, "the frames' refined odometry poses, Nx4x4")
    withheld: str = ""
    sent_at: Finite = 0.0

    def __post_init__(self) -> None:
        if decoding():
            ids = expect_array(self.frame_ids, "frame_ids", 1, "int64")
            poses = expect_array(self.poses, "poses", 3, "float64")
            if len(ids) != len(poses) or poses.shape[1:] != (4, 4):
                raise MessageError("frame_ids and poses must have the same length and poses be Nx4x4")
            if len(ids) > 1 and not np.all(np.diff(ids) > 0):
                raise MessageError("frame_ids must be strictly ascending")
            bad = non_rigid(poses) if len(poses) else np.zeros(0)
            if bad.size:
                raise MessageError(f"poses[{int(bad[0])}] is not a rigid transform")

    def encode(self) -> bytes:
        wire = msgspec.structs.replace(self, frame_ids=np.asarray(self.frame_ids, np.int64),
                                       poses=np.asarray(self.poses, np.float64).reshape(-1, 4, 4))
        return super(OdometryRefinement, wire).encode()


class CorrectedPoses(Message, tag="semmap.corrected_poses/2"):
    """The backend's estimate after processing `frame_id`, as a delta: the frames whose corrected pose moved by
    more than the backend's tolerance since its previous message (new frames always), and the landmarks whose
    position did. Every `full` message (the first, then periodically, for late joiners) carries every frame and
    landmark instead. `num_frames`: how many frames the backend holds, so a consumer can tell it is complete.

    Why deltas: the whole trajectory every frame grows without bound (an hour at 30 fps is 108,000 poses, 14 MB
    a message); a consumer keeps a pose per frame and applies each message with `apply_to`.
    """

    robot: RobotName
    seq: NonNegativeInt
    frame_id: NonNegativeInt
    frame_ids: array_map("int64", 1, "frame ids, strictly ascending")
    stamps: array_map("float64", 1, "the frames' stamps")
    poses: array_map("float64", 3, "the frames' corrected poses, Nx4x4")
    landmark_ids: array_map("int64", 1, "landmark ids") = msgspec.field(default_factory=lambda: np.zeros(0, np.int64))
    landmark_positions: array_map("float64", 2, "landmark positions, Nx3") = msgspec.field(
        default_factory=lambda: np.zeros((0, 3)))
    timing_ms: Timings = msgspec.field(default_factory=dict)
    sent_at: Finite = 0.0
    full: bool = True
    num_frames: NonNegativeInt = 0

    def __post_init__(self) -> None:
        if decoding():
            self._check()

    def encode(self) -> bytes:
        """Arrays as their wire dtypes, whatever the producer filled in (they may be assigned after construction)."""
        wire = msgspec.structs.replace(
            self, frame_ids=np.asarray(self.frame_ids, np.int64), stamps=np.asarray(self.stamps, np.float64),
            poses=np.asarray(self.poses, np.float64), landmark_ids=np.asarray(self.landmark_ids, np.int64),
            landmark_positions=np.asarray(self.landmark_positions, np.float64).reshape(-1, 3),
            num_frames=int(self.num_frames or len(self.frame_ids)))
        return super(CorrectedPoses, wire).encode()

    def _check(self) -> None:
        ids = expect_array(self.frame_ids, "frame_ids", 1, "int64")
        stamps = expect_array(self.stamps, "stamps", 1, "float64")
        poses = expect_array(self.poses, "poses", 3, "float64")
        lids = expect_array(self.landmark_ids, "landmark_ids", 1, "int64")
        lpos = expect_array(self.landmark_positions, "landmark_positions", 2, "float64")
        if not (len(ids) == len(stamps) == len(poses)) or poses.shape[1:] != (4, 4):
            raise MessageError("frame_ids, stamps and poses must have the same length and poses be Nx4x4")
        if len(ids) > 1 and not np.all(np.diff(ids) > 0):
            raise MessageError("frame_ids must be strictly ascending")
        if len(lids) != len(lpos) or lpos.shape[1] != 3:
            raise MessageError("landmark_ids and landmark_positions must match (Nx3)")
        bad = non_rigid(poses)
        if bad.size:
            raise MessageError(f"poses[{int(bad[0])}] is not a rigid transform")
        if self.num_frames < len(ids) or (self.full and self.num_frames != len(ids)):
            raise MessageError(f"num_frames {self.num_frames} does not fit {len(ids)} poses (full: {self.full})")

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

"""The tracker's output per frame: `Tracks` (key `tracks`: tracklets to associate) and `DynamicObjects` (key
`dynamic`: boxes a SLAM should leave out)."""

from __future__ import annotations

from typing import ClassVar, Literal

import msgspec

from .base import (
    Box,
    Finite,
    Id,
    Message,
    MessageError,
    NonNegativeFloat,
    NonNegativeInt,
    Part,
    RobotName,
    Timings,
    as_box,
    check_box,
    decoding,
    settle_box,
)
from .detections import Detection
from .frames import Intrinsics


class Measurement(Part):
    """One detection of a tracklet: what the associator back-projects."""

    frame_id: NonNegativeInt
    stamp: Finite
    detection: Detection
    intrinsics: Intrinsics
    depth_scale: Finite
    # a box of a dynamic class (a person) covers part of this one in the same frame: its depth may show the
    # person, so the associator's motion tests leave it out (optional on the wire: absent reads False)
    occluded: bool = False


class CandidateUpdate(Part):
    """A tracklet that reached the minimum size: its first proposal carries all measurements, later ones new."""

    track_id: Id
    class_name: str = msgspec.field(name="class")
    measurements: list[Measurement]
    first: bool  # True on the proposal, False when feeding an already proposed tracklet


class TrackedBox(Part):
    """A tracklet's box in this frame, for display (state: tentative / candidate)."""

    track_id: Id
    class_name: str = msgspec.field(name="class")
    box: Box
    length: int
    candidate: bool

    def __post_init__(self) -> None:
        settle_box(self)


class Tracks(Message, tag="semmap.tracks/1"):
    """The tracker's output for one frame (one per frame, always): candidates to associate and ended tracklets."""

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    candidates: list[CandidateUpdate] = msgspec.field(default_factory=list)
    ended: list[int] = msgspec.field(default_factory=list)
    boxes: list[TrackedBox] = msgspec.field(default_factory=list)
    skipped: str = ""
    timing_ms: Timings = msgspec.field(default_factory=dict)
    frame_sent_at: Finite = 0.0
    sent_at: Finite = 0.0


class DynamicBox(Part):
    """An object in a frame that is dynamic: by class (`associator.dynamic_classes`) or seen moving.

    depth_min_m..depth_max_m: the depth range of the object's surface in the box (metres; 0, 0 when the box
    held no valid depth): a consumer can leave out only the pixels in that range (the background behind a
    person stays usable) or the whole box. `held`: not detected in this frame; the object's last detected box,
    grown by how far it may have moved since (a mask, not a measurement of where it is).
    """

    REASONS: ClassVar[tuple[str, ...]] = ("class", "moving")
    track_id: Id
    class_name: str = msgspec.field(name="class")
    box: Box
    depth_min_m: NonNegativeFloat
    depth_max_m: NonNegativeFloat
    reason: Literal["class", "moving"]
    held: bool = False

    def __post_init__(self) -> None:
        if decoding():  # msgspec made it a tuple of floats
            check_box(self.box)
            if self.depth_min_m > self.depth_max_m:
                raise MessageError("a dynamic box needs 0 <= depth_min_m <= depth_max_m")
        else:
            self.box = as_box(self.box)


class DynamicObjects(Message, tag="semmap.dynamic/1"):
    """The tracker's dynamic objects of one frame, one message per frame (an empty list too, so a front end in
    lockstep can wait for it). `skipped`: the frame was not detected; the boxes are then those of the last
    detected frame of tracklets still alive."""

    robot: RobotName
    frame_id: NonNegativeInt
    stamp: Finite
    boxes: list[DynamicBox] = msgspec.field(default_factory=list)
    skipped: str = ""
    sent_at: Finite = 0.0

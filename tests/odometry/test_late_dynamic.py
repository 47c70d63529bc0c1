"""Real time: the tracker's dynamic objects come after the front end has posed their frame. The motion test sees
them at their own frame's pose, not at the pose of the frame they came with."""

from __future__ import annotations

import numpy as np

from semmap.algorithms.odometry.base import OdometryInput
from semmap.algorithms.odometry.checked import CheckedSlam
from semmap.core.messages import DynamicBox

FX = 525.0
W, H = 640, 480
K = np.array([[FX, 0.0, W / 2], [0.0, FX, H / 2], [0.0, 0.0, 1.0]])
LAG = 3  # frames between a frame and its dynamic objects reaching the front end


def _turning(i: int) -> np.ndarray:
    """A camera swinging +-20 degrees about its vertical axis once a second (a hand-held camera looking round)."""
    yaw = np.radians(20.0 * np.sin(2 * np.pi * i / 30.0))
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
    return pose


def _still_person(pose: np.ndarray) -> DynamicBox:
    """The box of a person standing still 2 m ahead of the world's origin, as this camera sees them."""
    x = np.linalg.inv(pose) @ np.array([0.0, 0.0, 2.0, 1.0])
    u = FX * x[0] / x[2] + W / 2
    return DynamicBox(5, "person", (u - 60, 100.0, u + 60, 400.0), float(x[2]) - 0.2, float(x[2]) + 0.2, "class")


def _watch(at_own_pose: bool) -> CheckedSlam:
    checked = CheckedSlam()
    rgb, depth = np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.uint16)
    for i in range(90):
        late = i - LAG
        boxes = [_still_person(_turning(late))] if late >= 0 else []
        frame = OdometryInput(i, i / 30.0, None, rgb, depth, 0.001, K, dynamic=boxes, behind=True)
        if at_own_pose:
            frame.dynamic_seen = [(late, late / 30.0, boxes)] if late >= 0 else []
        checked.pose(frame, slam_pose=_turning(i))
    return checked


def test_late_dynamic_objects_are_placed_by_their_own_frames_pose() -> None:
    assert not _watch(at_own_pose=True).moving.seen_moving
    # placed by the pose of the frame they arrived with, the turning camera would make the still person walk
    assert _watch(at_own_pose=False).moving.seen_moving == {5}


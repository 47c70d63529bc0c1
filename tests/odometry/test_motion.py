"""Which dynamic objects are seen moving (semmap/algorithms/odometry/motion.py): pure, made-up boxes."""

from __future__ import annotations

import numpy as np

from semmap.algorithms.odometry.motion import MotionParams, MovingObjects
from semmap.core.messages import DynamicBox

FX = FY = 525.0
CX, CY, W, H = 320.0, 240.0, 640, 480


def _box(track: int, x0: float, x1: float, y0: float = 100.0, y1: float = 400.0, depth: float = 2.0,
         held: bool = False, reason: str = "class") -> DynamicBox:
    return DynamicBox(track, "person", (x0, y0, x1, y1), depth - 0.2, depth + 0.2, reason, held=held)


def _watch(boxes_per_frame: list[list[DynamicBox]], poses: list[np.ndarray] | None = None,
           params: MotionParams | None = None) -> tuple[MovingObjects, list[bool], list[bool]]:
    moving = MovingObjects(params)
    seen, undecided = [], []
    for i, boxes in enumerate(boxes_per_frame):
        seen.append(moving.moving(boxes))
        undecided.append(moving.undecided(boxes))
        moving.observe(i / 30.0, boxes, np.eye(4) if poses is None else poses[i], FX, FY, CX, CY, W, H)
    return moving, seen, undecided


def test_a_person_sitting_still_never_moves_and_is_soon_known_to_be_still():
    rng = np.random.default_rng(0)
    frames = [[_box(7, 250 + rng.normal(0, 3), 390 + rng.normal(0, 3))] for _ in range(90)]
    moving, seen, undecided = _watch(frames)
    assert not any(seen) and not moving.seen_moving
    assert undecided[0] and not any(undecided[30:])  # (half a second of views tells)


def test_a_walker_is_seen_moving_within_two_thirds_of_a_second():
    frames = [[_box(3, 100 + 8 * i, 220 + 8 * i)] for i in range(60)]  # ~1 m/s across the view at 2 m
    moving, seen, _ = _watch(frames)
    assert moving.seen_moving == {3}
    assert seen.index(True) <= 20


def test_a_still_person_seen_by_a_turning_camera_is_still():
    """The camera turns (the box slides across the image) but the poses say so: in the world the person stays."""
    poses, frames = [], []
    for i in range(60):
        yaw = np.radians(0.3 * i)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        poses.append(T)
        x = np.linalg.inv(T) @ np.array([0.0, 0.0, 2.0, 1.0])  # the person at (0, 0, 2) in the world
        u = FX * x[0] / x[2] + CX
        frames.append([_box(5, u - 60, u + 60, depth=float(x[2]))])
    moving, seen, _ = _watch(frames, poses)
    assert not any(seen)


def test_held_boxes_and_boxes_whose_visible_part_changes_are_no_evidence():
    """A held box (the tracker's grown prediction) and a person entering from the top of a fast-turning view
    (its box widens as the shoulders come in) say nothing of where the person is."""
    held = [[_box(2, 100 + 20 * i, 200 + 20 * i, held=True)] for i in range(30)]
    entering = [[_box(4, 280 - 6 * i, 320 + 6 * i, y0=0.0, y1=40.0 + 12 * i)] for i in range(20)]
    for frames in (held, entering):
        moving, seen, _ = _watch(frames)
        assert not any(seen) and not moving.seen_moving


def test_a_walker_leaving_by_the_side_is_followed_by_its_inner_edge():
    """Cut by the image's left edge, the box's centre slides with the part in view; its right edge is the
    person's, and it keeps moving."""
    frames = [[_box(9, 0.0, 300 - 10 * i)] for i in range(30)]
    moving, _, _ = _watch(frames)
    assert moving.seen_moving == {9}


def test_an_object_the_associator_saw_move_is_moving():
    moving, seen, _ = _watch([[_box(1, 100, 200, reason="moving")]])
    assert seen == [True]


def test_state_keeps_who_moved():
    frames = [[_box(3, 100 + 8 * i, 220 + 8 * i)] for i in range(30)]
    moving, _, _ = _watch(frames)
    again = MovingObjects()
    again.restore(moving.state())
    assert again.moving(frames[-1]) and again.seen_moving == {3}

"""Approximate-time matching of the bridge (semmap.services.ros2.sync) and the ROS <-> numpy conversions, without ROS:
messages are plain objects with the ROS field names."""

from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from semmap.datasets.ros_convert import (
    ROS_BODY_TO_OPTICAL,
    ConversionError,
    colour_to_rgb,
    depth_to_mm,
    matrix_quaternion,
    parse_pose_to_optical,
    quaternion_matrix,
)
from semmap.services.ros2.sync import CameraFrames, FrameSync, StampGaps, missing_at_ends

W, H = 8, 6


def _header(t: float, frame: str = "cam") -> NS:
    sec = math.floor(t)
    return NS(stamp=NS(sec=sec, nanosec=round((t - sec) * 1e9)), frame_id=frame)


def colour(t: float, w: int = W, h: int = H, encoding: str = "rgb8") -> NS:
    rgb = np.full((h, w, 3), int(t * 10) % 255, np.uint8)
    return NS(header=_header(t), encoding=encoding, height=h, width=w, step=w * 3, data=rgb.tobytes())


def depth(t: float, w: int = W, h: int = H) -> NS:
    return NS(
        header=_header(t),
        encoding="16UC1",
        height=h,
        width=w,
        step=w * 2,
        is_bigendian=0,
        data=np.full((h, w), 1000, np.uint16).tobytes(),
    )


def pose(t: float, x: float = 0.0, qw: float = 1.0) -> NS:
    p = NS(position=NS(x=x, y=0.0, z=0.0), orientation=NS(x=0.0, y=0.0, z=0.0, w=qw))
    return NS(header=_header(t, "world"), child_frame_id="cam", pose=NS(pose=p))


def info(w: int = W, h: int = H) -> NS:
    return NS(width=w, height=h, k=[100.0, 0, w / 2, 0, 100.0, h / 2, 0, 0, 1])


ODOM = "nav_msgs/msg/Odometry"


def test_matches_within_tolerance_in_any_arrival_order_and_interpolates_the_pose() -> None:
    sync = FrameSync(tolerance_s=0.02)
    out = sync.add_camera_info(info())
    out += sync.add_pose(pose(0.0, x=0.0), ODOM)
    out += sync.add_depth(depth(0.105))
    out += sync.add_colour(colour(0.100))  # pose 0.1 not there yet: waits for one after it
    assert out == []
    out = sync.add_pose(pose(0.2, x=2.0), ODOM)
    assert len(out) == 1 and out[0].stamp == pytest.approx(0.1)
    assert out[0].pose[0, 3] == pytest.approx(1.0)  # halfway between the two poses
    assert out[0].world_frame == "world" and out[0].camera_frame == "cam" and out[0].intrinsics[4:] == (W, H)


def test_bad_and_unmatchable_messages_are_counted_and_skipped() -> None:
    sync = FrameSync(tolerance_s=0.02, max_wait_s=1.0)
    sync.add_camera_info(NS(width=W, height=H, k=[0.0] * 9))
    assert sync.counters["bad_camera_info"] == 1
    sync.add_camera_info(info())
    assert sync.add_colour(colour(0.0, encoding="yuv422")) == []
    assert sync.add_colour(NS(header=_header(0.0), encoding="rgb8", height=H, width=W, step=W * 3, data=b"x")) == []
    assert sync.add_pose(pose(0.0, x=math.nan), ODOM) == [] and sync.add_pose(pose(0.0, qw=0.0), ODOM) == []
    assert sync.counters["bad_colour"] == 2 and sync.counters["bad_pose"] == 2
    # another size than the camera info: dropped when matched
    sync.add_pose(pose(1.0), ODOM)
    sync.add_depth(depth(1.0, w=4, h=3))
    assert sync.add_colour(colour(1.0, w=4, h=3)) == [] and sync.counters["size_mismatch"] == 1
    # no depth near it, and a newer depth passed it: dropped
    sync.add_colour(colour(2.0))
    sync.add_pose(pose(2.0), ODOM)
    sync.add_depth(depth(2.5))
    assert sync.counters["colour_without_depth"] == 1
    # a pose gap longer than pose_max_gap_s: not interpolated, dropped once poses have passed it
    sync.add_colour(colour(3.0))
    sync.add_depth(depth(3.0))
    assert sync.add_pose(pose(3.7), ODOM) == [] and sync.counters["colour_without_pose"] == 1
    # and one good frame still goes through after all that
    sync.add_colour(colour(3.7))
    assert len(sync.add_depth(depth(3.7))) == 1 and sync.counters["matched"] == 1


def test_frames_wait_for_the_camera_info_then_go_in_order() -> None:
    sync = FrameSync()
    for t in (0.0, 0.1):
        sync.add_colour(colour(t))
        sync.add_depth(depth(t))
        sync.add_pose(pose(t), ODOM)
    out = sync.add_camera_info(info())
    assert [f.stamp for f in out] == pytest.approx([0.0, 0.1])


def test_conversions() -> None:
    rgb = np.arange(H * W * 3, dtype=np.uint8).reshape(H, W, 3)
    padded = np.zeros((H, W * 3 + 4), np.uint8)
    padded[:, : W * 3] = rgb.reshape(H, -1)
    assert np.array_equal(colour_to_rgb("rgb8", H, W, W * 3 + 4, padded.tobytes()), rgb)  # rows with padding
    assert np.array_equal(colour_to_rgb("bgr8", H, W, W * 3, rgb[:, :, ::-1].tobytes()), rgb)
    metres = np.array([[1.25, np.nan], [-1.0, 70.0]], np.float32)  # NaN, negative, beyond 65.535 m: invalid
    assert depth_to_mm("32FC1", 2, 2, 8, metres.tobytes()).tolist() == [[1250, 0], [0, 0]]
    big = np.array([[1, 2]], ">u2")
    assert depth_to_mm("16UC1", 1, 2, 4, big.tobytes(), big_endian=True).tolist() == [[1, 2]]
    with pytest.raises(ConversionError):
        depth_to_mm("8UC1", 1, 2, 2, b"ab")
    rot = quaternion_matrix(0.1, -0.2, 0.3, 0.9)
    assert np.allclose(quaternion_matrix(*matrix_quaternion(rot)), rot)
    assert np.allclose(parse_pose_to_optical("ros"), ROS_BODY_TO_OPTICAL)
    # REP 103 -> 104: the optical z (forward) is the body's x, the optical x (right) the body's -y
    assert np.allclose(ROS_BODY_TO_OPTICAL[:3, 2], [1, 0, 0]) and np.allclose(ROS_BODY_TO_OPTICAL[:3, 0], [0, -1, 0])
    assert np.allclose(parse_pose_to_optical("0 0 0.1 0 0 0 1")[:3, 3], [0, 0, 0.1])
    with pytest.raises(ValueError):
        parse_pose_to_optical("sideways")


def test_stamp_gaps_count_the_messages_missing_from_a_stream() -> None:
    """30 Hz stamps with 1, then 3 messages missing: two gaps, four messages; repeated stamps apart."""
    gaps = StampGaps()
    stamps = [i / 30 for i in range(40) if i not in (20, 30, 31, 32)]
    assert sum(gaps.add(t) for t in stamps) == 4
    assert gaps.gaps == 2 and gaps.missing == 4 and gaps.as_dict()["period_s"] == pytest.approx(1 / 30, abs=1e-6)
    gaps.add(stamps[-1])
    assert gaps.out_of_order == 1 and gaps.missing == 4


def test_the_last_frame_is_sent_by_flush_and_what_cannot_match_is_counted_at_the_end() -> None:
    """The last colour image of a recording, whose depth is a little older and whose pose is the last one, is held
    for a closer depth or a newer pose; flush() sends it. finish() counts colour images without depth."""
    sync = FrameSync(tolerance_s=0.02)
    sync.add_camera_info(info())
    out = []
    for i in range(5):
        t = i / 30
        out += sync.add_pose(pose(t), ODOM)
        out += sync.add_depth(depth(t - 0.005))
        out += sync.add_colour(colour(t))
    assert len(out) == 4 and sync.pending() == 1  # the last one waits for a closer depth image
    last = sync.flush()
    assert len(last) == 1 and last[0].stamp == pytest.approx(4 / 30)
    sync.add_colour(colour(10.0))  # no depth ever comes for it
    assert sync.finish() == []
    assert sync.counters["colour_unmatched_at_end"] + sync.counters["colour_without_depth"] == 1
    assert sync.pending() == 0


def test_colour_images_lost_at_the_ends_are_counted_from_the_depth_stream() -> None:
    """No gap shows the first two and the last three colour images lost; the depth stream (same rate) does."""
    colour, depth_stream, odom = StampGaps(), StampGaps(), StampGaps()
    for i in range(40):
        depth_stream.add(i / 30)
        odom.add(i / 100)  # another rate: says nothing about the camera's frames
        if 2 <= i < 37:
            colour.add(i / 30)
    assert missing_at_ends(colour.as_dict(), [depth_stream.as_dict(), odom.as_dict()]) == 5


def test_camera_frames_count_colour_images_lost_even_when_most_are() -> None:
    """150 frames at 30 Hz, camera info for all but two, colour for one in five (the median colour step is then
    the loss pattern's, not the camera's): the colour images missing are 150 - 30, also for the frames whose camera
    info was lost too, and stamps far behind the newest are only counted."""
    frames = CameraFrames(horizon_s=1.0)
    for i in range(150):
        t = 100 + i / 30
        if i not in (50, 51):
            frames.add(t, colour=False)
        if i % 5 == 0:
            frames.add(t, colour=True)
    assert frames.frames() == 150 and frames.colour_missing() == 120


def test_stamp_gaps_find_the_period_when_most_messages_are_lost() -> None:
    """30 % of a 30 Hz stream arrives, at random: the period is still the camera's, and every message missing
    between the first and the last received is counted, those before the period was known included."""
    rng = np.random.default_rng(7)
    kept = [i for i in range(300) if rng.random() < 0.3]
    gaps = StampGaps()
    for i in kept:
        gaps.add(5 + i / 30)
    assert gaps.period == pytest.approx(1 / 30, abs=1e-6)
    assert gaps.missing == (kept[-1] - kept[0] + 1) - len(kept)

"""What the viewer sends to Rerun per message, in real time where its CPU is taken from the detector
(semmap.services.viz.service): latency samples as one column per stage, nothing for a frame the detector passed
over (its last boxes stay up instead of blinking off), and camera paths redrawn by the part that changed."""

from __future__ import annotations

import argparse

import numpy as np
import rerun as rr

from semmap.core.messages import Detection, Detections, Intrinsics, OdometryPose, TrackedBox, Tracks
from semmap.runtime.transport.service import common_arguments
from semmap.services.viz.service import PathParts, TimingColumns, VizService

K = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)


def test_samples_wait_by_stage_in_arrival_order_and_are_taken_once() -> None:
    timings = TimingColumns()
    timings.add("timings/detector/detect_ms", 2, 101.5)
    timings.add("timings/tracker/proposal", 2, 1.25)
    timings.add("timings/detector/detect_ms", 4, 99.0)
    assert len(timings) == 3
    assert timings.take() == {"timings/detector/detect_ms": ([2, 4], [101.5, 99.0]),
                              "timings/tracker/proposal": ([2], [1.25])}
    assert len(timings) == 0 and timings.take() == {}


def test_a_skipped_frame_logs_nothing_and_keeps_the_last_boxes() -> None:
    parser = argparse.ArgumentParser()
    common_arguments(parser)
    viz = VizService(parser.parse_args(["--mode", "realtime"]))
    rr.init("semmap-test-viz", spawn=False)
    recording = rr.memory_recording()
    viz.rr, viz.timings = rr, TimingColumns()
    recording.drain_as_bytes()
    nothing = len(recording.drain_as_bytes())  # what a drain with nothing logged holds (framing only)
    box = Detection((10.0, 10.0, 50.0, 60.0), "cup", 0.9, 1.2)
    viz.on_detections(Detections("r", 2, 2 / 30, K, 1000.0, [box], "", "detector-a", {"detect_ms": 101.5}))
    assert len(recording.drain_as_bytes()) > nothing
    for reason in ("stride", "dropped"):
        viz.on_detections(Detections("r", 3, 3 / 30, K, 1000.0, [], reason, "detector-a"))
        assert len(recording.drain_as_bytes()) == nothing, reason
    viz.on_detections(Detections("r", 4, 4 / 30, K, 1000.0, [], "", "detector-a", {"detect_ms": 99.0}))
    assert len(recording.drain_as_bytes()) > nothing  # detected, nothing found: the boxes are cleared
    assert viz.timings.take() == {"timings/detector/detect_ms": ([2, 4], [101.5, 99.0])}


def test_a_skipped_frame_keeps_the_last_tracked_boxes() -> None:
    """The tracker answers a frame the detector passed over with no boxes (`skipped`): the viewer leaves the last
    tracked boxes up instead of clearing them at every other frame; its latency sample is still kept."""
    parser = argparse.ArgumentParser()
    common_arguments(parser)
    viz = VizService(parser.parse_args(["--mode", "realtime"]))
    rr.init("semmap-test-viz-tracks", spawn=False)
    recording = rr.memory_recording()
    viz.rr, viz.timings, viz.rejected = rr, TimingColumns(), set()
    recording.drain_as_bytes()
    nothing = len(recording.drain_as_bytes())
    tracked = TrackedBox(7, "cup", (10.0, 10.0, 50.0, 60.0), 4, False)
    viz.on_tracks(Tracks("r", 2, 2 / 30, boxes=[tracked], timing_ms={"proposal": 0.5}))
    assert len(recording.drain_as_bytes()) > nothing
    viz.on_tracks(Tracks("r", 3, 3 / 30, skipped="stride", timing_ms={"proposal": 0.1}))
    assert len(recording.drain_as_bytes()) == nothing, "a skipped frame cleared the tracked boxes"
    viz.on_tracks(Tracks("r", 4, 4 / 30, timing_ms={"proposal": 0.2}))
    assert len(recording.drain_as_bytes()) > nothing  # detected, no tracklet in it: the boxes are cleared
    assert viz.timings.take() == {"timings/tracker/proposal": ([2, 3, 4], [0.5, 0.1, 0.2])}


def test_path_parts_redraw_only_what_changed_and_join_up() -> None:
    path = PathParts(part_frames=10)
    for f in range(25):
        path.set(f, np.array([f, 0.0, 0.0]))
    strips = path.take()
    assert sorted(strips) == [0, 1, 2]
    assert strips[0][:, 0].tolist() == list(range(11))  # frames 0-9, joined to part 1's first point
    assert strips[1][:, 0].tolist() == list(range(10, 21))
    assert strips[2][:, 0].tolist() == list(range(20, 25))
    path.set(25, np.array([25.0, 0.0, 0.0]))
    assert sorted(path.take()) == [2]  # a new frame: its part only
    path.set(12, np.array([12.0, 1.0, 0.0]))
    assert sorted(path.take()) == [1]
    path.set(13, np.array([13.0, 0.0005, 0.0]))  # re-sent, not moved (the backend's rolling refresh)
    assert path.take() == {}
    path.set(20, np.array([20.0, 1.0, 0.0]))  # a part's first point: the part before it ends there too
    assert sorted(path.take()) == [1, 2]
    path.reset({f: np.array([f, 0.0, 0.0]) for f in range(6)})
    strips = path.take()
    assert strips[0][:, 0].tolist() == list(range(6))
    assert strips[1].shape == (0, 3) and strips[2].shape == (0, 3)  # emptied parts are cleared
    assert path.take() == {}


def test_a_path_redraw_costs_the_same_late_in_a_long_run() -> None:
    """The odometry path was re-logged whole every 5th frame: an hour at 30 fps made each redraw ~100x a
    minute's, and the recording grew with the square of the run's length. A redraw now logs its part only."""
    parser = argparse.ArgumentParser()
    common_arguments(parser)
    viz = VizService(parser.parse_args(["--mode", "realtime"]))
    rr.init("semmap-test-viz-path", spawn=False)
    recording = rr.memory_recording()
    viz.rr, viz.correction, viz.up = rr, None, np.array([0.0, -1.0, 0.0])
    viz.odometry, viz.odometry_path = {}, PathParts()
    pose = np.eye(4)
    logged: dict[int, int] = {}
    for frame_id in range(6000):
        pose[0, 3] = frame_id * 0.01
        recording.drain_as_bytes()
        viz.on_odometry(OdometryPose("r", frame_id, frame_id / 30, pose.copy()))
        logged[frame_id] = len(recording.drain_as_bytes())
    early, late = logged[995], logged[5995]  # both redraw a part of ~1000 frames
    assert late < 1.5 * early, (early, late)
    assert logged[5995] < 0.5 * 6000 * 12  # far less than the whole path's 6000 points

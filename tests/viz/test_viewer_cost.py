"""What the viewer sends to Rerun per message, in real time where its CPU is taken from the detector
(semmap.services.viz.service): latency samples as one column per stage, nothing for a frame the detector passed
over (its last boxes stay up instead of blinking off)."""

from __future__ import annotations

import argparse

import rerun as rr

from semmap.core.messages import Detection, Detections, Intrinsics, TrackedBox, Tracks
from semmap.runtime.service import common_arguments
from semmap.services.viz.service import TimingColumns, VizService

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

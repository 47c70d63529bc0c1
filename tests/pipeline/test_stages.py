"""The pipeline's stage objects (semmap/runtime/pipeline.py): the per-frame policy both drivers run.

Whole runs of the stages are tested through the drivers (tests/pipeline/test_closed_loop.py,
tests/associator/test_closed_loop_analytic.py); these pin the policy each stage holds.
"""

from __future__ import annotations

import numpy as np

from semmap.algorithms.associator.mapper import MapperParams, MapperStep
from semmap.algorithms.tracker.iou_tracker import TrackerParams
from semmap.core.messages import Detection, Detections, Intrinsics, Observations, OdometryPose
from semmap.runtime.pipeline import AssociatorStage, BackendStage, TrackerStage, combined

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
ROBOT = "robot1"


def detections(frame: int, stamp: float, boxes: list[Detection], skipped: str = "") -> Detections:
    return Detections(ROBOT, frame, stamp, K, 0.001, boxes, skipped)


def odometry(frame: int, x: float = 0.0) -> OdometryPose:
    pose = np.eye(4)
    pose[0, 3] = x
    return OdometryPose(ROBOT, frame, frame / 30.0, pose, sigma_translation=0.01, sigma_rotation=0.01)


def test_a_skipped_frame_only_ages_the_tracklets() -> None:
    stage = TrackerStage(TrackerParams(min_length=2, max_age_s=0.5))
    cup = Detection((100.0, 100.0, 140.0, 140.0), "cup", 0.9, 1.0)
    for f in range(3):
        out = stage.step(detections(f, f / 30.0, [cup]))
    assert [c.track_id for c in out.candidates] == [0]
    out = stage.step(detections(3, -1.0, [], "dropped"))  # no stamp: nothing ages
    assert (out.candidates, out.ended, out.boxes) == ([], [], []) and stage.tracker.active_count == 1
    out = stage.step(detections(30, 1.0, [], "stride"))  # 0.93 s after its last detection: it ends
    assert out.ended == [0] and out.boxes == [] and stage.tracker.active_count == 0


def test_the_associator_holds_a_frame_until_the_backend_answers_it() -> None:
    associator = AssociatorStage(MapperParams(), refine_every_n_frames=2, await_backend=True)
    backend = BackendStage()
    assert not associator.pose_known_or_lost(0, lockstep=True)
    for f in (0, 1):
        pose = odometry(f, 0.01 * f)
        associator.odometry(f, pose.pose)
        assert associator.pose_known_or_lost(f, lockstep=True)
        frame = detections(f, pose.stamp, [])
        step = associator.process(f, pose.stamp, [], [], [])
        assert associator.take_merges(step) == []
        assert associator.hold(frame, step) and associator.awaiting is not None
        answer = backend.step(pose, Observations(ROBOT, f, pose.stamp, [], []), None)
        assert answer.delta.frame_ids.tolist()[-1:] == [f]
        held = associator.corrected(answer.message(ROBOT, f + 1, f))
        assert held is not None and held[0] is frame and associator.awaiting is None
        assert f in associator.poses.corrected
        done, refine_ms = associator.complete(f, pose.stamp, held[1])
        assert refine_ms == 0.0  # no landmark: nothing to refine
    assert backend.graph.num_frames == 2


def test_real_time_goes_on_when_a_later_pose_came() -> None:
    associator = AssociatorStage(await_backend=False)
    associator.odometry(5, np.eye(4))
    assert not associator.pose_known_or_lost(4, lockstep=True)  # lockstep: frame 4's pose will come
    assert associator.pose_known_or_lost(4, lockstep=False)  # real time: it was dropped upstream
    assert not associator.pose_known_or_lost(6, lockstep=False)
    assert not associator.hold(detections(5, 0.2, []), MapperStep())  # nothing waits for the backend


def test_merges_a_refine_found_go_out_with_the_next_frame() -> None:
    associator = AssociatorStage()
    associator.pending_merges = [(5, 2)]  # found by a refine after frame i's observations left
    assert associator.take_merges(MapperStep(merges=[(7, 3)])) == [(5, 2), (7, 3)]
    assert associator.take_merges(MapperStep()) == []


def test_combined_steps_keep_removals_removed() -> None:
    a = MapperStep(removed=[4], merges=[(4, 1)], timing_ms={"proposal": 1.0})
    b = MapperStep(removed=[4, 6], merges=[(6, 2)], timing_ms={"proposal": 2.0, "refine": 3.0})
    out = combined(a, b)
    assert out.removed == [4, 6] and out.merges == [(4, 1), (6, 2)]
    assert out.timing_ms == {"proposal": 3.0, "refine": 3.0}

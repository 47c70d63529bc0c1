"""The pipeline's stage objects (semmap/runtime/pipeline/stages.py): the per-frame policy both drivers run.

Whole runs of the stages are tested through the drivers (tests/pipeline/test_closed_loop.py,
tests/associator/test_closed_loop_analytic.py); these pin the policy each stage holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from semmap.algorithms.associator.mapper import MapperParams, MapperStep
from semmap.algorithms.tracker.iou_tracker import TrackerParams
from semmap.core.messages import Detection, Detections, Intrinsics, Observations, OdometryPose
from semmap.runtime.pipeline.stages import AssociatorStage, BackendStage, TrackerStage, combined

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


def test_merges_still_to_go_out_survive_a_restart() -> None:
    """A refine's merges leave with the next frame's observations; saved before that, they must be in the
    associator's state, or the backend never joins the two landmarks."""
    import msgpack

    associator = AssociatorStage()
    associator.pending_merges = [(5, 2)]
    associator.odometry(3, odometry(3, 0.5).pose)
    state = msgpack.unpackb(msgpack.packb(associator.to_state(), use_bin_type=True), raw=False, strict_map_key=False)
    restarted = AssociatorStage()
    restarted.restore(state)
    assert restarted.take_merges(MapperStep(merges=[(7, 3)])) == [(5, 2), (7, 3)]
    np.testing.assert_array_equal(restarted.poses(3), associator.poses(3))


def test_combined_steps_keep_removals_removed() -> None:
    a = MapperStep(removed=[4], merges=[(4, 1)], timing_ms={"proposal": 1.0}, moved_why={9: "kept"},
                   kept_despite_motion=[9])  # fmt: skip
    b = MapperStep(removed=[4, 6], merges=[(6, 2)], timing_ms={"proposal": 2.0, "refine": 3.0}, moved=[6],
                   moved_why={6: "left"})  # fmt: skip
    out = combined(a, b)
    assert out.removed == [4, 6] and out.merges == [(4, 1), (6, 2)]
    assert out.timing_ms == {"proposal": 3.0, "refine": 3.0}
    assert out.moved == [6] and out.kept_despite_motion == [9] and out.moved_why == {9: "kept", 6: "left"}


def test_a_backend_restored_from_its_journal_sends_what_the_live_one_sends() -> None:
    """After a crash the backend replays its journalled frames; its corrections from then on must be the
    uninterrupted backend's, delta for delta: the publisher's memory (what it sent per frame, where the rolling
    refresh stands) is state too. A fresh one sent everything once and refreshed other frames than the live
    one, which left poses in the associator's book the clean run never had (sub-millimetre, enough to move a
    landmark)."""
    from tests.backend.backend_sim import FPS, Scene, drifting, landmarks_in_view, observe, square_path

    rng = np.random.default_rng(4)
    gt = square_path(120, side=3.0)  # a closed loop: the first corner is seen again at the end
    scene = Scene(gt, drifting(gt, seed=4), landmarks_in_view(gt, 16, rng))
    observe(scene, rng, every=2)
    frames = [(OdometryPose(ROBOT, i, i / FPS, pose, keyframe=i % 5 == 0, sigma_translation=scene.sigmas[0],
                            sigma_rotation=scene.sigmas[1]),
               Observations(ROBOT, i, i / FPS, scene.observations.get(i, []), []))
              for i, pose in enumerate(scene.odometry)]
    live = BackendStage()
    sent = [live.step(pose, obs, None).delta for pose, obs in frames]
    assert sum(len(d.frame_ids) for d in sent[60:]) > 60 * 34  # old frames move: more than new + refresh go out
    for crash in (40, 90):
        restored = BackendStage()
        replayed = [restored.restore(pose, obs, None).delta for pose, obs in frames[:crash]]
        for a, b in zip(replayed, sent[:crash], strict=True):  # what went out before the crash, rebuilt
            assert a.full == b.full and all(np.array_equal(x, y) for x, y in zip(a.arrays(), b.arrays(), strict=True))
        for i, ((pose, obs), ref) in enumerate(zip(frames[crash:], sent[crash:], strict=True), start=crash):
            delta = restored.step(pose, obs, None).delta
            assert delta.full == ref.full, f"frame {i}: a full message where the live backend sent a delta"
            for x, y in zip(delta.arrays(), ref.arrays(), strict=True):
                np.testing.assert_array_equal(x, y)


def test_the_tracker_stage_names_each_frames_dynamic_objects_and_keeps_them_over_a_restart() -> None:
    """People by class, a tracklet the associator saw moving by that; a skipped frame repeats the last detected
    frame's boxes of tracklets still alive; ended tracklets are forgotten; state() / restore() keep it all (a
    restarted tracker masks the same depth for the `rgbd` front end as one that never stopped)."""
    import msgpack

    from semmap.core.messages import DepthPatch

    depth = DepthPatch(300, 50, 2, np.full((175, 40), 2000, dtype=np.uint16))
    person = Detection((300.0, 50.0, 380.0, 400.0), "person", 0.9, 2.0, depth)
    cup = Detection((100.0, 100.0, 140.0, 140.0), "cup", 0.9, 1.0)
    stage = TrackerStage(TrackerParams(min_length=2, max_age_s=0.5), dynamic_classes={"person"})
    out = stage.step(detections(0, 0.0, [person, cup]))
    boxes = stage.dynamic_objects(detections(0, 0.0, [person, cup]), out)
    assert [(b.class_name, b.reason) for b in boxes] == [("person", "class")]
    assert boxes[0].depth_min_m == boxes[0].depth_max_m == 2.0  # the person's depth range, for a `range` mask
    cup_track = next(b.track_id for b in out.boxes if b.class_name == "cup")
    stage.saw_moving([cup_track])
    frame1 = detections(1, 1 / 30, [person, cup])
    boxes = stage.dynamic_objects(frame1, stage.step(frame1))
    assert sorted((b.class_name, b.reason) for b in boxes) == [("cup", "moving"), ("person", "class")]
    restored = TrackerStage(TrackerParams(min_length=2, max_age_s=0.5), dynamic_classes={"person"})
    restored.restore(msgpack.unpackb(msgpack.packb(stage.state())))
    skipped = detections(2, 2 / 30, [], "stride")
    for s in (stage, restored):
        again = s.dynamic_objects(skipped, s.step(skipped))
        assert [(b.track_id, b.reason) for b in again] == [(b.track_id, b.reason) for b in boxes]
    boxes = again
    held_at_2 = next(b for b in boxes if b.class_name == "person").box
    missed = detections(3, 3 / 30, [cup])  # the detector misses the person once: its last box stays dynamic,
    for s in (stage, restored):  # grown by how far the person may have walked since frame 1 (held_dynamic_box)
        again = s.dynamic_objects(missed, s.step(missed))
        assert sorted((b.class_name, b.reason) for b in again) == [("cup", "moving"), ("person", "class")]
        held = next(b for b in again if b.class_name == "person").box
        assert held[0] < held_at_2[0] < person.box[0] and held[2] > held_at_2[2] > person.box[2]
        assert held[0] == pytest.approx(person.box[0] - K.fx * 1.5 * (2 / 30) / 2.0)
    late = detections(40, 40 / 30, [], "stride")  # both tracklets ended: nothing dynamic, nothing remembered
    for s in (stage, restored):
        assert s.dynamic_objects(late, s.step(late)) == [] and s.moving == set()

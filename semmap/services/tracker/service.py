"""Tracker service: IOU tracklets from detections; tracklets of 5+ measurements become landmark candidates.

It also publishes, for every frame, the frame's dynamic objects (`semmap/v1/<robot>/dynamic`): the boxes of
tracklets of a dynamic class (`associator.dynamic_classes`) and of tracklets the associator saw moving (its
map updates' `moving_tracks`). Why here and not in the associator: the associator waits for each frame's
odometry, and the odometry (the built-in `rgbd` front end) waits in lockstep for the frame's dynamic boxes;
the tracker depends only on detections, so the wait cannot close a cycle.

Detections may arrive out of order (several detector replicas) or twice (a replica set that changed): they
are re-ordered by frame id and duplicates dropped, so the tracker sees each frame once, in order.

Every handled frame is journalled (`DIR/tracker.sqlite`: its output and the tracker's state after it). A tracker
restarted with --resume continues every tracklet where it was: a restart that began new tracklets would cut each
object's history in two (the associator keeps the old candidate, never ended, and must validate a new one from
scratch), which delays, moves or drops landmarks.
"""

from __future__ import annotations

import time

import msgpack

from semmap.algorithms.tracker.iou_tracker import IouTracker
from semmap.core.messages import Detections, DynamicObjects, MapUpdate, Tracks
from semmap.runtime.pipeline.stages import TrackerStage
from semmap.runtime.transport.service import REPLAY_FRAMES, service_main
from semmap.runtime.transport.stage_service import StageService

TRACK_ID_BLOCK = 10_000_000


class TrackerService(StageService):
    """Turns per-frame detections into tracklets and landmark candidates (see module docstring)."""

    name = "tracker"
    yields_to_front_end = True  # (real time: see StageService.yield_to_front_end)
    journal_file = "tracker.sqlite"  # per frame: its tracks and the tracker's state after it
    journal_keeps = REPLAY_FRAMES  # a restart reads the newest rows only
    lockstep_max_pending = 256  # (several detector replicas: frames come out of order)

    def setup_stage(self) -> None:
        self.params = self.config.tracker
        # track ids must never repeat within a run (the associator keys candidates by them): without a journal to
        # continue from, a restarted tracker starts a clock-based block of ids
        first_id = int(time.time()) * TRACK_ID_BLOCK if self.resume and self.out_dir is None else 0
        self.stage = TrackerStage(self.params, first_track_id=first_id,
                                  dynamic_classes=self.config.associator.dynamic_classes)
        self._last_detected_stamp: float | None = None  # for the run's detection cadence (`detect_interval_ms`)
        self.open_outputs()

    @property
    def tracker(self) -> IouTracker:
        return self.stage.tracker

    def on_map_update(self, update: MapUpdate) -> None:
        self.stage.saw_moving(update.moving_tracks)

    def restore(self) -> None:
        """Continue after a crash: the tracker's state after the last journalled frame; the outputs of the last
        few frames are remembered, so a frame sent again (its output may have died with the old process) is
        answered as before."""
        assert self.journal is not None
        rows = self.journal.last(1)
        if not rows:
            return
        self.remember_newest(self.out["tracks"], Tracks.decode)
        frame_id, _, state, _ = rows[-1]
        self.stage.restore(msgpack.unpackb(state))
        self.resume_after(frame_id)
        self.log.info("resumed after frame %d (%d tracklets)", frame_id, self.tracker.active_count)

    def handle(self, det: Detections) -> None:
        if not det.skipped:  # frames come here in order, from every detector replica: the run's real cadence
            if self._last_detected_stamp is not None and det.stamp > self._last_detected_stamp:
                self.metrics.time_ms("detect_interval_ms", (det.stamp - self._last_detected_stamp) * 1e3)
            self._last_detected_stamp = det.stamp
        with self.metrics.timer("proposal_ms") as timer:
            out = self.stage.step(det)
        # the frame's dynamic objects (see module docstring and `TrackerStage.dynamic_objects`)
        boxes = self.stage.dynamic_objects(det, out)
        self.metrics.count("dynamic_boxes", len(boxes))
        self.metrics.count("frames")
        self.metrics.count("candidates_proposed", sum(1 for c in out.candidates if c.first))
        tracks = Tracks(self.robot, det.frame_id, det.stamp, out.candidates, out.ended, out.boxes, det.skipped,
                        {"proposal": timer.ms, **det.timing_ms}, det.frame_sent_at)
        dynamic = DynamicObjects(self.robot, det.frame_id, det.stamp, boxes, det.skipped)
        self.complete_frame(det.frame_id, [(self.out["dynamic"], dynamic), (self.out["tracks"], tracks)],
                            (tracks.encode(), msgpack.packb(self.stage.state())))


def main(argv: list[str] | None = None) -> int:
    return service_main(TrackerService, argv)

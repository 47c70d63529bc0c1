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

from semmap.algorithms.tracker.iou_tracker import IouTracker, TrackerOutput
from semmap.core.journal import FrameJournal
from semmap.core.messages import Detections, DynamicObjects, MapUpdate, Tracks
from semmap.core.reorder import FrameReorderBuffer
from semmap.runtime.pipeline import TrackerStage
from semmap.runtime.service import REPLAY_FRAMES, Service, service_main

TRACK_ID_BLOCK = 10_000_000
JOURNAL_TRIM_EVERY = 10  # frames: the journal keeps at most this many rows more than a restart reads


class TrackerService(Service):
    """Turns per-frame detections into tracklets and landmark candidates (see module docstring)."""

    name = "tracker"

    def setup(self) -> None:
        self.params = self.config.tracker
        # track ids must never repeat within a run (the associator keys candidates by them): without a journal to
        # continue from, a restarted tracker starts a clock-based block of ids
        first_id = int(time.time()) * TRACK_ID_BLOCK if self.resume and self.out_dir is None else 0
        # the per-frame policy (runtime/pipeline.py)
        self.stage = TrackerStage(self.params, first_track_id=first_id,
                                  dynamic_classes=self.config.associator.dynamic_classes)
        self.pub = self.publisher(self.bus.keys.tracks)
        self.dynamic_pub = self.publisher(self.bus.keys.dynamic)
        self.reorder: FrameReorderBuffer[Detections] = FrameReorderBuffer()
        self.journal = FrameJournal(self.out_dir / "tracker.sqlite") if self.out_dir is not None else None
        if self.journal is not None:
            if self.resume:
                self._restore()
            else:
                self.journal.clear()
        self.listen(self.bus.keys.detections, Detections, self.on_detections)
        self.listen(self.bus.keys.map_updates, MapUpdate, self.on_map_update)

    @property
    def tracker(self) -> IouTracker:
        return self.stage.tracker

    def on_map_update(self, update: MapUpdate) -> None:
        self.stage.saw_moving(update.moving_tracks)

    def _restore(self) -> None:
        """Continue after a crash: the tracker's state after the last journalled frame; the outputs of the last
        few frames are remembered, so a frame sent again (its output may have died with the old process) is
        answered as before."""
        assert self.journal is not None
        rows = self.journal.last(REPLAY_FRAMES)
        if not rows:
            return
        for frame_id, tracks, _, _ in rows:
            self.remember(self.pub, Tracks.decode(tracks), frame_id)
        frame_id, _, state, _ = rows[-1]
        self.stage.restore(msgpack.unpackb(state))
        self.last_frame_id = frame_id
        self.reorder.mark_done(frame_id)
        self.log.info("resumed after frame %d (%d tracklets)", frame_id, self.tracker.active_count)

    def on_detections(self, message: Detections) -> None:
        if not self.reorder.push(message.frame_id, message):
            self.metrics.count("duplicates_dropped")
            self.replay(message.frame_id)  # a resent frame: answer it again (a consumer may have lost it)
            return
        self._release()

    def on_frame_unreadable(self, frame_id: int) -> None:
        self.reorder.skip(frame_id)
        self._release()

    def _release(self) -> None:
        for det in self.reorder.pop_ready():
            self._process(det)

    def _process(self, det: Detections) -> None:
        with self.metrics.timer("proposal_ms") as timer:
            out = self.stage.step(det)
        candidates, ended, boxes = out.candidates, out.ended, out.boxes
        self._publish_dynamic(det, out)
        self.metrics.count("frames")
        self.metrics.count("candidates_proposed", sum(1 for c in candidates if c.first))
        tracks = Tracks(self.robot, det.frame_id, det.stamp, candidates, ended, boxes, det.skipped,
                        {"proposal": timer.ms, **det.timing_ms}, det.frame_sent_at)
        self.emit(self.pub, tracks, det.frame_id)
        if self.journal is not None:
            with self.metrics.timer("journal_ms"):
                self.journal.append(det.frame_id, tracks.encode(), msgpack.packb(self.stage.state()))
                if det.frame_id % JOURNAL_TRIM_EVERY == 0:  # only the newest rows are ever read back
                    self.journal.trim(det.frame_id - REPLAY_FRAMES)
        self.report_progress(det.frame_id)


    def _publish_dynamic(self, det: Detections, out: TrackerOutput) -> None:
        """This frame's dynamic objects (see module docstring and `TrackerStage.dynamic_objects`)."""
        boxes = self.stage.dynamic_objects(det, out)
        self.metrics.count("dynamic_boxes", len(boxes))
        self.emit(self.dynamic_pub, DynamicObjects(self.robot, det.frame_id, det.stamp, boxes, det.skipped),
                  det.frame_id)


def main(argv: list[str] | None = None) -> int:
    return service_main(TrackerService, argv)

"""Tracker service: IOU tracklets from detections; tracklets of 5+ measurements become landmark candidates.

Detections may arrive out of order (several detector replicas) or twice (a replica set that changed): they
are re-ordered by frame id and duplicates dropped, so the tracker sees each frame once, in order.
"""

from __future__ import annotations

import time

from semmap.messages import Detections, Tracks
from semmap.outputs import atomic_write_text
from semmap.reorder import FrameReorderBuffer
from semmap.service import Service, service_main
from services.tracker.iou_tracker import IouTracker, TrackerParams

TRACK_ID_BLOCK = 10_000_000


class TrackerService(Service):
    """Turns per-frame detections into tracklets and landmark candidates (see module docstring)."""

    name = "tracker"

    def setup(self) -> None:
        self.tracker = IouTracker(TrackerParams(**self.config["tracker"]), first_track_id=self._first_track_id())
        self.pub = self.publisher(self.bus.keys.tracks)
        self.reorder: FrameReorderBuffer[Detections] = FrameReorderBuffer()
        self.listen(self.bus.keys.detections, Detections, self.on_detections)

    def _first_track_id(self) -> int:
        """Track ids must never repeat within a run: the associator keys candidates by them. A restarted tracker
        starts a new block of ids (one per restart, counted in DIR/tracker.epoch)."""
        path = self.out_dir / "tracker.epoch" if self.out_dir is not None else None
        if not self.resume:
            epoch = 0
        elif path is not None:
            epoch = (int(path.read_text()) if path.is_file() else 0) + 1
        else:
            epoch = int(time.time())  # no run directory: a clock-based block
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(path, str(epoch))
        return epoch * TRACK_ID_BLOCK

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
            if det.skipped:
                # tracklets can end on a skipped frame too: the associator must hear of it
                ended = self.tracker.skip(det.frame_id, det.stamp).ended if det.stamp >= 0 else []
                candidates, boxes = [], []
            else:
                out = self.tracker.update(det.frame_id, det.stamp, det.detections, det.intrinsics, det.depth_scale)
                candidates, ended, boxes = out.candidates, out.ended, out.boxes
        self.metrics.count("frames")
        self.metrics.count("candidates_proposed", sum(1 for c in candidates if c.first))
        self.emit(self.pub, Tracks(self.robot, det.frame_id, det.stamp, candidates, ended, boxes, det.skipped,
                                   {"proposal": timer.ms, **det.timing_ms}, det.frame_sent_at), det.frame_id)
        self.report_progress(det.frame_id)


def main(argv: list[str] | None = None) -> int:
    return service_main(TrackerService, argv)

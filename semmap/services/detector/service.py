"""Detector service: detections for every frame on `semmap/v1/<robot>/detections`.

Scaling out: each replica holds a liveliness token; the live replicas, sorted by name, share the stream by rank
in blocks of `every_n_frames` frames (block frame_id // every_n, owned by rank block % n: `owner`, with the rest
of the turn logic in semmap/algorithms/detector/turns.py), so N replicas
detect each frame once and, with a cadence, take turns (every 2nd frame, 2 replicas: frames 0, 2, 4, 6 go to
replicas 0, 1, 0, 1, each detected once in its turn, none left to a replica that never detects). Every frame
gets exactly one `Detections` message, `skipped` ones too (not this frame's turn under `every_n_frames`, dropped
under real-time overload), so consumers never wait for a frame that will not come; they re-order by frame id and
drop duplicates.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import zenoh

from semmap.algorithms.detector import create_detector, needs_model, resolve_kind
from semmap.algorithms.detector.onnx_detector import DetectedBox
from semmap.algorithms.detector.turns import ReplicaTurns, owner
from semmap.core.keys import Keys
from semmap.core.messages import Control, Detections, Frame
from semmap.runtime.models.detector_choice import describe_plan, load_detector_model, resolve_setup, setup_plan
from semmap.runtime.pipeline.stages import depth_detections
from semmap.runtime.transport.service import Service, service_main

MEMBERSHIP_SETTLE_S = 0.5
EOS_GRACE_S = 2.0  # real time: how long after the end of the stream a late frame may still arrive


class DetectorService(Service):
    """Detects COCO objects in frames (see module docstring)."""

    name = "detector"

    def setup(self) -> None:
        cfg = self.config.detector
        self.cfg = cfg
        if not self.lockstep and cfg.realtime_niceness > 0:
            # real time: the front end must pose every frame (a SLAM fed every 4th frame of a hand-held camera
            # loses track), so the detector takes the CPU the other services leave, not a share of theirs: the
            # kernel gives a core to them first whenever both want one
            try:
                os.nice(int(cfg.realtime_niceness))
                self.log.info("real time: detector at niceness %d (the front end and the other services first)",
                              os.getpriority(os.PRIO_PROCESS, 0))
            except OSError as exc:  # (a container may refuse it: then the shares stay as they are)
                self.log.warning("real time: could not lower the detector's priority: %s", exc)
        # (`semmap run` resolves `auto` for its dataset; a detector started by hand sees a camera)
        self.kind = resolve_kind(cfg.kind, synthetic=False)
        self.every_n = cfg.every_n_frames or 1
        self.stride = cfg.depth_patch_stride
        model: Path | bytes | None = None
        self.precision = cfg.precision
        if needs_model(self.kind) and cfg.model:
            model = Path(cfg.model)
        elif needs_model(self.kind):  # the packaged YOLOv5s: this machine's measured choice
            setup = resolve_setup(cfg.precision, cfg.threads, cfg.input_size, realtime=not self.lockstep)
            self.precision = setup.precision
            model = load_detector_model(setup)
            cfg = cfg.model_copy(update={"threads": setup.threads})
            self.log.info("%s model %s (%s, %s%s)", self.kind, setup.label(), setup.origin,
                          "auto" if self.cfg.precision == "auto" else "set",
                          "" if isinstance(model, Path) else ", resized in memory")
            if not self.lockstep and self.cfg.every_n_frames == 0:
                speed = float(getattr(self.config.run, "speed", 1.0) or 1.0)
                plan, source = setup_plan(setup, 30.0 * speed, self.config.odometry.mode)
                if plan is not None:
                    self.every_n = plan.every_n
                    self.log.info("frame budget: %s", describe_plan(plan, source))
        self.detector = create_detector(self.kind, cfg, model)
        unknown = getattr(self.detector, "unknown_confidence_classes", [])
        if unknown:
            self.log.warning("detector.class_confidence names classes this model does not detect: %s",
                             ", ".join(unknown))
        if model is not None:
            self.log.info("%s detector on %s, every %d frame(s)", self.kind,
                          ", ".join(getattr(self.detector, "providers", [])), self.every_n)
        self.open_outputs()
        # replica membership from liveliness tokens
        self._members: set[str] = {self.instance}
        self._members_lock = threading.Lock()
        self._members_changed = time.monotonic()
        liveliness = self.bus.session.liveliness()
        run = self.bus.trust.run_id
        self._token = liveliness.declare_token(self.bus.keys.detector_replica(self.instance, run))
        self._replica_prefix = self.bus.keys.detector_replicas(run)[:-1]  # a replica of this run: prefix + name
        self._foreign_tokens = 0
        self._live_sub = liveliness.declare_subscriber(
            self.bus.keys.detector_replicas_all, self._on_liveliness, history=True
        )
        self.last_mine = -1
        # frames the player could not read never come: not "dropped" here (the control message that says so may
        # arrive after the next frame, so a gap already counted as dropped is taken back)
        self._unreadable: set[int] = set()
        self._dropped_ids: set[int] = set()
        self.turns = ReplicaTurns(self.every_n, self.lockstep)  # (which frames of our share are detected)
        self._last_detected_stamp: float | None = None  # for the detection cadence (video time between detections)
        self._last_frame: Frame | None = None
        self._eos_since: float | None = None
        # only our share reaches the queue: another replica's frame would take the place of the newest of ours
        self.subscribe()
        deadline = time.monotonic() + 5.0
        while time.monotonic() - self._members_changed < MEMBERSHIP_SETTLE_S and time.monotonic() < deadline:
            time.sleep(0.05)
        self.log.info("replica %d of %d", *self._rank())

    def listen_options(self, topic: str) -> dict:
        return {"realtime_capacity": max(1, int(self.cfg.queue)), "wanted": self._ours} if topic == "frames" else {}

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        name = Keys.instance_of(key)
        if key != self._replica_prefix + name:  # another run's replica, or a forged token: not one of ours
            with self._members_lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._foreign_tokens += 1
                    self.metrics.counters["rejected_foreign_replica"] = self._foreign_tokens
            return
        with self._members_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._members.add(name)
            else:
                self._members.discard(name)
            self._members_changed = time.monotonic()

    def _rank(self) -> tuple[int, int]:
        with self._members_lock:
            members = sorted(self._members | {self.instance})
        return members.index(self.instance), len(members)

    def _ours(self, frame_id: int) -> bool:
        """Whether `frame_id` is in this replica's share (as the live replicas stand now)."""
        rank, n = self._rank()
        return owner(frame_id, self.every_n, n) == rank

    def _detect(self, frame: Frame) -> list[DetectedBox]:
        return self.detector.detect_frame(frame)

    def on_frame(self, frame: Frame) -> None:
        if not self._ours(frame.frame_id):  # (the replicas changed since it arrived)
            return
        started = time.time()
        # frames of our share that never reached us were left behind upstream of this handler (bounded queue)
        skips = self.turns.skips(frame.frame_id)
        if self.last_mine >= 0:
            self._answer_missed(frame, self._owed(frame.frame_id - 1), not skips)
        self.last_mine = frame.frame_id
        self._last_frame = frame
        if skips:
            self._publish_skip(frame, frame.frame_id, "stride")
            return
        self.turns.last_detected = frame.frame_id
        with self.metrics.timer("detect_ms") as t_detect:
            try:
                boxes = self._detect(frame)
                depth = frame.depth()
            except ValueError as exc:
                self.metrics.count("frames_bad")
                self.log.warning("frame %d not detected: %s", frame.frame_id, exc)
                self._publish_skip(frame, frame.frame_id, "bad_frame")
                return
        with self.metrics.timer("depth_ms"):
            detections = depth_detections(boxes, depth, frame.depth_scale, self.stride, self.cfg.depth_min_m,
                                          self.cfg.depth_max_m)
        self.metrics.count("frames_detected")
        if self._last_detected_stamp is not None and frame.stamp > self._last_detected_stamp:
            self.metrics.time_ms("detect_interval_ms", (frame.stamp - self._last_detected_stamp) * 1e3)
        self._last_detected_stamp = frame.stamp
        self.metrics.count("detections", len(detections))
        self.metrics.count("depth_gated", len(boxes) - len(detections))
        queue_ms = max(0.0, (started - frame.sent_at) * 1e3) if frame.sent_at else 0.0
        self.metrics.time_ms("queue_ms", queue_ms)
        self.out["detections"].put(
            Detections(
                self.robot,
                frame.frame_id,
                frame.stamp,
                frame.intrinsics,
                frame.depth_scale,
                detections,
                "",
                self.instance,
                {"detect_ms": t_detect.ms, "queue_ms": queue_ms},
                frame.sent_at,
            )
        )
        self.report_progress(frame.frame_id)

    def on_frame_unreadable(self, frame_id: int) -> None:
        self._unreadable.add(frame_id)
        if frame_id in self._dropped_ids:
            self._dropped_ids.discard(frame_id)
            self.metrics.counters["frames_dropped"] -= 1
        self._unreadable = {f for f in self._unreadable if f > frame_id - 1000}  # (bounded)
        self._dropped_ids = {f for f in self._dropped_ids if f > frame_id - 1000}

    def _answer_missed(self, frame: Frame, missed: list[int], detects_frame: bool = False) -> None:
        """Answer frames of our share that never reached the handler (`ReplicaTurns.passed_over`: `dropped` where
        a detection was lost, `stride` where the cadence would have skipped it or `frame` is detected instead)."""
        for frame_id, reason in self.turns.passed_over(frame.frame_id, missed, detects_frame):
            if reason == "dropped":
                self._dropped_ids.add(frame_id)
            self._publish_skip(frame, frame_id, reason)

    def _publish_skip(self, frame: Frame, frame_id: int, reason: str) -> None:
        self.metrics.count(f"frames_{reason}")
        stamp = frame.stamp if frame_id == frame.frame_id else -1.0
        self.out["detections"].put(
            Detections(
                self.robot,
                frame_id,
                stamp,
                frame.intrinsics,
                frame.depth_scale,
                [],
                reason,
                self.instance,
                {},
                frame.sent_at if frame_id == frame.frame_id else 0.0,
            )
        )
        self.report_progress(frame_id)

    def _owed(self, last_frame_id: int) -> list[int]:
        """Frames of our share up to `last_frame_id` that we have not answered yet."""
        rank, n = self._rank()
        return [f for f in range(self.last_mine + 1, last_frame_id + 1)
                if owner(f, self.every_n, n) == rank and f not in self._unreadable]

    def on_end_of_stream(self, control: Control) -> None:
        """Finish once our share is answered; frames still missing after a grace period were dropped."""
        if self.finished:
            return
        if not self._owed(control.last_frame_id):
            self.finish()
        elif self._eos_since is None:
            self._eos_since = time.monotonic()

    def tick(self) -> None:
        if self.end_of_stream is None or self.finished or self._eos_since is None:
            return
        if time.monotonic() - self._eos_since > EOS_GRACE_S and len(self.inbox) == 0:
            if self._last_frame is not None:
                self._answer_missed(self._last_frame, self._owed(self.end_of_stream.last_frame_id))
            self.finish()

    def teardown(self) -> None:
        self._live_sub.undeclare()
        self._token.undeclare()


def main(argv: list[str] | None = None) -> int:
    return service_main(DetectorService, argv)

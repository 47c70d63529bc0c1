"""Odometry front-end service: one `OdometryPose` per frame on `semmap/v1/<robot>/odometry`.

It stands in for an external SLAM; a real one publishes the same messages on the same key instead.

A front end that leaves out dynamic objects (`rgbd`) gets each frame's boxes from the tracker
(`semmap/v1/<robot>/dynamic`). Lockstep (with `--await-dynamic`, which `semmap run` passes when a tracker
runs): a frame waits for its own boxes, so a replay is deterministic; the tracker depends only on the
detector, never on the odometry, so the wait closes no cycle (the player waits for every service's progress,
the odometry's included). Real time: the newest boxes at hand, never a wait, late ones included (the tracker
yields the CPU to the front end and often answers after its frame was posed), each seen by the motion test at its
own frame's pose. An earlier frame's boxes mask as they are: grown by how far their people may have walked, they
blanked 35-50 % of Bonn crowd's images and ORB-SLAM3 lost track of up to 181 frames.
"""

from __future__ import annotations

import argparse
import time
from collections import deque

import msgpack
import numpy as np

from semmap.algorithms.evaluation import write_json_atomic
from semmap.algorithms.odometry.frontends import FrontEnd, OdometryInput, frame_offset, make_frontend
from semmap.core.messages import DynamicObjects, Frame, OdometryPose
from semmap.core.outputs import REPAIR_REPORT, SLAM_REFINED_TRAJECTORY, SLAM_TRAJECTORY
from semmap.datasets.trajectory_io import write_tum
from semmap.runtime.transport.service import service_main
from semmap.runtime.transport.stage_service import StageService

# real time: more frames than this waiting means the front end is behind the video (its checks wait, or thin out to
# every n-th step: odometry.repair_behind_check_every; its SLAM tracks every frame)
BEHIND_FRAMES = 2
DYNAMIC_KEPT = 64  # frames of dynamic objects kept (real time: boxes may run ahead of or behind the frames)
# lockstep: frames waiting for their dynamic objects (or an external SLAM's pose), oldest first; beyond this many the
# oldest is estimated without them (counted): a camera that does not wait for semmap (`semmap run external`) sends
# frames faster than the detector answers them, and each waiting frame holds its decoded images (~1.5 MB at VGA)
WAITING_KEPT = 64


class OdometryService(StageService):
    """Publishes camera poses for every frame (see module docstring)."""

    name = "odometry"
    journal_file = "odometry.sqlite"  # per frame: its pose and the front end's state after it
    # frames come in order; in real time the oldest waiting are dropped (a frame never waits for a missing one)
    reorders = False
    duplicates_counter = "frames_repeated"

    def setup_stage(self) -> None:
        cfg = self.config.odometry
        self.mode: str = cfg.mode
        self.frontend: FrontEnd = make_frontend(self.mode, cfg)
        self.to_session = np.linalg.inv(frame_offset(cfg.frame_offset))
        self.keyframe_every = cfg.keyframe_every
        self.trajectory: list[tuple[float, object]] = []
        self.open_outputs()
        self.dynamic: dict[int, DynamicObjects] = {}  # recent frames' dynamic objects by frame id
        self.dynamic_seen_upto = -1  # real time: the newest frame whose dynamic objects the front end has seen
        self.await_dynamic = self.frontend.uses_dynamic and self.lockstep and bool(self.args.await_dynamic)
        self.dynamic_wait_s = cfg.dynamic_wait_s
        # lockstep: frames waiting for their dynamic objects, oldest first, with when each came
        self.waiting: deque[tuple[Frame, float]] = deque()
        # an external SLAM's own poses to check (`external`): lockstep waits for each frame's, as for its boxes
        self.slam: dict[int, OdometryPose] = {}
        self.await_slam = self.frontend.needs_slam and self.lockstep

    @property
    def uses_dynamic(self) -> bool:
        """The front end leaves dynamic objects out: the dynamic port (semmap/core/dataflow.py) is wired."""
        return self.frontend.uses_dynamic

    @property
    def needs_slam(self) -> bool:
        """The front end checks an external SLAM's poses: the slam port is wired."""
        return self.frontend.needs_slam

    def listen_options(self, topic: str) -> dict:
        if topic != "frames":
            return {}
        # real time: every frame, `realtime_queue_s` of them queued through a stall (a SLAM that misses frames of a
        # hand-held camera loses track); a front end slower than the video for longer skips to newer frames (counted)
        self.frames_stream = f"{self.bus.keys.frames}#{Frame.SCHEMA}"  # (the inbox's name for it: Service.listen)
        return {"realtime_capacity": max(1, round(self.config.odometry.realtime_queue_s * 30)),
                "prepare": _decode if self.frontend.needs_images else None}

    def on_dynamic(self, message: DynamicObjects) -> None:
        if message.frame_id <= self.last_frame_id and self.lockstep:
            return  # (a replay: lockstep took this frame's own boxes; real time keeps late ones, see `_boxes`)
        # (real time: later than the frame after its own, the motion test no longer sees them; they still mask)
        self.metrics.count("dynamic_too_late_for_motion", message.frame_id <= self.dynamic_seen_upto)
        self.dynamic[message.frame_id] = message
        for old in sorted(self.dynamic)[:-DYNAMIC_KEPT]:
            del self.dynamic[old]
        self._estimate_ready()

    def on_slam(self, message: OdometryPose) -> None:
        if message.frame_id <= self.last_frame_id:
            self.metrics.count("slam_poses_late")
            return
        self.slam[message.frame_id] = message
        for old in sorted(self.slam)[:-DYNAMIC_KEPT]:
            del self.slam[old]
            self.metrics.count("slam_poses_unmatched")
        self._estimate_ready()

    def _ready(self, frame_id: int) -> bool:
        """Lockstep: what this frame waits for has come (its dynamic objects, an external SLAM's pose of it)."""
        return not ((self.await_dynamic and frame_id not in self.dynamic)
                    or (self.await_slam and frame_id not in self.slam))

    def _estimate_ready(self) -> None:
        """What a frame waited for came: the frames at the head of the queue that are ready now, in order."""
        while self.waiting and self._ready(self.waiting[0][0].frame_id):
            self._estimate(self.waiting.popleft()[0])

    def handle(self, frame: Frame) -> None:
        """Lockstep: a frame waits for its dynamic objects behind the frames that came before it (in order; a camera
        that does not wait for semmap sends the next ones meanwhile, and every one is posed)."""
        if not self.waiting and self._ready(frame.frame_id):
            self._estimate(frame)
            return
        if any(waiting.frame_id == frame.frame_id for waiting, _ in self.waiting):
            return  # (a resent frame: it is waiting already)
        self.waiting.append((frame, time.monotonic()))
        while len(self.waiting) > WAITING_KEPT:  # (bounded: the oldest goes on without them, counted)
            oldest = self.waiting.popleft()[0]
            self.metrics.count("dynamic_wait_overflow")
            if self.metrics.counters["dynamic_wait_overflow"] <= 5:
                self.log.warning("frame %d: %d frames wait for their dynamic objects, estimating it without them",
                                 oldest.frame_id, WAITING_KEPT)
            self._estimate(oldest)
        self._estimate_ready()

    def tick(self) -> None:
        while self.waiting and time.monotonic() - self.waiting[0][1] > self.dynamic_wait_s:
            frame = self.waiting.popleft()[0]
            self.metrics.count("dynamic_wait_timeouts")
            self.log.warning("frame %d: no dynamic objects or SLAM pose after %.0f s, estimating without them",
                             frame.frame_id, self.dynamic_wait_s)
            self._estimate(frame)
            self._estimate_ready()

    def _boxes(self, frame_id: int) -> DynamicObjects | None:
        """The frame's own dynamic objects, else (real time) the newest earlier ones: the tracker, which yields
        the CPU to the front end, often answers a frame after the front end has posed it, and its late answer is
        still the newest word on where the people are."""
        if frame_id in self.dynamic:
            return self.dynamic[frame_id]
        earlier = [f for f in self.dynamic if f < frame_id]
        return self.dynamic[max(earlier)] if earlier else None

    def _seen_since_last(self, frame_id: int) -> list[tuple[int, float, list]]:
        """Real time: the dynamic objects of frames up to this one that came since the previous frame, oldest
        first, for the front end to see each at its own frame's pose (`OdometryInput.dynamic_seen`)."""
        new = sorted(f for f in self.dynamic if self.dynamic_seen_upto < f <= frame_id)
        if new:
            self.dynamic_seen_upto = new[-1]
        return [(f, self.dynamic[f].stamp, self.dynamic[f].boxes) for f in new]

    def _estimate(self, frame: Frame) -> None:
        with self.metrics.timer("odometry_ms"):
            data = OdometryInput(frame.frame_id, frame.stamp, frame.gt_pose, depth_scale=frame.depth_scale,
                                 intrinsics=frame.intrinsics.matrix)
            if self.frontend.needs_images:
                data.rgb, data.depth = frame.rgb(), frame.depth()
            data.behind = not self.lockstep and self.inbox.waiting(self.frames_stream) > BEHIND_FRAMES
            if self.frontend.uses_dynamic:
                dynamic = self._boxes(frame.frame_id)
                data.dynamic = dynamic.boxes if dynamic is not None else []
                if dynamic is not None and dynamic.frame_id != frame.frame_id:
                    self.metrics.count("dynamic_from_earlier_frame")
                self.metrics.count("frames_with_dynamic_boxes", bool(data.dynamic))
                if not self.lockstep:
                    data.dynamic_seen = self._seen_since_last(frame.frame_id)
            slam = self.slam.pop(frame.frame_id, None)
            if self.frontend.needs_slam:
                data.slam_pose = None if slam is None else slam.pose
                self.metrics.count("slam_poses_missing", slam is None)
            pose = self.to_session @ self.frontend.estimate(data)
        if hasattr(self.frontend, "far_matches"):  # file:PATH frames with no pose within 0.05 s
            self.metrics.counters["frames_unmatched"] = self.frontend.far_matches
        self.metrics.counters.update(getattr(self.frontend, "counters", {}))  # e.g. rgbd's untrusted pairs
        sigma_t, sigma_r = self.frontend.sigmas
        keyframe = slam.keyframe if slam is not None else frame.frame_id % self.keyframe_every == 0
        message = OdometryPose(self.robot, frame.frame_id, frame.stamp, pose, keyframe=keyframe,
                               sigma_translation=sigma_t, sigma_rotation=sigma_r, source=self.mode,
                               bridged=bool(getattr(self.frontend, "bridged", False)),
                               step=str(getattr(self.frontend, "step_source", "")))
        if not message.bridged:  # (a stand-in pose is no measurement: the trajectory lists what was measured)
            self.trajectory.append((frame.stamp, pose))
        self.metrics.count("poses_published")
        self.metrics.count("poses_bridged", message.bridged)
        self.complete_frame(frame.frame_id, [(self.out["odometry"], message)],
                            (message.encode(), msgpack.packb(self.frontend.state())))

    def restore(self) -> None:
        """Continue the trajectory after a crash: earlier poses from the journal, the front end's state. The
        newest poses are remembered as sent: the old process may have journalled a frame and died before its pose
        or its progress left, and the player then sends that frame again; it must be answered, not ignored."""
        assert self.journal is not None
        state = None
        for frame_id, pose_bytes, state_bytes, _ in self.journal.frames():
            pose = OdometryPose.decode(pose_bytes)
            if not pose.bridged:
                self.trajectory.append((pose.stamp, pose.pose))
            self.resume_after(frame_id)
            state = state_bytes
        self.remember_newest(self.out["odometry"], OdometryPose.decode)
        if state is not None:
            self.frontend.restore(msgpack.unpackb(state))
            self.log.info("resumed after frame %d (%d poses)", self.last_frame_id, len(self.trajectory))

    def write_outputs(self) -> None:
        if self.out_dir is not None and self.trajectory:
            write_tum(self.out_dir / "trajectory_odometry.tum", self.trajectory)
        self._write_slam(SLAM_TRAJECTORY, getattr(self.frontend, "slam_trajectory", None))
        report = getattr(self.frontend, "repair_report", None)
        if self.out_dir is not None and report is not None:
            write_json_atomic(self.out_dir / REPAIR_REPORT, report(self.mode))
        close = getattr(self.frontend, "close", None)
        if close is not None:  # (ORB-SLAM3 stops its threads, then refines its own trajectory: after the rest)
            close()
        self._write_slam(SLAM_REFINED_TRAJECTORY, getattr(self.frontend, "refined_trajectory", None))

    def finish(self) -> None:
        """Finish as every service does (outputs written, which stops a SLAM front end), then hand the backend
        the SLAM's refinement at its end, once (even without an output folder: the backend waits for it)."""
        finishing = not self.finished
        super().finish()
        if finishing:
            self._send_refinement()

    def _send_refinement(self) -> None:
        refine = getattr(self.frontend, "refinement", None)
        if refine is None:
            return
        close = getattr(self.frontend, "close", None)
        if close is not None:  # (already closed where the outputs were written: a second close does nothing)
            close()
        refinement = refine()
        if refinement is None:
            return
        self.out["odometry/refined"].put(refinement.message(self.robot, self.mode, self.to_session))
        self.metrics.counters["refinement_frames"] = len(refinement.frame_ids)
        if refinement.withheld:
            self.log.info("the SLAM's refinement at its end is not offered: %s", refinement.withheld)
        self.publish_status()  # (its counter in the run's stats)

    def _write_slam(self, name: str, poses: list | None) -> None:
        """A checked SLAM's own poses, in the session's world."""
        if self.out_dir is not None and poses:
            write_tum(self.out_dir / name, [(t, self.to_session @ pose) for t, pose in poses])


def _decode(frame: Frame) -> None:
    """A frame's images decoded as it arrives (Frame caches them): the front end's thread only tracks."""
    frame.rgb()
    frame.depth()


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--await-dynamic", action="store_true",
                        help="lockstep: a front end that leaves out dynamic objects waits for each frame's boxes "
                             "(a tracker must run)")


def main(argv: list[str] | None = None) -> int:
    return service_main(OdometryService, argv, _arguments)

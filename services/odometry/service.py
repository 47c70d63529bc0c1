"""Odometry front-end service: one `OdometryPose` per frame on `semmap/v1/<robot>/odometry`.

It stands in for an external SLAM; a real one publishes the same messages on the same key instead.
"""

from __future__ import annotations

import msgpack
import numpy as np

from semmap.datasets.trajectory_io import write_tum
from semmap.journal import FrameJournal
from semmap.messages import Frame, OdometryPose
from semmap.service import REPLAY_FRAMES, Service, service_main
from services.odometry.frontends import FrontEnd, OdometryInput, frame_offset, make_frontend


class OdometryService(Service):
    """Publishes camera poses for every frame (see module docstring)."""

    name = "odometry"

    def setup(self) -> None:
        cfg = self.config["odometry"]
        self.mode: str = cfg["mode"]
        self.frontend: FrontEnd = make_frontend(self.mode, cfg)
        self.to_session = np.linalg.inv(frame_offset(cfg.get("frame_offset", [0.0] * 6)))
        self.keyframe_every = max(1, int(cfg["keyframe_every"]))
        self.trajectory: list[tuple[float, object]] = []
        self.pose_pub = self.publisher(self.bus.keys.odometry)
        self.journal = FrameJournal(self.out_dir / "odometry.sqlite") if self.out_dir is not None else None
        if self.journal is not None:
            if self.resume:
                self._restore()
            else:
                self.journal.clear()
        # real time: a slow front end (rgbd) skips to newer frames rather than queueing without bound
        self.listen(self.bus.keys.frames, Frame, self.on_frame, realtime_capacity=4)

    def on_frame(self, frame: Frame) -> None:
        if frame.frame_id <= self.last_frame_id:
            self.metrics.count("frames_repeated")
            self.replay(frame.frame_id)
            return
        with self.metrics.timer("odometry_ms"):
            data = OdometryInput(frame.frame_id, frame.stamp, frame.gt_pose, depth_scale=frame.depth_scale,
                                 intrinsics=frame.intrinsics.matrix)
            if self.frontend.needs_images:
                data.rgb, data.depth = frame.rgb(), frame.depth()
            pose = self.to_session @ self.frontend.estimate(data)
        if hasattr(self.frontend, "far_matches"):  # file:PATH frames with no pose within 0.05 s
            self.metrics.counters["frames_unmatched"] = self.frontend.far_matches
        sigma_t, sigma_r = self.frontend.sigmas
        self.emit(self.pose_pub, OdometryPose(self.robot, frame.frame_id, frame.stamp, pose,
                                              keyframe=frame.frame_id % self.keyframe_every == 0,
                                              sigma_translation=sigma_t, sigma_rotation=sigma_r, source=self.mode),
                  frame.frame_id)
        self.trajectory.append((frame.stamp, pose))
        if self.journal is not None:
            self.journal.append(frame.frame_id, self._sent[frame.frame_id][0][1].encode(),
                                msgpack.packb(self.frontend.state()))
        self.metrics.count("poses_published")
        self.report_progress(frame.frame_id)

    def _restore(self) -> None:
        """Continue the trajectory after a crash: earlier poses from the journal, the front end's state. The
        newest poses are remembered as sent: the old process may have journalled a frame and died before its pose
        or its progress left, and the player then sends that frame again; it must be answered, not ignored."""
        state = None
        for frame_id, pose_bytes, state_bytes, _ in self.journal.frames():
            pose = OdometryPose.decode(pose_bytes)
            self.trajectory.append((pose.stamp, pose.pose))
            self.last_frame_id, state = frame_id, state_bytes
        for frame_id, pose_bytes, _, _ in self.journal.last(REPLAY_FRAMES):
            self.remember(self.pose_pub, OdometryPose.decode(pose_bytes), frame_id)
        if state is not None:
            self.frontend.restore(msgpack.unpackb(state))
            self.log.info("resumed after frame %d (%d poses)", self.last_frame_id, len(self.trajectory))

    def write_outputs(self) -> None:
        if self.out_dir is not None and self.trajectory:
            write_tum(self.out_dir / "trajectory_odometry.tum", self.trajectory)


def main(argv: list[str] | None = None) -> int:
    return service_main(OdometryService, argv)

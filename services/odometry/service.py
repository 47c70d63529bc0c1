"""Odometry front-end service: one `OdometryPose` per frame on `semmap/v1/<robot>/odometry`.

It stands in for an external SLAM; a real one publishes the same messages on the same key instead.
"""

from __future__ import annotations

from semmap.datasets.trajectory_io import write_tum
from semmap.messages import Frame, OdometryPose
from semmap.service import Service, service_main
from services.odometry.frontends import FrontEnd, OdometryInput, make_frontend


class OdometryService(Service):
    """Publishes camera poses for every frame (see module docstring)."""

    name = "odometry"

    def setup(self) -> None:
        cfg = self.config["odometry"]
        self.mode: str = cfg["mode"]
        self.frontend: FrontEnd = make_frontend(self.mode, cfg)
        self.keyframe_every = max(1, int(cfg["keyframe_every"]))
        self.trajectory: list[tuple[float, object]] = []
        self.pose_pub = self.publisher(self.bus.keys.odometry)
        self.listen(self.bus.keys.frames, Frame, self.on_frame)

    def on_frame(self, frame: Frame) -> None:
        if frame.frame_id <= self.last_frame_id:
            self.metrics.count("frames_out_of_order")
            return
        with self.metrics.timer("odometry_ms"):
            data = OdometryInput(frame.frame_id, frame.stamp, frame.gt_pose, depth_scale=frame.depth_scale,
                                 intrinsics=frame.intrinsics.matrix)
            if self.frontend.needs_images:
                data.rgb, data.depth = frame.rgb(), frame.depth()
            pose = self.frontend.estimate(data)
        sigma_t, sigma_r = self.frontend.sigmas
        self.pose_pub.put(OdometryPose(self.robot, frame.frame_id, frame.stamp, pose,
                                       keyframe=frame.frame_id % self.keyframe_every == 0,
                                       sigma_translation=sigma_t, sigma_rotation=sigma_r, source=self.mode))
        self.trajectory.append((frame.stamp, pose))
        self.metrics.count("poses_published")
        self.report_progress(frame.frame_id)

    def write_outputs(self) -> None:
        if self.out_dir is not None and self.trajectory:
            write_tum(self.out_dir / "trajectory_odometry.tum", self.trajectory)


def main(argv: list[str] | None = None) -> int:
    return service_main(OdometryService, argv)

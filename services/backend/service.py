"""Backend service: the GTSAM pose graph of keyframes and landmark observations, corrected poses out.

Per frame it joins the front end's odometry with the associator's observations for that frame (both arrive for
every frame), runs one iSAM2 update and publishes the whole corrected trajectory on `poses/corrected`, which
the associator uses to associate against the current optimised estimate (closed loop). An external SLAM can
consume the same key.
"""

from __future__ import annotations

from semmap.datasets.trajectory_io import write_tum
from semmap.messages import Control, CorrectedPoses, Observations, OdometryPose
from semmap.reorder import FrameReorderBuffer
from semmap.service import Service, service_main
from services.backend.pose_graph import BackendParams, PoseGraph


class BackendService(Service):
    """Optimises the trajectory with landmark constraints (see module docstring)."""

    name = "backend"

    def setup(self) -> None:
        self.graph = PoseGraph(BackendParams.from_config(self.config.get("backend")))
        self.pub = self.publisher(self.bus.keys.corrected_poses)
        self.odometry: FrameReorderBuffer[OdometryPose] = FrameReorderBuffer(max_pending=100_000)
        self.observations: dict[int, Observations] = {}
        self.ready_odometry: list[OdometryPose] = []
        self.seq = 0
        self.listen(self.bus.keys.odometry, OdometryPose, self.on_odometry)
        self.listen(self.bus.keys.observations, Observations, self.on_observations)

    def on_odometry(self, pose: OdometryPose) -> None:
        if not self.odometry.push(pose.frame_id, pose):
            self.metrics.count("odometry_duplicates")
            return
        self.ready_odometry.extend(self.odometry.pop_ready())
        self._drain()

    def on_observations(self, obs: Observations) -> None:
        self.observations[obs.frame_id] = obs
        self._drain()

    def _drain(self) -> None:
        """Handle frames in order, each once both its odometry and its observations are here."""
        while self.ready_odometry and self.ready_odometry[0].frame_id in self.observations:
            pose = self.ready_odometry.pop(0)
            obs = self.observations.pop(pose.frame_id)
            with self.metrics.timer("update_ms") as timer:
                self.graph.add_odometry_message(pose)
                self.graph.add_observations_message(obs)
                self.graph.update()
            with self.metrics.timer("publish_ms"):
                ids, stamps, poses = self.graph.corrected_poses()
                lids, lpos = self.graph.landmark_positions()
                self.seq += 1
                self.pub.put(CorrectedPoses(self.robot, self.seq, pose.frame_id, ids, stamps, poses, lids, lpos,
                                            {"update": timer.ms}))
            self.metrics.count("frames")
            self.metrics.count("observations", len(obs.observations))
            self.report_progress(pose.frame_id)
        # observations for frames before our first odometry can never be joined
        first = self.odometry.next_id
        for stale in [f for f in self.observations if first is not None and f < first - 1]:
            del self.observations[stale]
            self.metrics.count("observations_unjoined")

    def on_end_of_stream(self, control: Control) -> None:
        if self.last_frame_id >= control.last_frame_id:
            self.finish()

    def write_outputs(self) -> None:
        if self.out_dir is None or self.graph.num_frames == 0:
            return
        ids, stamps, poses = self.graph.corrected_poses()
        write_tum(self.out_dir / "trajectory_optimized.tum", zip(stamps.tolist(), poses, strict=True))


def main(argv: list[str] | None = None) -> int:
    return service_main(BackendService, argv)

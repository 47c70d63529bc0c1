"""Backend service: the GTSAM pose graph of keyframes and landmark observations, corrected poses out.

Per frame it joins the front end's odometry with the associator's observations for that frame (both arrive for
every frame), runs one iSAM2 update and publishes the whole corrected trajectory on `poses/corrected`, which
the associator uses to associate against the current optimised estimate (closed loop). An external SLAM can
consume the same key.
"""

from __future__ import annotations

from semmap.datasets.trajectory_io import write_tum
from semmap.journal import FrameJournal
from semmap.messages import Control, CorrectedPoses, Observations, OdometryPose
from semmap.reorder import FrameReorderBuffer
from semmap.service import Service, service_main
from services.backend.pose_graph import BackendParams, PoseGraph

REALTIME_MAX_PENDING = 8


class BackendService(Service):
    """Optimises the trajectory with landmark constraints (see module docstring)."""

    name = "backend"

    def setup(self) -> None:
        self.graph = PoseGraph(BackendParams.from_config(self.config.get("backend")))
        self.pub = self.publisher(self.bus.keys.corrected_poses)
        # real time: odometry of a dropped frame never comes; give up on it after a few later ones
        self.odometry: FrameReorderBuffer[OdometryPose] = FrameReorderBuffer(
            max_pending=100_000 if self.lockstep else REALTIME_MAX_PENDING)
        self.observations: dict[int, Observations] = {}
        self.ready_odometry: list[OdometryPose] = []
        self.seq = 0
        self.journal = FrameJournal(self.out_dir / "backend.sqlite") if self.out_dir is not None else None
        if self.journal is not None:
            if self.resume:
                self._restore()
            else:
                self.journal.clear()
        self.listen(self.bus.keys.odometry, OdometryPose, self.on_odometry)
        self.listen(self.bus.keys.observations, Observations, self.on_observations)

    def on_odometry(self, pose: OdometryPose) -> None:
        if not self.odometry.push(pose.frame_id, pose):
            self.metrics.count("odometry_duplicates")
            return
        self._release()

    def on_observations(self, obs: Observations) -> None:
        if obs.frame_id <= self.last_frame_id:
            self.metrics.count("observations_duplicates")
            self.replay(obs.frame_id)
            return
        self.observations[obs.frame_id] = obs
        self._drain()

    def on_frame_unreadable(self, frame_id: int) -> None:
        self.odometry.skip(frame_id)
        self.observations.pop(frame_id, None)
        self._release()

    def _release(self) -> None:
        self.ready_odometry.extend(self.odometry.pop_ready())
        self._drain()

    def _drain(self) -> None:
        """Handle frames in order, each once both its odometry and its observations are here."""
        while self.ready_odometry and self.ready_odometry[0].frame_id in self.observations:
            pose = self.ready_odometry.pop(0)
            obs = self.observations.pop(pose.frame_id)
            if self.journal is not None:
                self.journal.append(pose.frame_id, pose.encode(), obs.encode())
            with self.metrics.timer("update_ms") as timer:
                self.graph.add_odometry_message(pose)
                self.graph.add_observations_message(obs)
                self.graph.update()
            with self.metrics.timer("publish_ms"):
                ids, stamps, poses = self.graph.corrected_poses()
                lids, lpos = self.graph.landmark_positions()
                self.seq += 1
                self.emit(self.pub, CorrectedPoses(self.robot, self.seq, pose.frame_id, ids, stamps, poses, lids,
                                                   lpos, {"update": timer.ms}), pose.frame_id)
            self.metrics.count("frames")
            self.metrics.count("observations", len(obs.observations))
            self.report_progress(pose.frame_id)
        # observations for frames before our first odometry can never be joined
        first = self.odometry.next_id
        for stale in [f for f in self.observations if first is not None and f < first - 1]:
            del self.observations[stale]
            self.metrics.count("observations_unjoined")

    def _restore(self) -> None:
        """Rebuild the graph from the journal of handled frames (after a crash), without publishing."""
        n = 0
        for frame_id, odometry, observations in self.journal.frames():
            self.graph.add_odometry_message(OdometryPose.decode(odometry))
            self.graph.add_observations_message(Observations.decode(observations))
            self.graph.update()
            self.odometry.mark_done(frame_id)
            self.last_frame_id = frame_id
            n += 1
        if n:
            self.log.info("restored the pose graph from %d journalled frames (last %d)", n, self.last_frame_id)

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

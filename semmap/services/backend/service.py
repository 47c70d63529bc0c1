"""Backend service: the GTSAM pose graph of keyframes and landmark observations, corrected poses out.

Per frame it joins the front end's odometry with the associator's observations for that frame (both arrive for
every frame), runs one iSAM2 update and publishes the whole corrected trajectory on `poses/corrected`, which
the associator uses to associate against the current optimised estimate (closed loop). An external SLAM can
consume the same key.

Loop closures (`loop_closure:` config, on by default): the depth image of every n-th frame comes from the
frames key; at a revisit the keyframe is registered to an earlier one by ICP
(semmap/algorithms/backend/loop_closure.py) and the relative pose joins the graph before that frame's poses go out.
In lockstep a keyframe waits for its depth too, so a replay closes the same loops; with
`--await-keyframe-dynamic` (passed by `semmap run` when a tracker runs) it also waits for the keyframe's dynamic
objects (`dynamic` key), left out of its cloud. A session started from a prior map (`--prior-map`) also registers
its keyframes to the prior run's once it has relocalised (semmap/runtime/maps/prior_keyframes.py, docs/MAPS.md).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterable
from pathlib import Path

from semmap.algorithms.backend.loop_closure import (
    KeyframeCloud,
    LoopCloser,
    LoopClosure,
    decode_keyframe,
    encode_keyframe,
)
from semmap.algorithms.backend.pose_graph import PoseGraph
from semmap.algorithms.backend.prior_alignment import FinalAlignment
from semmap.core.dataflow import REFINING_FRONT_ENDS
from semmap.core.messages import (
    Control,
    DynamicObjects,
    Frame,
    MessageError,
    Observations,
    OdometryPose,
    OdometryRefinement,
)
from semmap.core.outputs import atomic_write_text
from semmap.datasets.trajectory_io import write_tum
from semmap.runtime.pipeline.stages import BackendStage
from semmap.runtime.transport.service import service_main
from semmap.runtime.transport.stage_service import StageService

REALTIME_MAX_PENDING = 8
REALTIME_FRAME_QUEUE = 8  # frames waiting for the backend in real time (only keyframes are looked at)
MAX_PENDING_CLOUDS = 64  # keyframe clouds waiting for their odometry and observations (~80 KB each)
# how long the run's end waits for a refining front end's refinement: ORB-SLAM3 stops its threads and saves its
# trajectory first (about a second on the recordings here; its last loop closure's bundle adjustment may be longer)
REFINEMENT_WAIT_S = 60.0


class BackendService(StageService):
    """Optimises the trajectory with landmark constraints (see module docstring)."""

    name = "backend"
    yields_to_front_end = True  # (real time: see StageService.yield_to_front_end)
    # per frame, once complete: its odometry and observations (and, as its extra, a keyframe's cloud and closure)
    journal_file = "backend.sqlite"
    # the frame inputs re-ordered are the odometry's; real time: a pose of a dropped frame never comes, so a frame
    # is given up after a few later ones
    realtime_max_pending = REALTIME_MAX_PENDING
    duplicates_counter = "odometry_duplicates"
    gaps_counter = "frames_without_odometry"

    def setup_stage(self) -> None:
        # the per-frame policy (graph update, loop closure, corrections) is the stage's
        # (semmap/runtime/pipeline/stages.py)
        prior_map = getattr(self.args, "prior_map", None)
        self.stage = BackendStage(self.config.backend, self.config.loop_closure, self.config.corrections,
                                  expect_alignment=prior_map is not None)
        if prior_map is not None and self.closer.params.enabled:
            self._load_prior_keyframes(Path(prior_map))
        # keyframe clouds waiting for their frame's turn; None: the frame's depth could not be read
        self.clouds: dict[int, KeyframeCloud | None] = {}
        # a keyframe's depth waiting for its dynamic objects (to leave out of its cloud), and those that came first
        self.key_depth: dict[int, Frame] = {}
        self.key_dynamic: dict[int, DynamicObjects] = {}
        self.mask_dynamic = self.config.loop_closure.dynamic_mask != "none"
        # lockstep, a tracker running: a keyframe's cloud waits for its boxes (real time: what is here by then)
        self.await_dynamic = (self.mask_dynamic and self.lockstep
                              and bool(getattr(self.args, "await_keyframe_dynamic", False)))
        self.open_outputs()
        self.observations: dict[int, Observations] = {}
        self.ready_odometry: list[OdometryPose] = []
        self.seq = 0
        # `semmap run external`: no odometry service writes the SLAM's input, so the backend does
        self.write_odometry = bool(getattr(self.args, "write_odometry", False))
        self.input_trajectory: list[tuple[float, object]] = []  # only then: it grows with every frame
        # a front end that refines its trajectory at its end (ORB-SLAM3) sends it once after its last pose: the run
        # ends with it (`on_refinement`), or without it after REFINEMENT_WAIT_S (counted)
        self.refinement: OdometryRefinement | None = None
        self.refinement_done = False
        self.refinement_waiting_since: float | None = None

    @property
    def takes_keyframes(self) -> bool:
        """Loop closures register keyframes' depth: the frames port (semmap/core/dataflow.py) is wired."""
        return bool(self.closer.params.enabled)

    @property
    def awaits_refinement(self) -> bool:
        """The front end refines its trajectory at its end (dataflow.REFINING_FRONT_ENDS, unless turned off):
        the `odometry/refined` port is wired, and the run's trajectory waits for it."""
        odometry = self.config.odometry
        return odometry.mode in REFINING_FRONT_ENDS and odometry.orbslam3_refinement

    @property
    def masks_keyframes(self) -> bool:
        """... and leave their dynamic objects out: the dynamic port too."""
        return self.takes_keyframes and bool(self.mask_dynamic)

    def listen_options(self, topic: str) -> dict:
        if topic == "frames":  # keyframes only: the rest pass unread
            return {"realtime_capacity": REALTIME_FRAME_QUEUE, "wanted": lambda fid: self.closer.wants(fid)}
        return {}

    def _load_prior_keyframes(self, map_db: Path) -> None:
        """The prior run's keyframes, to register this session's to once it has relocalised."""
        prior = self.stage.load_prior_keyframes(map_db)
        self.metrics.counters["prior_keyframes"] = len(self.closer.prior)
        if prior.unreadable or prior.without_pose:
            self.metrics.counters["prior_keyframes_skipped"] = prior.unreadable + prior.without_pose
            self.log.warning("prior map: %d of its run's keyframes unreadable, %d without an optimised pose: skipped",
                             prior.unreadable, prior.without_pose)
        if prior.missing is not None:
            self.log.warning("prior map: no keyframes of its run (%s): this session is held to the map by its "
                             "objects only", prior.missing)
        else:
            self.log.info("prior map: %d keyframes of its run to register to once relocalised", len(self.closer.prior))

    @property
    def graph(self) -> PoseGraph:
        return self.stage.graph  # (a new graph once the session relocalises against a prior map)

    @property
    def closer(self) -> LoopCloser:
        return self.stage.closer

    def on_frame(self, frame: Frame) -> None:
        """Keep a keyframe's depth until its frame is handled (other frames are not looked at): as a cloud at once,
        or, where its dynamic objects are to be left out, once they are here too."""
        fid = frame.frame_id
        if (not self.closer.wants(fid) or fid <= self.last_frame_id or fid in self.clouds
                or fid in self.key_depth):
            return
        if self.mask_dynamic:
            self.key_depth[fid] = frame
            self._bounded(self.key_depth, "keyframe_depth_dropped")
            self._cloud_when_ready(fid)
        else:
            self._make_cloud(frame, None)
        self._drain()

    def on_dynamic(self, message: DynamicObjects) -> None:
        fid = message.frame_id
        if not self.closer.wants(fid) or fid <= self.last_frame_id or fid in self.clouds:
            return
        self.key_dynamic[fid] = message
        self._bounded(self.key_dynamic, "keyframe_dynamic_dropped")
        self._cloud_when_ready(fid)
        self._drain()

    def _cloud_when_ready(self, fid: int) -> None:
        if fid in self.key_depth and fid in self.key_dynamic:
            self._make_cloud(self.key_depth.pop(fid), self.key_dynamic.pop(fid))

    def _make_cloud(self, frame: Frame, dynamic: DynamicObjects | None) -> None:
        """The keyframe's cloud, its dynamic objects left out (`loop_closure.dynamic_mask`); None if its depth
        cannot be read (no closure from it)."""
        fid = frame.frame_id
        try:
            depth = frame.depth()
        except MessageError as exc:
            self.metrics.count("keyframe_depth_unreadable")
            self.log.warning("frame %d: no loop closure from it (%s)", fid, exc)
            self.clouds[fid] = None
        else:
            k = frame.intrinsics
            with self.metrics.timer("keyframe_cloud_ms"):
                self.clouds[fid] = self.closer.cloud_from_depth(fid, frame.stamp, depth, frame.depth_scale, k.fx,
                                                                k.fy, k.cx, k.cy, None if dynamic is None else
                                                                dynamic.boxes)
        self._bounded(self.clouds, "keyframe_clouds_dropped")

    def _bounded(self, pending: dict, counter: str) -> None:
        while len(pending) > MAX_PENDING_CLOUDS:  # frames without odometry: bounded, the oldest go
            del pending[min(pending)]
            self.metrics.count(counter)

    def on_resent(self, pose: OdometryPose) -> None:
        """A pose of a frame handled or waiting already: counted only (the backend answers a resent frame when
        its observations come again, the input that follows the pose)."""

    def on_observations(self, obs: Observations) -> None:
        if obs.frame_id <= self.last_frame_id:
            self.metrics.count("observations_duplicates")
            self.replay(obs.frame_id)
            return
        self.observations[obs.frame_id] = obs
        self._drain()

    def on_frame_unreadable(self, frame_id: int) -> None:
        self.observations.pop(frame_id, None)
        self.clouds.pop(frame_id, None)
        self.key_depth.pop(frame_id, None)
        self.key_dynamic.pop(frame_id, None)
        super().on_frame_unreadable(frame_id)

    def handle(self, pose: OdometryPose) -> None:
        """A pose released in order: it waits for its frame's observations (`release` drains)."""
        self.ready_odometry.append(pose)

    def release(self, ready: Iterable[OdometryPose] | None = None) -> None:
        """The poses now in order, then the frames that are ready: drained once every released pose is queued,
        because a drain forgets the observations of frames before the next expected pose (they can never be
        joined), and poses released together must all be joined first."""
        super().release(ready)
        self._drain()

    def _drain(self) -> None:
        """Handle frames in order, each once its odometry and its observations (and, in lockstep, a keyframe's
        depth) are here."""
        while self.ready_odometry:
            if not self._ready(self.ready_odometry[0].frame_id):
                if not self._observations_passed(self.ready_odometry[0].frame_id):
                    break
                self._give_up_pose(self.ready_odometry.pop(0))
                continue
            pose = self.ready_odometry.pop(0)
            obs = self.observations.pop(pose.frame_id)
            if pose.frame_id in self.key_depth:  # real time, its boxes not here (yet): its cloud with none left out
                self.metrics.count("keyframe_clouds_unmasked")
                self._make_cloud(self.key_depth.pop(pose.frame_id), None)
            cloud = self.clouds.pop(pose.frame_id, None)
            if self.write_odometry:
                self.input_trajectory.append((pose.stamp, pose.pose))
            step = self.stage.step(pose, obs, cloud)
            if step.realigned:
                self._log_realigned(obs)
            elif obs.alignment is not None and not self.stage.aligner.expected:
                self.metrics.count("alignments_ignored")
                self.log.warning("frame %d carries a prior-map alignment, but this backend was not started for a "
                                 "prior map (--prior-map): ignored", obs.frame_id)
            self.metrics.time_ms("update_ms", step.update_ms)
            self._count_refactorisation()
            if cloud is not None:
                self._loop_closed(cloud, step.closure, step.loop_closure_ms or 0.0)
            self.metrics.time_ms("publish_ms", step.timing_ms["publish"])
            self.seq += 1
            message = step.message(self.robot, self.seq, pose.frame_id)
            self.metrics.count("corrected_poses_sent", len(step.delta.frame_ids))
            self.metrics.count("frames")
            self.metrics.count("observations", len(obs.observations))
            # journalled after the frame's closure (its extra): a frame journalled is a frame complete, so a crash
            # in between loses no closure; one before it means the frame is handled again
            self.complete_frame(pose.frame_id, [(self.out["poses/corrected"], message)], (pose.encode(), obs.encode()))
        # observations for frames before the oldest pose still waiting (or, none waiting, before the last pose
        # handled) can never be joined: their pose never came or was given up. (Not before the next pose expected:
        # poses run ahead of observations, and the observations of poses already queued must stay.)
        waiting = self.ready_odometry[0].frame_id if self.ready_odometry else None
        first = waiting if waiting is not None else (None if self.inputs.next_id is None else self.inputs.next_id - 1)
        for stale in [f for f in self.observations if first is not None and f < first]:
            del self.observations[stale]
            self.metrics.count("observations_unjoined")
        for pending in (self.clouds, self.key_depth, self.key_dynamic):  # its frame was skipped or dropped
            for stale in [f for f in pending if f <= self.last_frame_id]:
                del pending[stale]

    def _observations_passed(self, frame_id: int) -> bool:
        """Real time: a later frame's observations are here, so this frame's never come (the associator sends in
        frame order; its frame was lost upstream, e.g. a detector replica's answer for the stream's first frame
        came after the other replica's for the second, and the tracker had started at the second). Lockstep loses
        no frame: there the pose waits."""
        return not self.lockstep and any(f > frame_id for f in self.observations)

    def _give_up_pose(self, pose: OdometryPose) -> None:
        """A pose whose frame's observations never come: counted and logged (the first few), its frame left out of
        the graph like a frame without odometry, so that the frames after it go through."""
        self.clouds.pop(pose.frame_id, None)
        self.metrics.count("frames_without_observations")
        if self.metrics.counters["frames_without_observations"] <= 3:
            self.log.warning("frame %d: its observations never came (lost upstream); the frame is left out of the "
                             "pose graph (counted: frames_without_observations)", pose.frame_id)

    def _count_refactorisation(self) -> None:
        """Say so when the pose graph had to leave Cholesky for QR (an ill-conditioned graph: a long street)."""
        done = self.graph.counters["qr_refactorisations"]
        if done > self.metrics.counters.get("graph_qr_refactorisations", 0):
            self.metrics.counters["graph_qr_refactorisations"] = done
            self.log.warning("pose graph: iSAM2's Cholesky refused an ill-conditioned update (%s); rebuilt and "
                             "factorised by QR from now on (slower, stable)", self.graph.refactorised_because)

    def _log_realigned(self, obs: Observations) -> None:
        """A frame that carried a prior-map alignment moved the graph into the prior map's frame
        (semmap/algorithms/backend/prior_alignment.py)."""
        assert obs.alignment is not None
        self.log.info("relocalised against the prior map at frame %d (%d landmarks agree, residual %.1f cm): "
                      "the trajectory is now in the prior map's frame, %d prior landmarks anchor it",
                      obs.frame_id, obs.alignment.inliers, 100 * obs.alignment.rms_m, len(obs.alignment.anchors))
        self.metrics.counters["relocalised_at_frame"] = obs.frame_id

    def _ready(self, frame_id: int) -> bool:
        if frame_id not in self.observations:
            return False
        # lockstep: a keyframe waits for its depth so that a replay closes the same loops; in real time the
        # depth arrives long before the observations, and a dropped one only means no closure from that frame
        return (not (self.lockstep and self.closer.wants(frame_id)) or frame_id in self.clouds
                or (frame_id in self.key_depth and not self.await_dynamic))

    def _loop_closed(self, cloud: KeyframeCloud, closure: LoopClosure | None, ms: float) -> None:
        """Journal and count a keyframe's loop-closure search (the stage ran it)."""
        self.metrics.time_ms("loop_closure_ms", ms)
        if self.journal is not None:
            self.journal.append_extra(cloud.frame_id, encode_keyframe(cloud, closure))
        if closure is not None:
            self.metrics.count("loop_closures")
            self.log.info("loop closure: frame %d to %sframe %d (fitness %.2f, rmse %.1f cm, moved %.1f cm)",
                          closure.frame_b, "the prior run's " if closure.T_wa is not None else "",
                          closure.frame_a, closure.fitness, 100 * closure.rmse_m, 100 * closure.correction_m)
        for name in ("registered", "rejected_fitness", "rejected_rmse", "rejected_degenerate",
                     "rejected_correction", "evicted", "prior_searched", "prior_accepted"):
            self.metrics.counters[f"loop_{name}"] = self.closer.counters[name]
        self.metrics.counters["loop_kept_keyframes"] = len(self.closer.keyframes)
        self.metrics.counters["loop_kept_kb"] = self.closer.nbytes // 1024

    def restore(self) -> None:
        """Rebuild the graph from the journal of handled frames (after a crash), without publishing."""
        assert self.journal is not None
        n = 0
        for frame_id, odometry, observations, keyframe in self.journal.frames():
            pose = OdometryPose.decode(odometry)
            if self.write_odometry:
                self.input_trajectory.append((pose.stamp, pose.pose))
            obs = Observations.decode(observations)
            step = self.stage.restore(pose, obs, None if keyframe is None else decode_keyframe(keyframe))
            if step.realigned:
                self._log_realigned(obs)
            self.resume_after(frame_id)
            n += 1
        self.seq = n  # one correction went out per frame
        if n:
            # the old process may have journalled its last frame and died before that frame's correction left:
            # the associator sends the frame's observations again and must get it (the same message: the same
            # delta, not the whole trajectory, which would hand it poses the clean run never sent)
            message = step.message(self.robot, self.seq, self.last_frame_id, {})
            self.remember(self.out["poses/corrected"], message, self.last_frame_id)
            self.log.info("restored the pose graph from %d journalled frames (last %d)", n, self.last_frame_id)

    def tick(self) -> None:
        self._refinement_overdue()
        self._give_up_missing()

    def _refinement_overdue(self) -> None:
        since = self.refinement_waiting_since
        if since is None or self.refinement_done or self.finished or time.monotonic() - since < REFINEMENT_WAIT_S:
            return
        self.refinement_done = True
        self.metrics.count("odometry_refinement_timeouts")
        self.log.warning("no refinement from the front end %.0f s after the stream's end: the trajectory is written "
                         "as tracked", REFINEMENT_WAIT_S)
        self.finish()

    def _give_up_missing(self) -> None:
        """Real time, once the odometry of the stream's last frame is here: a frame still missing before it was
        dropped upstream (the odometry keeps only the newest frames under load; poses come in order) and never
        comes. Give it up, counted, so that the last frames go through: otherwise fewer than
        REALTIME_MAX_PENDING later frames never release it and the run waits at its end until it fails. A last
        frame whose odometry never comes releases nothing: that is a stall, and the run's watchdog says so."""
        eos = self.end_of_stream
        if self.lockstep or eos is None or self.finished or eos.last_frame_id not in self.inputs.pending:
            return
        self.release(self.inputs.give_up_before(eos.last_frame_id))

    def on_refinement(self, message: OdometryRefinement) -> None:
        if self.refinement is not None or self.refinement_done:
            self.metrics.count("odometry_refinements_repeated")
            return
        self.refinement = message
        if self.end_of_stream is not None and not self.finished:
            self.on_end_of_stream(self.end_of_stream)

    def on_end_of_stream(self, control: Control) -> None:
        """Finish once the last frame is handled and, from a refining front end, its refinement is in the graph
        (or did not come within REFINEMENT_WAIT_S: `tick`)."""
        self.count_frames_before_the_first(control)
        if self.last_frame_id < control.last_frame_id:
            return
        if self.awaits_refinement and not self.refinement_done:
            if self.refinement is None:
                if self.refinement_waiting_since is None:
                    self.refinement_waiting_since = time.monotonic()
                return
            self._take_refinement(self.refinement)
        self.finish()

    def _take_refinement(self, message: OdometryRefinement) -> None:
        self.refinement_done = True
        with self.metrics.timer("refinement_ms"):
            taken, withheld = self.stage.refine(message)
        if withheld:
            self.metrics.counters["odometry_refinement_withheld"] = 1
            self.log.info("the front end's refinement at its end is not taken: %s", withheld)
            return
        self.metrics.counters["odometry_refined_frames"] = taken
        # (frames the graph does not hold as measured: never seen, or stand-ins; counted, not silently lost)
        self.metrics.counters["odometry_refinement_passed_over"] = len(message.frame_ids) - taken
        self.log.info("took %s's refinement at its end: %d of %d frames' odometry, optimised again", message.source,
                      taken, len(message.frame_ids))

    def write_outputs(self) -> None:
        if self.out_dir is None or self.graph.num_frames == 0:
            return
        ids, stamps, poses = self.graph.measured_poses()  # (not the stand-ins of frames no front end measured)
        self.metrics.counters["frames_unmeasured"] = self.graph.num_unmeasured
        write_tum(self.out_dir / "trajectory_optimized.tum", zip(stamps.tolist(), poses, strict=True))
        final = self.stage.aligner.final(self.graph)
        if final is not None:
            self._write_final_alignment(final)
        if self.write_odometry and self.input_trajectory:
            write_tum(self.out_dir / "trajectory_odometry.tum", self.input_trajectory)


    def _write_final_alignment(self, final: FinalAlignment) -> None:
        """DIR/relocalization_final.json: the session-to-map transform the run ends with, next to the object fit
        it started from (relocalization.json, the associator's): what the graph corrected."""
        assert self.out_dir is not None
        closures = self.closer.counters["prior_accepted"]
        body = {"frame_id": final.frame_id, "transform": [round(float(v), 9) for v in final.transform.reshape(16)],
                "object_fit_transform": [round(float(v), 9) for v in final.object_fit.reshape(16)],
                "correction_deg": round(final.correction_deg, 4),
                "correction_m_at_camera": round(final.correction_m, 4), "prior_keyframe_closures": closures}
        atomic_write_text(self.out_dir / "relocalization_final.json", json.dumps(body, indent=1) + "\n")
        self.log.info("relocalisation at frame %d: the final estimate moved the object fit by %.2f deg, %.1f cm at "
                      "that frame's camera (%d keyframes registered to the prior run's)", final.frame_id,
                      final.correction_deg, 100 * final.correction_m, closures)


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--write-odometry", action="store_true",
                        help="also write the odometry it received as trajectory_odometry.tum (external runs)")
    parser.add_argument("--await-keyframe-dynamic", action="store_true",
                        help="lockstep: a keyframe's cloud waits for the frame's dynamic objects, left out of it "
                             "(a tracker must run)")
    parser.add_argument("--prior-map", default=None, metavar="MAP_SQLITE",
                        help="the associator starts from this prior map: keep the frames handled until it "
                        "relocalises, to rebuild the graph in the map's frame, then register keyframes to the "
                        "map's run's keyframes (its backend.sqlite and trajectory_optimized.tum)")


def main(argv: list[str] | None = None) -> int:
    return service_main(BackendService, argv, _arguments)

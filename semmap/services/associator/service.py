"""Associator service: landmark candidates -> validated, associated, refined semantic landmarks.

Per frame (tracks and odometry both arrive for every frame) it runs the mapper against the current best poses:
the backend's corrected poses where it has them, the odometry moved by the newest correction otherwise
("associate against the optimised estimate, not the drifted odometry"). It publishes the frame's landmark
observations for the backend and, in lockstep, waits for the backend's answer for that frame before it
refines the map and reports the frame done, so a replay gives the same map every time.
The map is persisted to `DIR/map.sqlite` (atomic) and exported to `DIR/map.json`; it survives a restart.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperStep
from semmap.algorithms.associator.pose_book import PoseBook
from semmap.algorithms.associator.prior_map import PriorParams, PriorSession
from semmap.core.journal import MessageJournal
from semmap.core.messages import (
    Control,
    CorrectedPoses,
    Landmark,
    MapAlignment,
    MapUpdate,
    Observations,
    OdometryPose,
    TagDetection,
    TagDetections,
    Tracks,
)
from semmap.core.reorder import FrameReorderBuffer
from semmap.runtime.map_query import MapQuery, QueryError, reply_document, run_query
from semmap.runtime.map_store import MapStore, write_map_json
from semmap.runtime.pipeline import AssociatorStage, combined
from semmap.runtime.service import Service, service_main

SAVE_PERIOD_S = 1.0


class AssociatorService(Service):
    """Maps validated candidates to landmarks (see module docstring)."""

    name = "associator"

    def setup(self) -> None:
        self.params = self.config.associator  # the mapper's settings, the service's own and the prior map's
        self.await_backend = bool(self.args.await_backend) and self.lockstep
        # the per-frame policy (pose book, waiting on the backend, refinement, carried-over merges) is the stage's
        # (semmap/runtime/pipeline.py); this service decodes, re-orders, journals, persists and publishes
        self.stage = AssociatorStage(self.params, self.params.refine_every_n_frames, self.await_backend)
        self.snapshot: list[Landmark] = []  # what map queries answer from (swapped whole, read from Zenoh threads)
        self.tracks: FrameReorderBuffer[Tracks] = FrameReorderBuffer(max_pending=100_000 if self.lockstep else 8)
        self.ready: list[Tracks] = []
        self.map_seq = 0
        self.completed_frame = -1  # the newest frame completed (what a save includes)
        self.last_saved = 0.0
        self.dirty = False
        db = self.args.map_db or (self.out_dir / "map.sqlite" if self.out_dir is not None else None)
        self.store = MapStore(db) if db is not None else None
        self.journal = MessageJournal(db.with_name(f"{db.stem}.journal.sqlite")) if db is not None else None
        self.journal_seq = 0  # the last journalled input the saved map includes
        self.restoring = self.store is not None and bool(self.resume or self.args.map_db)
        self.prior: PriorSession | None = None
        self.session_start: float | None = None
        self._alignment: MapAlignment | None = None  # to go out with the current frame's observations
        if self.args.prior_map is not None:
            self._load_prior(self.args.prior_map, self.params.prior())
        if self.restoring:
            self._restore()
        elif self.store is not None and self.journal is not None:  # a new run: nothing of an earlier one
            self.store.clear()
            self.journal.clear()
        self.snapshot = self._landmarks()
        self.obs_pub = self.publisher(self.bus.keys.observations)
        self.tags_pub = self.publisher(self.bus.keys.landmark_tags)
        self.map_pub = self.publisher(self.bus.keys.map_updates)
        self._queryable = self.bus.session.declare_queryable(self.bus.keys.map_query, self._on_query)
        self.listen(self.bus.keys.odometry, OdometryPose, self.on_odometry)
        self.listen(self.bus.keys.corrected_poses, CorrectedPoses, self.on_corrected)
        self.listen(self.bus.keys.tracks, Tracks, self.on_tracks)
        self._replay_journal()
        if self.stage.awaiting is not None:  # the replay ended on a frame held for the backend, which may never
            self.obs_pub.put(self._awaited_observations)  # have got its observations: they go (again) now
        if self.snapshot:
            self._publish_map(MapperStep(), self.last_frame_id, 0.0, full=True)

    @property
    def mapper(self) -> LandmarkMapper:
        return self.stage.mapper

    @property
    def poses(self) -> PoseBook:
        return self.stage.poses

    def _load_prior(self, path: Path, params: PriorParams) -> None:
        """The prior map this session relocalises against (its landmarks join the map once it has)."""
        state = MapStore.open_existing(path).load()  # MessageError (MapVersionError) on a file of another version
        if state is None:
            raise ValueError(f"the prior map {path} holds no map")
        prior = LandmarkMapper.from_state(state, self.params).map
        self.prior = PriorSession(prior, params)
        self.mapper.map.next_id = max(self.mapper.map.next_id, prior.next_id)  # session ids after the prior's
        self.metrics.counters["prior_landmarks"] = len(prior)
        self.metrics.counters["relocalised"] = 0
        self.log.info("prior map %s: %d landmarks; mapping in a provisional frame (this session's odometry) until "
                      "the session relocalises against it", path, len(prior))

    def _landmarks(self) -> list[Landmark]:
        """The map as published and saved: with each prior landmark's status when a prior map is loaded."""
        landmarks = self.mapper.landmarks()
        return landmarks if self.prior is None else self.prior.with_status(landmarks)

    def _prior_step(self, tracks: Tracks, step: MapperStep) -> MapperStep:
        """Relocalise when due; afterwards, statuses of the prior landmarks (seen again, missing)."""
        assert self.prior is not None
        seen = [lm.id for lm in step.updated]
        if self.prior.due(tracks.frame_id):
            with self.metrics.timer("relocalize_ms"):
                fit = self.prior.try_relocalize(self.mapper)
            if fit is not None:
                self.poses.align(fit.transform, tracks.frame_id)
                adopted, self._alignment = self.prior.adopt(self.mapper, fit, tracks.frame_id,
                                                            self.session_start or tracks.stamp, self.poses)
                step = combined(step, adopted)
                t = fit.translation
                self.log.info("relocalised at frame %d: %d landmarks agree (next best placement %d), residual "
                              "%.1f cm%s; translation (%.3f, %.3f, %.3f) m, rotation %.2f deg; now mapping in the "
                              "prior map's frame", tracks.frame_id, fit.inliers, fit.runner_up, 100 * fit.rms_m,
                              ", refined on clouds" if fit.refined else "", t[0], t[1], t[2], fit.rotation_deg)
                self.metrics.counters.update(relocalised=1, relocalised_at_frame=tracks.frame_id,
                                             relocalised_inliers=fit.inliers)
            self.metrics.counters["relocalize_attempts"] = self.prior.attempts
        changed = self.prior.update(self.mapper, tracks.frame_id, self.poses(tracks.frame_id),
                                    None if tracks.skipped else tracks.boxes, self.mapper._intrinsics, seen)
        if changed:
            ids = set(changed)
            step.updated = [m for m in step.updated if m.id not in ids] + [
                self.mapper.map[i].to_message() for i in sorted(ids) if i in self.mapper.map]
            self.metrics.counters["prior_missing"] = sum(v == "missing" for v in self.prior.status.values())
            self.metrics.counters["prior_seen_again"] = sum(v == "present" for v in self.prior.status.values())
        if self.prior.relocalised and self.prior.fit is not None:
            self._write_relocalisation()
        return step

    def _write_relocalisation(self) -> None:
        """DIR/relocalization.json: the fit, for the record and for tools (written once)."""
        if self.out_dir is None or self.prior is None or self.prior.fit is None:
            return
        target = self.out_dir / "relocalization.json"
        if target.exists():
            return
        fit = self.prior.fit
        body = {"frame_id": self.prior.aligned_at, "inliers": fit.inliers, "runner_up": fit.runner_up,
                "rms_m": fit.rms_m, "rotation_sigma_deg": fit.rotation_sigma_deg, "refined_on_clouds": fit.refined,
                "matches": [list(m) for m in fit.matches],
                "transform": [float(v) for v in fit.transform.reshape(16)], "attempts": self.prior.attempts}
        tmp = target.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(body, indent=1))
        tmp.replace(target)

    def _on_query(self, query) -> None:  # noqa: ANN001 - zenoh.Query, answered on a Zenoh thread
        try:
            spec = MapQuery.from_parameters(dict(query.parameters))
        except QueryError as exc:
            query.reply_err(str(exc).encode())
            return
        self.metrics.count("queries")
        query.reply(self.bus.keys.map_query, reply_document(run_query(spec, self.snapshot)))

    # -- inputs ---------------------------------------------------------------------------------------------
    def on_odometry(self, pose: OdometryPose) -> None:
        self._journal("odometry", pose)
        self.stage.odometry(pose.frame_id, pose.pose)
        self._drain()

    def on_tracks(self, tracks: Tracks) -> None:
        self._journal("tracks", tracks)
        if self.session_start is None or tracks.stamp < self.session_start:
            self.session_start = tracks.stamp
        if not self.tracks.push(tracks.frame_id, tracks):
            self.metrics.count("tracks_duplicates")
            if self.muted:  # (a resent frame, journalled: it changed nothing then either)
                return
            if self.stage.awaiting is not None and self.stage.awaiting[0].frame_id == tracks.frame_id:
                self.obs_pub.put(self._awaited_observations)  # the backend may have lost them
            elif (not any(t.frame_id == tracks.frame_id for t in self.ready) and not self.replay(tracks.frame_id)
                  and tracks.frame_id <= self.completed_frame):
                # completed before a crash (it is in the saved map) but its progress may have died with the
                # process: say it again, or a lockstep run waits for it for ever
                self.report_progress(tracks.frame_id)
            return
        self._release()

    def on_frame_unreadable(self, frame_id: int) -> None:
        # (the tracker may have answered it as a frame the detector never got: nothing in it, drop it too)
        self.tracks.skip(frame_id)
        self.ready = [t for t in self.ready if t.frame_id != frame_id]
        self._release()

    def _release(self) -> None:
        self.ready.extend(self.tracks.pop_ready())
        self._drain()

    def on_corrected(self, msg: CorrectedPoses) -> None:
        # journalled like the inputs: a replay must apply each correction where it came (between the same
        # frames), or the frames after the last save are associated and refined against other poses
        self._journal("corrected", msg)
        held = self.stage.corrected(msg)
        self.metrics.count("corrections")
        if held is not None:
            tracks, step = held
            self._complete(tracks, step)
            self._drain()
        elif not self.await_backend and self.stage.refine_due(msg.frame_id):
            self._complete_refine_only(msg.frame_id)

    # -- per frame ------------------------------------------------------------------------------------------
    def _drain(self) -> None:
        while (self.stage.awaiting is None and self.ready
               and self.stage.pose_known_or_lost(self.ready[0].frame_id, self.lockstep)):
            tracks = self.ready.pop(0)
            with self.metrics.timer("process_ms"):
                step = self.stage.process(tracks.frame_id, tracks.stamp, tracks.candidates, tracks.ended,
                                          None if tracks.skipped else tracks.boxes)
            for stage, ms in step.timing_ms.items():
                self.metrics.time_ms(f"{stage}_ms", ms)
            if self.prior is not None:
                step = self._prior_step(tracks, step)
            self.metrics.count("candidates_rejected", len(step.rejected))
            self.metrics.count("observations", len(step.observations))
            merges = self.stage.take_merges(step)
            observations = Observations(self.robot, tracks.frame_id, tracks.stamp, step.observations, merges,
                                        alignment=self._alignment, retired=list(step.moved))
            self._alignment = None
            self._awaited_observations = observations
            self.emit(self.obs_pub, observations, tracks.frame_id)
            if step.observations:
                self.emit(self.tags_pub, TagDetections(self.robot, tracks.frame_id, tracks.stamp,
                                                       [TagDetection.from_observation(o) for o in step.observations]),
                          tracks.frame_id)
            # (replaying the journal too: the backend's answer comes from the journal, where it came before)
            if not self.stage.hold(tracks, step):
                self._complete(tracks, step)


    def _complete(self, tracks: Tracks, step: MapperStep) -> None:
        step, refine_ms = self.stage.complete(tracks.frame_id, tracks.stamp, step)
        self.completed_frame = max(self.completed_frame, tracks.frame_id)
        if refine_ms:
            self.metrics.time_ms("refine_ms", refine_ms)
        self._publish_map(step, tracks.frame_id, tracks.stamp, frame_sent_at=tracks.frame_sent_at,
                          refine_ms=refine_ms)
        self.metrics.count("frames")
        self.report_progress(tracks.frame_id)

    def _complete_refine_only(self, frame_id: int) -> None:
        refined = self.stage.refine_only()
        if refined.updated or refined.removed or refined.merges:
            self._publish_map(refined, max(self.last_frame_id, 0), 0.0)

    def _publish_map(self, step: MapperStep, frame_id: int, stamp: float, full: bool = False,
                     frame_sent_at: float = 0.0, refine_ms: float = 0.0) -> None:
        self.map_seq += 1
        if frame_sent_at > 0:  # from the frame's publication to its map update: the pipeline's latency
            self.metrics.time_ms("end_to_end_ms", (time.time() - frame_sent_at) * 1e3)
        landmarks = self._landmarks() if full else (step.updated if self.prior is None
                                                              else self.prior.with_status(step.updated))
        timing = dict(step.timing_ms)
        if refine_ms:
            timing["refine"] = refine_ms
        self.emit(self.map_pub, MapUpdate(self.robot, self.map_seq, max(frame_id, 0), stamp, landmarks, step.removed,
                                          step.merges, full, step.rejected, timing, frame_sent_at,
                                          moved=list(step.moved), moving_tracks=list(step.moving_tracks)),
                  max(frame_id, 0))
        for lid in step.moved:
            self.log.info("retired landmark %d: its object moved", lid)
        self.metrics.count("landmarks_retired_moving", len(step.moved))
        structural = False
        if step.updated or step.removed or step.merges or full:  # most frames change nothing
            known = {lm.id for lm in self.snapshot}
            self.snapshot = self._landmarks()
            self.dirty = True
            # a new, removed or merged landmark is saved at once (a crash must not lose it); refinements of
            # existing ones at most once a second
            structural = bool(step.removed or step.merges or {lm.id for lm in self.snapshot} - known)
        self.metrics.counters["landmarks"] = len(self.snapshot)
        self.metrics.count("merges", len(step.merges))
        for absorbed, survivor in step.merges:
            self.log.info("merged landmark %d into %d", absorbed, survivor)
        if self.dirty and (structural or time.monotonic() - self.last_saved > SAVE_PERIOD_S):
            self._save()

    # -- persistence ----------------------------------------------------------------------------------------
    def _journal(self, stream: str, message: Tracks | OdometryPose | CorrectedPoses) -> None:
        if self.journal is not None and not self.muted:
            with self.metrics.timer("journal_ms"):
                self.journal_seq = self.journal.append(stream, message.encode())

    def _restore(self) -> None:
        """The saved map, its pose book and where in the journal it stopped (inputs after that come next)."""
        assert self.store is not None
        state = self.store.load()
        if state is None:
            return
        self.stage.restore(state)
        self.journal_seq = int(state.get("journal_seq", 0))
        # frames up to the saved one are in the map: one that comes again (resent) is not mapped twice
        self.completed_frame = int(state.get("completed_frame", -1))
        if self.completed_frame >= 0:
            self.tracks.mark_done(self.completed_frame)
            self.last_frame_id = self.completed_frame
        if state.get("session_start") is not None:
            self.session_start = float(state["session_start"])
        if self.prior is not None:
            self.prior.restore(state.get("prior"))
        self.log.info("restored %d landmarks from %s", len(self.mapper.landmarks()), self.store.path)

    def _replay_journal(self) -> None:
        """Handle the inputs journalled after the saved map again (muted: their outputs went out before the
        crash), so a restart goes on from the last input handled, not from the last save: losing even a few
        frames of a tracklet's views can flip its motion test and take an established landmark with it."""
        if self.journal is None or not self.restoring:
            return
        kinds = {"odometry": (OdometryPose, self.on_odometry), "tracks": (Tracks, self.on_tracks),
                 "corrected": (CorrectedPoses, self.on_corrected)}
        n = 0
        self.muted = True
        try:
            for seq, stream, body in self.journal.entries(self.journal_seq):
                kind, handler = kinds[stream]
                self._guarded(handler, kind.decode(body), f"journalled {stream}")
                self.journal_seq = seq
                n += 1
        finally:
            self.muted = False
        if n:
            self.log.info("replayed %d journalled inputs (to frame %d)", n, self.last_frame_id)
            self.snapshot = self._landmarks()
            self._save()

    def _save(self) -> None:
        # not while a frame is held for the backend: its tracks are in the journal up to here, and a save would
        # drop them from it though the frame is not complete (a restart would never refine it)
        if self.muted or self.stage.awaiting is not None:
            self.dirty = True
            return
        with self.metrics.timer("save_ms"):
            if self.store is not None:
                self.store.save({**self.stage.to_state(), "journal_seq": self.journal_seq,
                                 "completed_frame": self.completed_frame, "session_start": self.session_start,
                                 "prior": None if self.prior is None else self.prior.to_state()})
                if self.journal is not None:
                    self.journal.truncate(self.journal_seq)
            if self.out_dir is not None:
                write_map_json(self.out_dir / "map.json", self.snapshot)
        self.last_saved = time.monotonic()
        self.dirty = False

    def on_end_of_stream(self, control: Control) -> None:
        if self.last_frame_id >= control.last_frame_id and self.stage.awaiting is None:
            self.finish()

    def write_outputs(self) -> None:
        self.snapshot = self._landmarks()
        self._save()
        if self.prior is not None and not self.prior.relocalised:
            reason = self.prior.last_attempt.reason if self.prior.last_attempt is not None else "too few landmarks"
            self.log.warning("never relocalised against the prior map (%d attempts; last: %s): the map is in this "
                             "session's own frame and holds none of the prior landmarks", self.prior.attempts, reason)

    def teardown(self) -> None:
        self._queryable.undeclare()
        if self.journal is not None:
            self.journal.close()


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--await-backend", action="store_true",
                        help="lockstep: wait for the backend's corrected poses of each frame before the next")
    parser.add_argument("--prior-map", type=Path, default=None,
                        help="map.sqlite of a prior run: relocalise against it, then map in its frame (docs/MAPS.md)")
    parser.add_argument("--map-db", type=Path, default=None,
                        help="SQLite file of a persistent map, loaded at start if present (default: DIR/map.sqlite, "
                             "loaded only with --resume)")


def main(argv: list[str] | None = None) -> int:
    return service_main(AssociatorService, argv, _arguments)

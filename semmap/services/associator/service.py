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
import math
import time
from pathlib import Path

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperStep
from semmap.algorithms.associator.pose_book import PoseBook
from semmap.core.journal import MessageJournal
from semmap.core.messages import (
    Control,
    CorrectedPoses,
    Landmark,
    MapUpdate,
    OdometryPose,
    TagDetection,
    TagDetections,
    Tracks,
)
from semmap.runtime.maps.map_query import MapQuery, QueryError, reply_document, run_query
from semmap.runtime.maps.map_store import MapStore, write_map_json
from semmap.runtime.pipeline.stages import AssociatorStage, PriorFrame
from semmap.runtime.transport.service import service_main
from semmap.runtime.transport.stage_service import StageService

SAVE_PERIOD_S = 1.0  # refinements of existing landmarks are saved at most this often
# ... and no save comes sooner than its own duration / SAVE_SHARE after the last: a save writes the whole map, so on
# a street of thousands of landmarks saving at every new one would take most of the associator's time (the input
# journal keeps whatever came after a save, so a crash loses nothing either way)
SAVE_SHARE = 0.05
REALTIME_MAX_PENDING = 8  # tracks of later frames that may wait for a missing one (real time)


class AssociatorService(StageService):
    """Maps validated candidates to landmarks (see module docstring).

    Unlike the other stage services it snapshots its state (the map, `map.sqlite`) now and then and journals its
    inputs in between (`map.journal.sqlite`), as the map is too large to journal with every frame."""

    name = "associator"
    yields_to_front_end = True  # (real time: see StageService.yield_to_front_end)
    realtime_max_pending = REALTIME_MAX_PENDING
    duplicates_counter = "tracks_duplicates"

    def setup_stage(self) -> None:
        self.params = self.config.associator  # the mapper's settings, the service's own and the prior map's
        self.await_backend = bool(self.args.await_backend) and self.lockstep
        # the per-frame policy (pose book, waiting on the backend, refinement, carried-over merges, a prior map) is
        # the stage's (semmap/runtime/pipeline/stages.py); this service decodes, re-orders, journals, persists,
        # publishes
        self.stage = AssociatorStage(self.params, self.params.refine_every_n_frames, self.await_backend)
        self.snapshot: list[Landmark] = []  # what map queries answer from (swapped whole, read from Zenoh threads)
        self.ready: list[Tracks] = []
        self.map_seq = 0
        self.completed_frame = -1  # the newest frame completed (what a save includes)
        self.last_saved = 0.0
        self.last_save_s = 0.0  # how long the last save took (saves are spaced by it: SAVE_SHARE)
        self.dirty = False
        db = self.args.map_db or (self.out_dir / "map.sqlite" if self.out_dir is not None else None)
        self.store = MapStore(db) if db is not None else None
        self.inputs_journal = MessageJournal(db.with_name(f"{db.stem}.journal.sqlite")) if db is not None else None
        self.journal_seq = 0  # the last journalled input the saved map includes
        if self.args.prior_map is not None:
            self._load_prior(self.args.prior_map)
        self.open_outputs()

    def resuming(self) -> bool:
        return self.store is not None and bool(self.resume or self.args.map_db)

    def start_afresh(self) -> None:
        if self.store is not None and self.inputs_journal is not None:  # a new run: nothing of an earlier one
            self.store.clear()
            self.inputs_journal.clear()

    def subscribe(self) -> None:
        self.snapshot = self.stage.landmarks()
        self._queryable = self.bus.session.declare_queryable(self.bus.keys.map_query, self._on_query)
        super().subscribe()

    def restored(self) -> None:
        self._replay_journal()
        if self.stage.awaiting is not None:  # the replay ended on a frame held for the backend, which may never
            self.out["observations"].put(self._awaited_observations)  # have got its observations: they go (again) now
        if self.snapshot:
            self._publish_map(MapperStep(), self.last_frame_id, 0.0, full=True)

    @property
    def mapper(self) -> LandmarkMapper:
        return self.stage.mapper

    @property
    def poses(self) -> PoseBook:
        return self.stage.poses

    def _load_prior(self, path: Path) -> None:
        """The prior map this session relocalises against (its landmarks join the map once it has)."""
        prior = self.stage.load_prior(path, self.params.prior())
        self.metrics.counters["prior_landmarks"] = len(prior.prior)
        self.metrics.counters["relocalised"] = 0
        self.log.info("prior map %s: %d landmarks; mapping in a provisional frame (this session's odometry) until "
                      "the session relocalises against it", path, len(prior.prior))

    def _count_prior(self, frame_id: int, frame: PriorFrame) -> None:
        """Count and log what the prior map did on this frame (`AssociatorStage.prior_step`)."""
        prior = self.stage.prior
        if prior is None:
            return
        if frame.relocalize_ms is not None:
            self.metrics.time_ms("relocalize_ms", frame.relocalize_ms)
        fit = frame.relocalised
        if fit is not None:
            t = fit.translation
            self.log.info("relocalised at frame %d: %d landmarks agree (next best placement %d), residual "
                          "%.1f cm%s; translation (%.3f, %.3f, %.3f) m, rotation %.2f deg; now mapping in the "
                          "prior map's frame", frame_id, fit.inliers, fit.runner_up, 100 * fit.rms_m,
                          ", refined on clouds" if fit.refined else "", t[0], t[1], t[2], fit.rotation_deg)
            self.metrics.counters.update(relocalised=1, relocalised_at_frame=frame_id,
                                         relocalised_inliers=fit.inliers)
        counters = self.stage.prior_counters()
        if frame.relocalize_ms is not None:
            self.metrics.counters["relocalize_attempts"] = counters["relocalize_attempts"]
        if frame.statuses_changed:
            self.metrics.counters["prior_missing"] = counters["prior_missing"]
            self.metrics.counters["prior_seen_again"] = counters["prior_seen_again"]
        if prior.relocalised and prior.fit is not None:
            self._write_relocalisation()

    def _write_relocalisation(self) -> None:
        """DIR/relocalization.json: the fit, for the record and for tools (written once)."""
        record = self.stage.relocalisation_record()
        if self.out_dir is None or record is None:
            return
        target = self.out_dir / "relocalization.json"
        if target.exists():
            return
        tmp = target.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(record, indent=1))
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
        self.stage.saw_stamp(tracks.stamp)
        self.receive(tracks)

    def on_resent(self, tracks: Tracks) -> None:
        if self.muted:  # (a resent frame, journalled: it changed nothing then either)
            return
        if self.stage.awaiting is not None and self.stage.awaiting[0].frame_id == tracks.frame_id:
            self.out["observations"].put(self._awaited_observations)  # the backend may have lost them
        elif (not any(t.frame_id == tracks.frame_id for t in self.ready) and not self.replay(tracks.frame_id)
              and tracks.frame_id <= self.completed_frame):
            # completed before a crash (it is in the saved map) but its progress may have died with the
            # process: say it again, or a lockstep run waits for it for ever
            self.report_progress(tracks.frame_id)

    def on_frame_unreadable(self, frame_id: int) -> None:
        # (the tracker may have answered it as a frame the detector never got: nothing in it, drop it too)
        self.ready = [t for t in self.ready if t.frame_id != frame_id]
        super().on_frame_unreadable(frame_id)

    def handle(self, tracks: Tracks) -> None:
        """A frame's tracks, in order: mapped once its pose is known (and no frame is held for the backend)."""
        self.ready.append(tracks)
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
            self._map_frame(self.ready.pop(0))

    def _map_frame(self, tracks: Tracks) -> None:
        """One frame through the stage: its observations go to the backend; in lockstep the frame is then held
        for the backend's answer, else completed at once."""
        boxes = None if tracks.skipped else tracks.boxes
        with self.metrics.timer("process_ms"):
            step = self.stage.process(tracks.frame_id, tracks.stamp, tracks.candidates, tracks.ended, boxes)
        for stage, ms in step.timing_ms.items():
            self.metrics.time_ms(f"{stage}_ms", ms)
        revisit = self.stage.last_revisit
        if revisit is not None:
            t = revisit.transform[:3, 3]
            self.log.info("revisit at frame %d: %d landmarks seen before (next best placement %d, residual %.2f m, "
                          "drift since %.1f m): fused into the old ones", tracks.frame_id, len(revisit.pairs),
                          revisit.runner_up, revisit.rms_m, math.hypot(*t))
        self.metrics.counters.update(self.stage.revisits.counters())
        prior = self.stage.prior_step(tracks.frame_id, tracks.stamp, boxes, step)
        self._count_prior(tracks.frame_id, prior)
        step = prior.step
        self.metrics.count("candidates_rejected", len(step.rejected))
        self.metrics.count("observations", len(step.observations))
        observations = self.stage.observations(self.robot, tracks.frame_id, tracks.stamp, step)
        self._awaited_observations = observations
        self.emit(self.out["observations"], observations, tracks.frame_id)
        if step.observations:
            self.emit(self.out["observations/tags"], TagDetections(self.robot, tracks.frame_id, tracks.stamp,
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
        landmarks = self.stage.landmarks() if full else self.stage.with_status(step.updated)
        timing = dict(step.timing_ms)
        if refine_ms:
            timing["refine"] = refine_ms
        update = MapUpdate(self.robot, self.map_seq, max(frame_id, 0), stamp, landmarks, step.removed, step.merges,
                           full, step.rejected, timing, frame_sent_at, moved=list(step.moved),
                           moving_tracks=list(step.moving_tracks))
        self.emit(self.out["map/updates"], update, max(frame_id, 0))
        for lid in step.moved:
            self.log.info("retired landmark %d: its object moved: %s", lid, step.moved_why.get(lid, "(no evidence)"))
        self.metrics.count("landmarks_retired_moving", len(step.moved))
        for lid in step.kept_despite_motion:
            self.log.info("kept landmark %d: a track of it moved, but inside it: %s", lid,
                          step.moved_why.get(lid, "(no evidence)"))
        self.metrics.count("landmarks_kept_despite_moving_track", len(step.kept_despite_motion))
        self._map_changed(step, full)

    def _map_changed(self, step: MapperStep, full: bool) -> None:
        """Refresh what queries answer from and save when due: a new, removed or merged landmark at once while saves
        are cheap, refinements of existing ones at most once a second (most frames change nothing); a large map's
        saves are spaced so that saving takes at most SAVE_SHARE of the time."""
        structural = False
        if step.updated or step.removed or step.merges or full:
            known = {lm.id for lm in self.snapshot}
            self.snapshot = self.stage.landmarks()
            self.dirty = True
            structural = bool(step.removed or step.merges or {lm.id for lm in self.snapshot} - known)
        self.metrics.counters["landmarks"] = len(self.snapshot)
        self.metrics.count("merges", len(step.merges))
        for absorbed, survivor in step.merges:
            self.log.info("merged landmark %d into %d", absorbed, survivor)
        since = time.monotonic() - self.last_saved
        if self.dirty and since > self.last_save_s / SAVE_SHARE and (structural or since > SAVE_PERIOD_S):
            self._save()

    # -- persistence ----------------------------------------------------------------------------------------
    def _journal(self, stream: str, message: Tracks | OdometryPose | CorrectedPoses) -> None:
        seq = self.journal_input(self.inputs_journal, stream, message)
        if seq is not None:
            self.journal_seq = seq

    def restore(self) -> None:
        """The saved map, its pose book and where in the journal it stopped (inputs after that come next)."""
        assert self.store is not None
        state = self.store.load()
        if state is None:
            return
        self.stage.restore(state)  # (with the prior map's relocalisation and statuses)
        self.journal_seq = int(state.get("journal_seq", 0))
        # frames up to the saved one are in the map: one that comes again (resent) is not mapped twice
        self.completed_frame = int(state.get("completed_frame", -1))
        if self.completed_frame >= 0:
            self.resume_after(self.completed_frame)
        self.log.info("restored %d landmarks from %s", len(self.mapper.landmarks()), self.store.path)

    def _replay_journal(self) -> None:
        """Handle the inputs journalled after the saved map again (muted: their outputs went out before the
        crash), so a restart goes on from the last input handled, not from the last save: losing even a few
        frames of a tracklet's views can flip its motion test and take an established landmark with it."""
        if self.inputs_journal is None or not self.resuming():
            return
        kinds = {"odometry": (OdometryPose, self.on_odometry), "tracks": (Tracks, self.on_tracks),
                 "corrected": (CorrectedPoses, self.on_corrected)}
        n, last = self.replay_inputs(self.inputs_journal.entries(self.journal_seq), kinds)
        if last is not None:
            self.journal_seq = last
        if n:
            self.log.info("replayed %d journalled inputs (to frame %d)", n, self.last_frame_id)
            self.snapshot = self.stage.landmarks()
            self._save()

    def _save(self) -> None:
        # not while a frame is held for the backend: its tracks are in the journal up to here, and a save would
        # drop them from it though the frame is not complete (a restart would never refine it)
        if self.muted or self.stage.awaiting is not None:
            self.dirty = True
            return
        t0 = time.perf_counter()
        with self.metrics.timer("save_ms"):
            if self.store is not None:
                self.store.save({**self.stage.to_state(), "journal_seq": self.journal_seq,
                                 "completed_frame": self.completed_frame})
                if self.inputs_journal is not None:
                    self.inputs_journal.truncate(self.journal_seq)
            if self.out_dir is not None:
                write_map_json(self.out_dir / "map.json", self.snapshot)
        self.last_saved = time.monotonic()
        self.last_save_s = time.perf_counter() - t0
        self.dirty = False

    def on_end_of_stream(self, control: Control) -> None:
        self.count_frames_before_the_first(control)
        if self.last_frame_id >= control.last_frame_id and self.stage.awaiting is None:
            self.finish()

    def write_outputs(self) -> None:
        self.snapshot = self.stage.landmarks()
        self._save()
        prior = self.stage.prior
        if prior is not None and not prior.relocalised:
            reason = prior.last_attempt.reason if prior.last_attempt is not None else "too few landmarks"
            self.log.warning("never relocalised against the prior map (%d attempts; last: %s): the map is in this "
                             "session's own frame and holds none of the prior landmarks", prior.attempts, reason)

    def teardown(self) -> None:
        self._queryable.undeclare()
        if self.inputs_journal is not None:
            self.inputs_journal.close()


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

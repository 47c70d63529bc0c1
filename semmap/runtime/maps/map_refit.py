"""Re-optimise a saved run's trajectory in another map's frame before its landmarks are fused (`semmap merge`).

Why: a rigid transform of map B onto map A (the objects' fit) carries B's own drift along: a 500-frame session
on drifting odometry is bent by degrees, 14-16 cm at its far objects (docs/MAPS.md). When B is a run directory,
its backend journal holds every frame's odometry, observations and keyframe cloud, so B is replayed as a session
relocalised against A would have run: its odometry taken through the fit from the first frame, B's landmarks that
the fit paired held at A's positions, B's keyframes registered to A's run's keyframes (when A is a run directory
too); then B's stored landmark views are re-placed with the new poses and re-estimated, as the associator does
when the pose graph changes (`LandmarkMapper.refine`).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import msgspec
import numpy as np

from semmap.algorithms.associator.mapper import LandmarkMapper
from semmap.algorithms.backend.loop_closure import decode_keyframe
from semmap.algorithms.backend.pose_graph import PoseGraphError
from semmap.algorithms.relocalize import RelocResult
from semmap.core.config import Config
from semmap.core.journal import read_frames
from semmap.core.messages import Landmark, MapAlignment, MessageError, Observations, OdometryPose
from semmap.runtime.maps.map_store import MapStore
from semmap.runtime.maps.prior_keyframes import load_prior_keyframes
from semmap.runtime.pipeline.stages import BackendStage


@dataclass
class Refit:
    landmarks: list[Landmark]  # B's, in A's frame
    clouds: dict[int, np.ndarray]  # their world clouds, in A's frame
    frames: int = 0  # B's frames replayed
    skipped: int = 0  # journal rows that could not be decoded
    prior_keyframes: int = 0  # A's keyframes B's were registered to ...
    closures_to_a: int = 0  # ... and the registrations accepted
    counters: dict[str, int] = field(default_factory=dict)


def refit_run(b_map_db: Path, a_map_db: Path | None, fit: RelocResult, a_landmarks: list[Landmark],
              config: Config | None = None) -> Refit | str:
    """B (its map.sqlite, beside its run's backend.sqlite) re-optimised in A's frame; a reason (str) when B's run
    does not hold what it takes, and the caller falls back to the rigid transform."""
    config = config or Config()
    journal = Path(b_map_db).parent / "backend.sqlite"
    if not journal.is_file():
        return f"{journal} not found"
    state = MapStore.open_existing(Path(b_map_db)).load()
    if state is None:
        return f"{b_map_db} holds no map"
    try:
        mapper = LandmarkMapper.from_state(state, config.associator)
    except (KeyError, TypeError, ValueError) as exc:
        return f"{b_map_db}: unreadable map state: {exc}"
    a_at = {lm.id: lm.centroid for lm in a_landmarks}
    # B's map is in B's map frame; its odometry in B's session frame, which differ where B was itself started
    # from a prior map and relocalised: then the odometry goes through B's own transform (its saved session's) first
    own = (state.get("prior") or {}).get("transform")
    to_a = fit.transform if own is None else fit.transform @ np.asarray(own, dtype=np.float64).reshape(4, 4)
    anchors = [(b_id, a_at[a_id]) for b_id, a_id in fit.matches if a_id in a_at]
    residual = fit.cloud_rms_m if fit.refined and fit.cloud_rms_m is not None else fit.rms_m
    alignment = MapAlignment(np.array(to_a, dtype=np.float64), anchors, config.associator.prior_anchor_sigma_m,
                             fit.inliers, float(residual))
    stage = BackendStage(config.backend, config.loop_closure, config.corrections, expect_alignment=True)
    if a_map_db is not None and config.loop_closure.enabled:
        stage.closer.set_prior(load_prior_keyframes(Path(a_map_db), config.loop_closure.max_keyframes).keyframes)
    out = Refit([], {}, prior_keyframes=len(stage.closer.prior))
    try:
        for _, odometry, observations, keyframe in read_frames(journal):
            try:
                pose, obs = OdometryPose.decode(odometry), Observations.decode(observations)
                cloud = None if keyframe is None else decode_keyframe(keyframe)[0]
            except (MessageError, msgpack.UnpackException, ValueError, KeyError, TypeError):
                out.skipped += 1
                continue
            # B's own alignment (if it was itself relocalised) is folded into A's, given at its first frame
            obs = msgspec.structs.replace(obs, alignment=alignment if out.frames == 0 else None)
            try:
                stage.step(pose, obs, cloud)
            except PoseGraphError:  # (a row the graph refuses, e.g. a pose that is not rigid: skipped)
                out.skipped += 1
                continue
            out.frames += 1
    except sqlite3.Error as exc:
        return f"{journal}: unreadable: {exc}"
    if out.frames == 0:
        return f"{journal} holds no frames"
    ids, _, poses = stage.graph.corrected_poses()
    by_frame = {int(f): poses[i] for i, f in enumerate(ids)}
    mapper.move_frame(fit.transform)  # (B's map frame to A's: what no replayed pose re-places, e.g. frozen views)
    mapper.refine(by_frame.get)
    out.landmarks = mapper.landmarks()
    out.clouds = {lm.id: lm.cloud for lm in mapper.map.all() if len(lm.cloud)}
    out.closures_to_a = stage.closer.counters["prior_accepted"]
    out.counters = dict(stage.closer.counters)
    return out

"""Revisits: a place seen again after drift, recognised by its objects, closes the loop.

The validation gate (association.py) joins a candidate to a landmark only within sqrt(dt / u * s) of it. After
kilometres of odometry drift, the parked cars of a street driven again lie metres to tens of metres from where the
map holds them, beyond any gate: the mapper makes new landmarks, and nothing tells the backend that the car is
where it was before. The paper closes such loops through revisited objects; this module finds the revisits.

Every `revisit_every_s` the landmarks of the recent past (first seen within `revisit_recent_s`, with at least
`revisit_min_views` views) are placed against the map's old ones (last seen more than `revisit_old_s` ago) by the
relocalisation search (relocalize.py: class-consistent triples, one-to-one inliers, a distinct runner-up refused),
with tolerances that follow the objects' size (`revisit_gate_size_factor` of the recent landmarks' median size: a
car's centroid moves by tens of centimetres with the side it is seen from, a cup's by a centimetre). The drift over
the recent window is small, so the recent landmarks are one rigid body against the old ones. A confident fit names
pairs (recent id, old id) of one object each; the caller fuses every recent landmark into its old id
(`LandmarkMapper.fuse`), and the backend's merge factor (not robust, on purpose: a merge is a loop closure) pulls
the trajectory together. A wrong revisit would bend the map, so the fit must have `revisit_min_inliers` agreeing
objects (5: a street has rows of parked cars, and three or four in a row agree with many places) and beat every
distinct alternative.

Pure: landmarks in, pairs out (the associator stage in runtime/pipeline.py calls it, for the services and the
in-process driver alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semmap.algorithms.relocalize import MapObject, RelocParams, relocalize

from .landmark_map import LandmarkState
from .params import MapperParams


@dataclass
class Revisit:
    """One recognised revisit: `pairs` (recent id, old id) of one object each, and the fit that found them."""

    stamp: float
    pairs: list[tuple[int, int]]
    transform: np.ndarray  # recent landmarks' frame -> the old ones' (the drift gathered since)
    rms_m: float
    runner_up: int


class RevisitFinder:
    """When to look and what a look found (`search`); its clock and counters are its state."""

    def __init__(self, params: MapperParams) -> None:
        self.params = params
        self.last_search = float("-inf")
        self.searches = 0
        self.found = 0
        self.fused = 0

    def reloc_params(self, size_m: float) -> RelocParams:
        """The relocalisation's tolerances for objects of median size `size_m` (a car's centroid wanders by tens of
        centimetres with the side it is seen from, a cup's by centimetres)."""
        p = self.params
        gate = max(p.revisit_gate_min_m, p.revisit_gate_size_factor * size_m)
        return RelocParams(min_inliers=p.revisit_min_inliers, inlier_gate_m=gate, max_rms_m=0.5 * gate,
                           pair_tol_m=0.7 * gate, min_triangle_m=gate, distinct_m=gate,
                           max_rotation_sigma_deg=p.revisit_max_rotation_sigma_deg, centroid_sigma_floor_m=0.2,
                           max_hypotheses=p.revisit_max_hypotheses, max_thirds=p.revisit_max_thirds)

    def due(self, stamp: float) -> bool:
        return self.params.revisit and stamp - self.last_search >= self.params.revisit_every_s

    def search(self, landmarks: list[LandmarkState], stamp: float) -> Revisit | None:
        """Recent landmarks against old ones (see module docstring); None when there is no confident revisit."""
        p = self.params
        self.last_search = stamp
        recent = [lm for lm in landmarks if lm.first_seen >= stamp - p.revisit_recent_s
                  and len(lm.views) >= p.revisit_min_views]
        old = [lm for lm in landmarks if lm.last_seen <= stamp - p.revisit_old_s and lm.views]
        if len(recent) < p.revisit_min_inliers or len(old) < p.revisit_min_inliers:
            return None
        self.searches += 1
        size = float(np.median([lm.size for lm in recent]))
        attempt = relocalize([_object(lm) for lm in recent], [_object(lm) for lm in old], self.reloc_params(size))
        fit = attempt.result
        if fit is None:
            return None
        self.found += 1
        pairs = sorted((int(q), int(o)) for q, o in fit.matches)
        return Revisit(stamp, pairs, fit.transform, fit.rms_m, fit.runner_up)

    def to_state(self) -> dict:
        last = None if not np.isfinite(self.last_search) else self.last_search
        return {"last_search": last, "searches": self.searches, "found": self.found, "fused": self.fused}

    def restore(self, state: dict | None) -> None:
        state = state or {}
        last = state.get("last_search")
        self.last_search = float("-inf") if last is None else float(last)
        self.searches, self.found = int(state.get("searches", 0)), int(state.get("found", 0))
        self.fused = int(state.get("fused", 0))

    def counters(self) -> dict[str, int]:
        return {"revisit_searches": self.searches, "revisits": self.found, "revisit_fused_landmarks": self.fused}


def _object(lm: LandmarkState) -> MapObject:
    return MapObject(lm.id, lm.class_name, np.asarray(lm.centroid, float))

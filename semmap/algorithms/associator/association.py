"""Candidate-to-landmark association: the paper's validation gate and nearest-neighbour step, made safer.

Paper: a candidate may join a same-class landmark whose centroid lies within r = sqrt(dt / u * s) of the
candidate's centroid (dt: seconds since that landmark was last associated, s: object size, u = 10): the
longer an object was out of sight, the more the pose may have drifted meanwhile. None in the gate -> a new
landmark; one -> associate; several -> the one with the smallest mean nearest-neighbour distance from the
candidate's cloud to the landmark's cloud.

Where we go beyond it, and why:
- Gate floor max(gate_min_m, gate_size_factor * s). The paper's r -> 0 when dt -> 0, but a landmark that
  was associated a moment ago is exactly the one a broken-and-restarted tracklet must rejoin: its centroid
  error then is not drift but the per-view scatter of partial views, which grows with the object's size
  (measured 3-6 cm for small objects, up to ~0.3 s for chairs). Half the size covers that, and 0.1 m keeps
  two cups 15 cm apart in separate gates.
- Co-visibility veto: a landmark measured in `covis_veto_frames` of the candidate's own frames by another
  tracklet is a different object seen side by side (two cups, two chairs), whatever the distances say.
- Cloud check for a single landmark in the gate unless the centroids are clearly close: the clouds must
  overlap (trimmed mean NN distance <= max(nn_accept_min_m, nn_accept_size_factor * s, the gate's drift
  allowance)); a near-by same-class object whose centroid happens to fall into the gate gets its own landmark.
- Ambiguity hold: when several landmarks pass and the best NN distance is not clearly better than the
  second (ratio above `ambiguity_ratio`), the candidate is held back (no landmark changes) until more of its
  views arrive, at most until `hold_max_views` views or the tracklet ends; then the best one is taken.
The NN distance is a trimmed mean (largest 20% left out) so background caught in one box does not decide.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .landmark_map import LandmarkState
from .params import MapperParams


def gate_radius(dt_s: float, size_m: float, p: MapperParams) -> float:
    """Validation gate: max(paper's sqrt(dt / u * s), the floor max(gate_min_m, gate_size_factor * s))."""
    return float(gate_radii(np.asarray(dt_s, dtype=np.float64), np.asarray(size_m, dtype=np.float64), p))


def gate_radii(dt_s: np.ndarray, size_m: np.ndarray, p: MapperParams) -> np.ndarray:
    """`gate_radius` over arrays (one gate per landmark): the one place the gate's formula is written."""
    paper = np.sqrt(np.maximum(dt_s, 0.0) / p.gate_u * np.maximum(size_m, 0.0))
    return np.maximum(paper, np.maximum(p.gate_min_m, p.gate_size_factor * size_m))


def gate_floor(size_m: float, p: MapperParams) -> float:
    return float(gate_radii(np.zeros(()), np.asarray(size_m, dtype=np.float64), p))


def trimmed_mean(values: np.ndarray, trim: float) -> float:
    if len(values) == 0:
        return float("inf")
    keep = max(1, int(math.ceil(len(values) * (1.0 - trim))))
    return float(np.mean(np.partition(values, keep - 1)[:keep]))


def nn_distance(cloud: np.ndarray, lm: LandmarkState, trim: float) -> float:
    """Trimmed mean distance from each candidate point to its nearest landmark point."""
    if len(cloud) == 0 or len(lm.cloud) == 0:
        return float("inf")
    d, _ = lm.tree().query(cloud, k=1)
    return trimmed_mean(d, trim)


def near_enough(
    centroid: np.ndarray, size: float, landmarks: list[LandmarkState], stamp: float, p: MapperParams
) -> list[LandmarkState]:
    """The landmarks (with views) whose gate may hold `centroid`, found with array arithmetic: a street-scale map
    holds a thousand cars, and one Python distance per landmark per candidate would grow with the map. The
    bound is the gate radius itself with a small tolerance (the exact test follows, per landmark)."""
    live = [lm for lm in landmarks if lm.views]
    if len(live) <= 16:
        return live
    c = np.array([lm.centroid for lm in live], dtype=np.float64)
    s = np.maximum(np.array([lm.size for lm in live]), size)
    dt = np.maximum(stamp - np.array([lm.last_assoc for lm in live]), 0.0)
    r = gate_radii(dt, s, p)
    d = np.linalg.norm(c - centroid, axis=1)
    return [lm for lm, ok in zip(live, d <= r * (1.0 + 1e-9) + 1e-9, strict=True) if ok]


@dataclass
class Decision:
    kind: str  # "new" | "associate" | "hold"
    landmark_id: int | None = None
    in_gate: list[int] = field(default_factory=list)
    nn: dict[int, float] = field(default_factory=dict)
    nn_ms: float = 0.0


def decide(
    centroid: np.ndarray,
    size: float,
    frames: set[int],
    cloud_fn: Callable[[], np.ndarray],
    landmarks: list[LandmarkState],
    stamp: float,
    n_views: int,
    p: MapperParams,
    force: bool = False,
) -> Decision:
    """Where a validated candidate goes (see module docstring). `landmarks`: same class, id order."""
    in_gate: list[tuple[LandmarkState, float, float]] = []  # (landmark, distance, gate radius)
    for lm in near_enough(centroid, size, landmarks, stamp, p):
        s = max(lm.size, size)
        r = gate_radius(stamp - lm.last_assoc, s, p)
        d = float(np.linalg.norm(centroid - lm.centroid))
        if d > r:
            continue
        if len(frames & lm.frames) >= p.covis_veto_frames:
            continue
        in_gate.append((lm, d, r))
    ids = [lm.id for lm, _, _ in in_gate]
    if not in_gate:
        return Decision("new", in_gate=ids)
    if len(in_gate) == 1:
        lm, d, r = in_gate[0]
        if d <= p.clear_match_fraction * gate_floor(max(lm.size, size), p):
            return Decision("associate", lm.id, ids)
    t0 = time.perf_counter()
    cloud = cloud_fn()
    nn = {lm.id: nn_distance(cloud, lm, p.nn_trim) for lm, _, _ in in_gate}
    nn_ms = (time.perf_counter() - t0) * 1e3
    accept = {
        lm.id: max(
            p.nn_accept_min_m,
            p.nn_accept_size_factor * max(lm.size, size),
            0.5 * (r - gate_floor(max(lm.size, size), p)),
        )
        for lm, _, r in in_gate
    }
    ranked = sorted(ids, key=lambda i: (nn[i], i))
    best = ranked[0]
    if nn[best] > accept[best]:
        return Decision("new", in_gate=ids, nn=nn, nn_ms=nn_ms)
    if len(ranked) > 1 and not force and n_views < p.hold_max_views:
        second = ranked[1]
        if nn[second] <= accept[second] and nn[best] > p.ambiguity_ratio * nn[second]:
            return Decision("hold", in_gate=ids, nn=nn, nn_ms=nn_ms)
    return Decision("associate", best, ids, nn, nn_ms)

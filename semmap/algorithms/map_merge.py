"""Comparing and fusing two maps: `semmap diff` and `semmap merge` (pure: landmarks in, landmarks out).

Both first put map B into map A's frame: by relocalisation on their objects (semmap/algorithms/relocalize.py, with the
landmark clouds when the maps come with their `map.sqlite`), or as they are when the caller knows they share a
frame (two sessions of one relocalised run). Then landmarks are paired one-to-one, same class, nearest first,
within a gate of `max(gate_m, gate_radius_factor * larger radius)`: a large object's centre is less certain.

- diff: pairs are `kept` (or `moved` when their centres differ by more than `moved_m`); unpaired landmarks of
  one class on both sides are paired again within `move_radius_m` (an object carried elsewhere in the room) and
  reported as `moved`; what is left is `missing` (in A, not in B) or `added` (in B, not in A). A landmark that B
  itself marks `missing` (a relocalised session looked and did not find it) counts as absent from B; one that B
  marks `prior` (carried over, never looked at) is reported `unseen`, not missing.
- merge: landmarks are paired as for diff, then (with clouds) unpaired same-class landmarks whose clouds overlap
  (two sides of one table, centres 40 cm apart); a pair becomes one landmark (the older id, A's), observations
  summed, first/last seen the earliest/latest; its extent is the robust box of the two clouds fused where both
  maps come with their clouds (run directories), otherwise the larger; its centre is A's, moved by B's only as
  far as B's is worth (`held_place`, semmap/algorithms/associator/prior_anchor.py: B's registration and the
  object's size against A's anchor sigma), or B's when B's lies beyond `moved_sigmas` of that (a pair by the gate
  only: two overlapping clouds are one object in place), as a session relocalised against A places A's
  landmarks; not the fused clouds' centre, which puts a partly seen object 10-14 cm from A's place (as it
  would in a relocalised run too). Unpaired landmarks of B join with new ids after A's. The result is in
  A's frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from msgspec.structs import replace

from semmap.algorithms.relocalize import MapObject, RelocAttempt, RelocParams, apply, relocalize
from semmap.core.config.associator import PriorParams
from semmap.core.messages import Landmark


@dataclass(frozen=True)
class MatchParams:
    gate_m: float = 0.3
    gate_radius_factor: float = 0.5
    moved_m: float = 0.3  # a paired landmark whose centre moved more than this is reported moved
    move_radius_m: float = 6.0  # unpaired same-class landmarks within this are one object carried elsewhere
    # merge, with clouds: unpaired same-class landmarks are one object when this share of either's cloud lies
    # within touch_m of the other's (two sides of a table, centres 40 cm apart; 7-Scenes: one object's two maps
    # overlap 0.5-1.0, neighbours of one class 0.0-0.11)
    touch_m: float = 0.05
    overlap_share: float = 0.5
    # a pair's centre (`held_place`): as a relocalised session holds a prior landmark (PriorParams, same defaults)
    anchor_sigma_m: float = PriorParams().anchor_sigma_m
    registration_sigma_m: float = PriorParams().registration_sigma_m
    moved_sigmas: float = PriorParams().moved_sigmas
    moved_min_observations: int = PriorParams().moved_min_views


@dataclass
class MapDiff:
    kept: list[tuple[Landmark, Landmark]] = field(default_factory=list)
    moved: list[tuple[Landmark, Landmark]] = field(default_factory=list)  # (in A, in B, in A's frame)
    missing: list[Landmark] = field(default_factory=list)  # in A, not in B
    added: list[Landmark] = field(default_factory=list)  # in B (A's frame), not in A
    unseen: list[Landmark] = field(default_factory=list)  # in A, carried into B but never looked at

    def to_json(self) -> dict:
        def one(lm: Landmark) -> dict:
            return {"id": lm.id, "class": lm.class_name, "centroid": [round(v, 4) for v in lm.centroid]}

        def pair(a: Landmark, b: Landmark) -> dict:
            return {"a": one(a), "b": one(b), "distance_m": round(math.dist(a.centroid, b.centroid), 4)}

        return {
            "kept": [pair(a, b) for a, b in self.kept],
            "moved": [pair(a, b) for a, b in self.moved],
            "missing": [one(lm) for lm in self.missing],
            "added": [one(lm) for lm in self.added],
            "unseen": [one(lm) for lm in self.unseen],
        }


def transform_landmark(lm: Landmark, T: np.ndarray) -> Landmark:
    """The landmark in another frame (the extent stays axis-aligned in its own frame: a bound, not a box)."""
    c = apply(T, np.asarray(lm.centroid, float)[None])[0]
    return replace(lm, centroid=(float(c[0]), float(c[1]), float(c[2])))


# Two whole maps, B's drifted over its whole length: a rigid fit of B's objects onto A's keeps B's drift in its
# residual (the second 7-Scenes session alone, gt+drift: 0.159 m over 10 objects), while a relocalisation at the start
# of a
# session fits the few objects seen in its first seconds (0.15 m, RelocParams). The merge re-optimises B in A's frame
# after this fit, so the fit only has to pair the objects; it stays under the inlier gate (0.3 m), and every other
# guard against a false fit (4 inliers, pair distances, ambiguity, rotation sigma) is the relocalisation's.
MERGE_MAX_RMS_M = 0.25
# The same drift inflates the centres' residual, and with it the rotation uncertainty the fit's guard computes from
# it (the second 7-Scenes session alone: 10 objects within 12.9 cm, 2.2 deg). Where B's trajectory is re-optimised in
# A's frame
# afterwards (its keyframes registered to A's run's, each from this fit as a first guess: a 3 deg error is 10 cm at
# 2 m, inside the keyframe registration's reach), the fit only has to pair the objects, and this looser guard holds;
# B moved by the fit alone (`--rigid`, `semmap diff`, or a re-optimisation that fails) keeps the relocalisation's.
MERGE_REFIT_MAX_ROTATION_SIGMA_DEG = 3.0


def register(
    a: Sequence[Landmark],
    b: Sequence[Landmark],
    clouds_a: dict[int, np.ndarray] | None = None,
    clouds_b: dict[int, np.ndarray] | None = None,
    params: RelocParams | None = None,
    refit: bool = False,
) -> RelocAttempt:
    """B's frame -> A's frame by the maps' objects (the `missing` ones of either map take no part); by default
    with the merge's residual limit (MERGE_MAX_RMS_M), and with `refit` (B's trajectory re-optimised from this fit)
    the merge's rotation guard (MERGE_REFIT_MAX_ROTATION_SIGMA_DEG)."""
    clouds_a, clouds_b = clouds_a or {}, clouds_b or {}
    prior = [
        MapObject(lm.id, lm.class_name, np.asarray(lm.centroid, float), clouds_a.get(lm.id))
        for lm in a
        if lm.status != "missing"
    ]
    query = [
        MapObject(lm.id, lm.class_name, np.asarray(lm.centroid, float), clouds_b.get(lm.id))
        for lm in b
        if lm.status == "present"
    ]
    if params is None:
        params = RelocParams(max_rms_m=MERGE_MAX_RMS_M)
        if refit:
            params = dataclasses.replace(params, max_rotation_sigma_deg=MERGE_REFIT_MAX_ROTATION_SIGMA_DEG)
    return relocalize(query, prior, params)


def _gate(x: Landmark, y: Landmark, p: MatchParams) -> float:
    return max(p.gate_m, p.gate_radius_factor * max(x.radius, y.radius))


def _pair(a: Sequence[Landmark], b: Sequence[Landmark], limit) -> list[tuple[int, int]]:  # noqa: ANN001
    """One-to-one same-class pairs (indices), nearest first, each within limit(x, y)."""
    cand = []
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            if x.class_name == y.class_name:
                d = math.dist(x.centroid, y.centroid)
                if d <= limit(x, y):
                    cand.append((d, x.id, y.id, i, j))
    cand.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    out = []
    for _, _, _, i, j in cand:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return out


def diff_maps(a: Sequence[Landmark], b_in_a: Sequence[Landmark], params: MatchParams | None = None) -> MapDiff:
    """What changed from A to B (B already in A's frame): see the module docstring."""
    p = params or MatchParams()
    out = MapDiff()
    a_live = [lm for lm in a if lm.status != "missing"]
    b_live = [lm for lm in b_in_a if lm.status == "present"]
    b_prior = {lm.id for lm in b_in_a if lm.status == "prior"}
    pairs = _pair(a_live, b_live, lambda x, y: _gate(x, y, p))
    for i, j in pairs:
        (out.moved if math.dist(a_live[i].centroid, b_live[j].centroid) > p.moved_m else out.kept).append(
            (a_live[i], b_live[j])
        )
    rest_a = [lm for k, lm in enumerate(a_live) if k not in {i for i, _ in pairs}]
    rest_b = [lm for k, lm in enumerate(b_live) if k not in {j for _, j in pairs}]
    # carried into B (same id) and never looked at: unknown, not missing
    out.unseen = [lm for lm in rest_a if lm.id in b_prior]
    rest_a = [lm for lm in rest_a if lm.id not in b_prior]
    moves = _pair(rest_a, rest_b, lambda x, y: p.move_radius_m)
    out.moved += [(rest_a[i], rest_b[j]) for i, j in moves]
    out.missing = [lm for k, lm in enumerate(rest_a) if k not in {i for i, _ in moves}]
    out.added = [lm for k, lm in enumerate(rest_b) if k not in {j for _, j in moves}]
    out.moved.sort(key=lambda ab: ab[0].id)
    return out


def merge_maps(
    a: Sequence[Landmark],
    b_in_a: Sequence[Landmark],
    params: MatchParams | None = None,
    clouds_a: dict[int, np.ndarray] | None = None,
    clouds_b_in_a: dict[int, np.ndarray] | None = None,
) -> list[Landmark]:
    """A and B (already in A's frame, clouds too) as one map in A's frame: see the module docstring."""
    p = params or MatchParams()
    clouds_a, clouds_b_in_a = clouds_a or {}, clouds_b_in_a or {}
    pairs = _pair(a, b_in_a, lambda x, y: _gate(x, y, p))
    by_gate = set(pairs)
    pairs += _pair_overlapping(a, b_in_a, pairs, clouds_a, clouds_b_in_a, p)
    fused = {
        a[i].id: _fuse(a[i], b_in_a[j], p, clouds_a.get(a[i].id), clouds_b_in_a.get(b_in_a[j].id), (i, j) in by_gate)
        for i, j in pairs
    }
    paired_b = {j for _, j in pairs}
    out = [fused.get(lm.id, lm) for lm in a]
    next_id = max((lm.id for lm in a), default=-1) + 1
    for j, lm in enumerate(b_in_a):
        if j not in paired_b:
            out.append(replace(lm, id=next_id))
            next_id += 1
    return sorted(out, key=lambda lm: lm.id)


def _pair_overlapping(
    a: Sequence[Landmark],
    b: Sequence[Landmark],
    pairs: list[tuple[int, int]],
    clouds_a: dict[int, np.ndarray],
    clouds_b: dict[int, np.ndarray],
    p: MatchParams,
) -> list[tuple[int, int]]:
    """One-to-one pairs (indices) among the landmarks `pairs` left, same class, whose clouds overlap (see
    MatchParams.overlap_share), most overlapping first."""
    from scipy.spatial import cKDTree

    used_a, used_b = {i for i, _ in pairs}, {j for _, j in pairs}
    trees: dict[tuple[str, int], cKDTree] = {}  # (each cloud's tree built once, only where a pair may touch)

    def tree(side: str, key: int, cloud: np.ndarray) -> cKDTree:
        if (side, key) not in trees:
            trees[side, key] = cKDTree(cloud)
        return trees[side, key]

    def reach(cloud: np.ndarray, centre: Sequence[float]) -> float:
        return float(np.linalg.norm(cloud - np.asarray(centre), axis=1).max())

    cand = []
    for i, x in enumerate(a):
        cx = clouds_a.get(x.id)
        if i in used_a or cx is None or len(cx) < 4:
            continue
        rx = reach(cx, x.centroid)
        for j, y in enumerate(b):
            cy = clouds_b.get(y.id)
            if j in used_b or y.class_name != x.class_name or cy is None or len(cy) < 4:
                continue
            if math.dist(x.centroid, y.centroid) > rx + reach(cy, y.centroid) + p.touch_m:
                continue  # too far apart for any point of one to touch the other
            near_x = tree("b", j, cy).query(cx, distance_upper_bound=p.touch_m)[0] <= p.touch_m
            near_y = tree("a", i, cx).query(cy, distance_upper_bound=p.touch_m)[0] <= p.touch_m
            share = max(float(near_x.mean()), float(near_y.mean()))
            if share >= p.overlap_share:
                cand.append((-share, x.id, y.id, i, j))
    out = []
    for _, _, _, i, j in sorted(cand):
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return out


def _fuse(
    x: Landmark,
    y: Landmark,
    p: MatchParams,
    cx: np.ndarray | None = None,
    cy: np.ndarray | None = None,
    may_move: bool = True,
) -> Landmark:
    """A's landmark `x` and B's `y` as one: A's id and class, A's place unless B's says it moved (module
    docstring), the extent of both."""
    from semmap.algorithms.associator.params import MapperParams
    from semmap.algorithms.associator.prior_anchor import estimate_sigma, held_place

    mp = MapperParams()
    e = np.maximum(x.extent, y.extent)
    radius = max(x.radius, y.radius)
    if cx is not None and cy is not None and len(cx) >= 4 and len(cy) >= 4:
        from semmap.algorithms.associator.geometry import robust_box, voxel_downsample

        cloud = voxel_downsample(np.concatenate([cx, cy]), mp.voxel_m, mp.cloud_max_points)
        _, e = robust_box(cloud, mp.extent_percentile)
        radius = float(np.linalg.norm(e)) / 2.0
    sigma = estimate_sigma(p.registration_sigma_m, float(np.linalg.norm(e)), mp)
    enough = may_move and y.observations >= p.moved_min_observations
    c, _ = held_place(np.asarray(x.centroid), p.anchor_sigma_m, np.asarray(y.centroid), sigma, p.moved_sigmas, enough)
    statuses = (x.status, y.status)
    status = next(s for s in ("present", "missing", "prior") if s in statuses)
    return Landmark(
        x.id,
        x.class_name,
        (float(c[0]), float(c[1]), float(c[2])),
        radius,
        (float(e[0]), float(e[1]), float(e[2])),
        x.observations + y.observations,
        min(x.first_seen, y.first_seen),
        max(x.last_seen, y.last_seen),
        status,
    )

"""Relocalisation by objects: the rigid transform that takes a new session's landmarks onto a prior map's.

Pure (numpy / scipy, no I/O), shared by `semmap run --map`, `semmap diff` and `semmap merge`.

Why objects: a saved semantic map keeps landmarks (class, centroid, a thinned cloud), not images, so the new
session is placed by the objects it has validated so far. The search is a deterministic, exhaustive RANSAC
over class-consistent triples:

1. base pairs: pairs of query landmarks, widest and rarest-class first (a wide pair pins rotation better, a rare
   class has fewer prior candidates); for each, the prior pairs of the same two classes whose distance agrees
   within `pair_tol_m` (a ball query in a per-class KD-tree, so the cost grows with the local density of the
   prior map, not with its size);
2. each pair is completed by a third query landmark (not on the pair's line) and the prior landmarks of its
   class whose distances to both agree; the triple gives a Kabsch (Umeyama without scale) fit;
3. a hypothesis is scored by its inliers: query landmarks that land within `inlier_gate_m` of an unused prior
   landmark of their class (one-to-one, nearest first); the best is refitted on all its inliers.

A wrong relocalisation must be rare, so the answer is refused (None, with the reason) unless it has at least
`min_inliers` inliers (4: a session of 6 objects placed against an unrelated room of 40 objects in 8 classes
found 3 agreeing landmarks by chance in 22 of 60 seeded layouts, 4 in none, while 30 of 30 true sessions of 5
objects with 5 cm centroid noise relocalised either way), an RMS residual within `max_rms_m`, and beats
every *distinct* alternative (one that moves some of the best's inliers by more than `distinct_m`) by
`ambiguity_margin` inliers, and a rotation pinned to within `max_rotation_sigma_deg` (1 sigma, from the
inliers' spread and the residual, floored at `centroid_sigma_floor_m`: on 7-Scenes four objects that agreed
to 8.5 cm still left the rotation 11 degrees off). A symmetric layout (four chairs around a table) is ambiguous
and stays unanswered until an asymmetric object is seen.

Refinement: where both sides have clouds, a trimmed point-to-point ICP over the inlier pairs' clouds (each
query cloud against its own prior landmark's cloud, so objects cannot slide onto neighbours), its
correspondence gate shrinking from 0.3 to 0.05 m; the centroid of a partly seen object moves with the
viewpoint, its surface does not. The refinement is kept only if it keeps every inlier within the gate, and then
the rotation test uses the uncertainty the matched surfaces leave (when smaller than the centres'): on
7-Scenes six objects within a metre, whose centres differ between the sessions by 5-25 cm, gave a centroid
fit 8-10 degrees off that the surfaces brought to 1-2 degrees.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class MapObject:
    """A landmark as relocalisation sees it: class, centroid and (optionally) its world cloud."""

    id: int
    class_name: str
    centroid: np.ndarray
    cloud: np.ndarray | None = None


@dataclass(frozen=True)
class RelocParams:
    min_inliers: int = 4  # 3 agree by chance in a dense room (see the module docstring), 4 do not
    inlier_gate_m: float = 0.3  # a transformed query landmark within this of its prior match is an inlier
    max_rms_m: float = 0.15  # RMS centroid residual over the inliers
    pair_tol_m: float = 0.2  # distances between two landmarks must agree within this on both sides
    min_triangle_m: float = 0.15  # the third landmark's distance from the base pair's line (conditioning)
    ambiguity_margin: int = 1  # the best needs this many more inliers than any distinct alternative
    distinct_m: float = 0.3  # two hypotheses are distinct if some query landmark lands this far apart
    max_base_pairs: int = 15  # widest, rarest-class pairs; any pair of two true matches finds the answer
    max_hypotheses: int = 20000
    # third landmarks tried per base pair (None: all): those furthest from the pair's line, which pin the fit best;
    # a street's revisit search sets a few, as 30 recent cars against 200 old ones made ~100k Python steps a search
    max_thirds: int | None = None
    icp_iterations: int = 30  # per stage of the schedule
    icp_schedule_m: tuple[float, ...] = (0.3, 0.2, 0.1, 0.05)  # correspondence gates, coarse to fine
    icp_trim: float = 0.8  # share of closest correspondences kept per iteration
    icp_points_per_object: int = 300
    centroid_sigma_floor_m: float = 0.03  # per axis: a partly seen object's centre is never surer than this
    max_rotation_sigma_deg: float = 1.5  # the fit's rotation uncertainty (from its inliers' spread) must be below
    cloud_points_per_object: int = 20  # independent surface points an object counts for in the cloud sigma
    cloud_sigma_floor_m: float = 0.02  # per axis: a surface point matched across viewpoints is never surer


@dataclass
class RelocResult:
    """A relocalisation: `transform` maps query-frame points into the prior frame."""

    transform: np.ndarray
    matches: list[tuple[int, int]]  # (query id, prior id), inliers only
    inliers: int
    rms_m: float  # centroid residual over the inliers, after refinement
    runner_up: int  # inliers of the best distinct alternative (0 if none)
    hypotheses: int
    refined: bool  # the cloud refinement was applied
    cloud_rms_m: float | None = None
    rotation_sigma_deg: float = 0.0  # 1-sigma rotation uncertainty of the fit, from the inliers' geometry

    @property
    def translation(self) -> np.ndarray:
        return self.transform[:3, 3]

    @property
    def rotation_deg(self) -> float:
        return rotation_angle_deg(self.transform[:3, :3])


@dataclass
class RelocAttempt:
    """The outcome of one attempt: a result, or why there is none."""

    result: RelocResult | None
    reason: str
    hypotheses: int = 0
    best_inliers: int = 0
    runner_up: int = 0
    stats: dict[str, float] = field(default_factory=dict)


def rotation_angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))))


def rotation_sigma_deg(points: np.ndarray, sigma_m: float) -> float:
    """1-sigma rotation uncertainty (largest axis) of a rigid fit on these points, each known to `sigma_m`:
    the information about a small rotation is sum(|q|^2 I - q q^T) / sigma^2 over the centred points, so a few
    objects close together (or on a line) pin the rotation badly however small the residual."""
    q = points - points.mean(axis=0)
    info = (np.sum(q * q) * np.eye(3) - q.T @ q) / sigma_m**2
    smallest = float(np.linalg.eigvalsh(info)[0])
    return math.inf if smallest <= 1e-12 else math.degrees(1.0 / math.sqrt(smallest))


def rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform (4x4) with dst ~ R src + t (Kabsch; no scale, a proper rotation)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    H = ((src - ms) * w[:, None]).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = md - R @ ms
    return T


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


class PriorIndex:
    """The prior map, indexed once per map: per-class KD-trees of centroids and per-landmark cloud trees."""

    def __init__(self, prior: Sequence[MapObject]) -> None:
        self.objects = list(prior)
        self.by_class: dict[str, np.ndarray] = {}  # class -> indices into objects
        for i, o in enumerate(self.objects):
            self.by_class.setdefault(o.class_name, []).append(i)  # type: ignore[arg-type]
        self.by_class = {k: np.asarray(v, np.int64) for k, v in self.by_class.items()}
        self.centroids = np.array([o.centroid for o in self.objects], float).reshape(-1, 3)
        self.trees = {k: cKDTree(self.centroids[v]) for k, v in self.by_class.items()}
        self._cloud_trees: dict[int, cKDTree] = {}

    def count(self, class_name: str) -> int:
        return len(self.by_class.get(class_name, ()))

    def near(self, class_name: str, point: np.ndarray, lo: float, hi: float) -> np.ndarray:
        """Prior indices of `class_name` at a distance in [lo, hi] from `point`."""
        tree = self.trees.get(class_name)
        if tree is None:
            return np.zeros(0, np.int64)
        local = np.asarray(tree.query_ball_point(point, hi), np.int64)
        if not len(local):
            return local
        idx = self.by_class[class_name][local]
        d = np.linalg.norm(self.centroids[idx] - point, axis=1)
        return np.sort(idx[d >= lo])

    def cloud_tree(self, i: int) -> cKDTree | None:
        cloud = self.objects[i].cloud
        if cloud is None or len(cloud) < 10:
            return None
        if i not in self._cloud_trees:
            self._cloud_trees[i] = cKDTree(cloud)
        return self._cloud_trees[i]


def _score(
    T: np.ndarray, groups: list[tuple[str, np.ndarray]], qc: np.ndarray, index: PriorIndex, gate: float
) -> tuple[list[tuple[int, int]], float]:
    """One-to-one inliers (query index, prior index), nearest first, and their summed squared residual.

    groups: the query indices per class (one KD-tree query per class, not per landmark)."""
    moved = apply(T, qc)
    dist, qidx, pidx = [], [], []
    for cls, members in groups:
        k = min(3, index.count(cls))
        d, local = index.trees[cls].query(moved[members], k=k, distance_upper_bound=gate)
        d, local = d.reshape(len(members), k), local.reshape(len(members), k)
        ok = np.isfinite(d)
        dist.append(d[ok])
        qidx.append(np.broadcast_to(members[:, None], d.shape)[ok])
        pidx.append(index.by_class[cls][local[ok]])
    d, qi, pi = np.concatenate(dist), np.concatenate(qidx), np.concatenate(pidx)
    order = np.lexsort((pi, qi, d))
    used_q: set[int] = set()
    used_p: set[int] = set()
    pairs, sse = [], 0.0
    for o in order:
        a, b = int(qi[o]), int(pi[o])
        if a in used_q or b in used_p:
            continue
        used_q.add(a)
        used_p.add(b)
        pairs.append((a, b))
        sse += float(d[o]) ** 2
    return sorted(pairs), sse


def _refit(pairs: list[tuple[int, int]], qc: np.ndarray, index: PriorIndex) -> np.ndarray:
    q = np.array([qc[a] for a, _ in pairs])
    p = np.array([index.centroids[b] for _, b in pairs])
    return rigid_fit(q, p)


def _icp(
    T: np.ndarray, pairs: list[tuple[int, int]], query: Sequence[MapObject], index: PriorIndex, params: RelocParams
) -> tuple[np.ndarray, float, float] | None:
    """Trimmed point-to-point ICP over the matched objects' clouds (each against its own match), its
    correspondence gate shrinking stage by stage (`icp_schedule_m`): a centroid fit can be ten degrees off
    (partly seen objects), beyond a tight gate's reach. Returns the transform, the trimmed RMS and the 1-sigma
    rotation uncertainty the surfaces leave (`cloud_points_per_object` points an object, never surer than
    `cloud_sigma_floor_m`: neighbouring points of one surface are not independent)."""
    sets = []
    for qi, pi in pairs:
        cloud, tree = query[qi].cloud, index.cloud_tree(pi)
        if cloud is None or len(cloud) < 10 or tree is None:
            continue
        step = max(1, len(cloud) // params.icp_points_per_object)
        sets.append((np.asarray(cloud, float)[::step], tree, np.asarray(index.objects[pi].cloud)))
    if len(sets) < 2:
        return None
    rms, per_object = math.inf, []
    for gate in params.icp_schedule_m:
        for _ in range(params.icp_iterations):
            src, dst, owner = [], [], []
            for n, (pts, tree, target) in enumerate(sets):
                d, j = tree.query(apply(T, pts), k=1, distance_upper_bound=gate)
                ok = np.isfinite(d)
                src.append(pts[ok])
                dst.append(target[j[ok]])
                owner.append(np.full(int(ok.sum()), n))
            s, t, who = np.concatenate(src), np.concatenate(dst), np.concatenate(owner)
            if len(s) < 30:
                return None
            d = np.linalg.norm(apply(T, s) - t, axis=1)
            keep = np.argsort(d, kind="stable")[: max(30, int(params.icp_trim * len(d)))]
            rms = float(np.sqrt(np.mean(d[keep] ** 2)))
            T_new = rigid_fit(s[keep], t[keep])
            per_object = [t[keep][who[keep] == n] for n in range(len(sets))]
            if np.abs(T_new - T).max() < 1e-6:
                T = T_new
                break
            T = T_new
    k = params.cloud_points_per_object
    sample = [pts[:: max(1, len(pts) // k)][:k] for pts in per_object if len(pts)]
    if len(sample) < 2:
        return None
    sigma = rotation_sigma_deg(np.concatenate(sample), max(rms / math.sqrt(3.0), params.cloud_sigma_floor_m))
    return T, rms, sigma


def _triples(
    base: list[tuple[int, float, int, int]],
    query: Sequence[MapObject],
    qc: np.ndarray,
    index: PriorIndex,
    p: RelocParams,
):  # noqa: ANN202 - a generator of index 6-tuples
    """Class-consistent (query i, j, k; prior a, b, c) triples whose pairwise distances agree, base pair by base
    pair; ball queries are batched per base pair (one per class), so the Python loop runs over candidates only."""
    tol = p.pair_tol_m
    for _, neg_d, i, j in base:
        d_ij = -neg_d
        axis = (qc[j] - qc[i]) / d_ij
        thirds, lever = [], []
        for k in range(len(query)):
            off = qc[k] - qc[i]
            perp = float(np.linalg.norm(off - (off @ axis) * axis))
            if k not in (i, j) and perp >= p.min_triangle_m:
                thirds.append(k)
                lever.append(perp)
        if not thirds:
            continue
        if p.max_thirds is not None and len(thirds) > p.max_thirds:
            best = sorted(np.argsort(-np.asarray(lever), kind="stable")[: p.max_thirds])
            thirds = [thirds[n] for n in best]
        A = index.by_class[query[i].class_name]
        pa = index.centroids[A]
        cls_j = index.by_class[query[j].class_name]
        balls_b = index.trees[query[j].class_name].query_ball_point(pa, d_ij + tol)
        balls_c = {
            k: index.trees[query[k].class_name].query_ball_point(pa, float(np.linalg.norm(qc[k] - qc[i])) + tol)
            for k in thirds
        }
        for n_a, a in enumerate(A):
            bs = cls_j[np.asarray(balls_b[n_a], np.int64)]
            if not len(bs):
                continue
            bs = bs[(np.linalg.norm(index.centroids[bs] - pa[n_a], axis=1) >= d_ij - tol) & (bs != a)]
            for k in thirds:
                cs = index.by_class[query[k].class_name][np.asarray(balls_c[k][n_a], np.int64)]
                if not len(cs) or not len(bs):
                    continue
                d_ik, d_jk = float(np.linalg.norm(qc[k] - qc[i])), float(np.linalg.norm(qc[k] - qc[j]))
                cs = cs[np.linalg.norm(index.centroids[cs] - pa[n_a], axis=1) >= d_ik - tol]
                if not len(cs):
                    continue
                d_bc = np.linalg.norm(index.centroids[bs][:, None, :] - index.centroids[cs][None, :, :], axis=2)
                for nb, nc in zip(*np.nonzero(np.abs(d_bc - d_jk) <= tol), strict=True):
                    b, c = int(bs[nb]), int(cs[nc])
                    if c not in (a, b):
                        yield i, j, k, int(a), b, c


def relocalize(
    query: Sequence[MapObject], prior: Sequence[MapObject] | PriorIndex, params: RelocParams | None = None
) -> RelocAttempt:
    """Place `query` (a new session's landmarks, own frame) in the frame of `prior` (see module docstring)."""
    p = params or RelocParams()
    index = prior if isinstance(prior, PriorIndex) else PriorIndex(prior)
    query = [o for o in query if index.count(o.class_name)]
    if len(query) < p.min_inliers:
        return RelocAttempt(None, f"too few landmarks of classes the prior map has ({len(query)} < {p.min_inliers})")
    qc = np.array([o.centroid for o in query], float)
    n = len(query)
    classes = sorted({o.class_name for o in query})
    groups = [(c, np.array([i for i, o in enumerate(query) if o.class_name == c], np.int64)) for c in classes]
    base = []
    for i, j in itertools.combinations(range(n), 2):
        d = float(np.linalg.norm(qc[i] - qc[j]))
        if d < 2 * p.min_triangle_m:
            continue
        cost = index.count(query[i].class_name) * index.count(query[j].class_name)
        base.append((cost, -d, i, j))
    base.sort()
    hyps: list[tuple[int, float, np.ndarray]] = []  # (inliers, sse, T)
    tried = 0
    seen: set[tuple[tuple[int, int], ...]] = set()
    covered: set[tuple[int, int]] = set()  # (query, prior) pairs already inside a found hypothesis
    for i, j, k, a, b, c in _triples(base[: p.max_base_pairs], query, qc, index, p):
        if (i, a) in covered and (j, b) in covered and (k, c) in covered:
            continue  # it would refit to a placement already found
        tried += 1
        T = rigid_fit(qc[[i, j, k]], index.centroids[[a, b, c]])
        pairs, sse = _score(T, groups, qc, index, p.inlier_gate_m)
        key = tuple(pairs)
        if len(pairs) >= p.min_inliers and key not in seen:
            seen.add(key)
            T = _refit(pairs, qc, index)
            pairs, sse = _score(T, groups, qc, index, p.inlier_gate_m)
            hyps.append((len(pairs), sse, T))
            covered.update(pairs)
        if tried >= p.max_hypotheses:
            break
    if not hyps:
        return RelocAttempt(None, f"no {p.min_inliers} landmarks agree on a placement", tried)
    hyps.sort(key=lambda h: (-h[0], h[1]))
    best_n, best_sse, best_T = hyps[0]
    support = qc[[a for a, _ in _score(best_T, groups, qc, index, p.inlier_gate_m)[0]]]
    moved = apply(best_T, support)
    runner = 0
    for n_in, _, T in hyps[1:]:  # distinct: it moves the best's own inliers elsewhere
        if np.linalg.norm(apply(T, support) - moved, axis=1).max() > p.distinct_m:
            runner = n_in
            break
    if best_n - runner < p.ambiguity_margin:
        return RelocAttempt(
            None,
            f"ambiguous: {runner} landmarks also agree on another placement ({best_n} on the best)",
            tried,
            best_n,
            runner,
        )
    pairs, sse = _score(best_T, groups, qc, index, p.inlier_gate_m)
    T, refined, cloud_rms, cloud_sigma = best_T, False, None, math.inf
    icp = _icp(best_T, pairs, query, index, p)
    if icp is not None:
        T_icp, cloud_rms, cloud_sigma = icp
        pairs_icp, sse_icp = _score(T_icp, groups, qc, index, p.inlier_gate_m)
        if set(pairs_icp) >= set(pairs):
            T, refined, pairs, sse = T_icp, True, pairs_icp, sse_icp
    rms = math.sqrt(sse / len(pairs))
    # per-axis sigma of a centroid: the 3-D RMS over sqrt(3), never below the floor
    rot_sigma = rotation_sigma_deg(
        index.centroids[[b for _, b in pairs]], max(rms / math.sqrt(3.0), p.centroid_sigma_floor_m)
    )
    if refined:  # the surfaces pin the rotation better than the centres of partly seen objects
        rot_sigma = min(rot_sigma, cloud_sigma)
    if rot_sigma > p.max_rotation_sigma_deg:
        return RelocAttempt(
            None,
            f"weak geometry: {len(pairs)} landmarks within {rms * 100:.1f} cm leave the rotation uncertain by "
            f"{rot_sigma:.1f} deg (> {p.max_rotation_sigma_deg} deg)",
            tried,
            len(pairs),
            runner,
        )
    if rms > p.max_rms_m:
        return RelocAttempt(
            None, f"residual {rms:.3f} m over {len(pairs)} landmarks exceeds {p.max_rms_m} m", tried, len(pairs), runner
        )
    matches = [(query[a].id, index.objects[b].id) for a, b in pairs]
    result = RelocResult(T, matches, len(pairs), rms, runner, tried, refined, cloud_rms, rot_sigma)
    return RelocAttempt(result, "ok", tried, len(pairs), runner)

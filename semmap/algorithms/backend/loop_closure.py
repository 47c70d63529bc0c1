"""Geometric loop closures: whole-depth-frame ICP between keyframes that revisit a place.

Why: a landmark observation is the centroid of the object's visible part, which moves with the viewpoint, so
observations scatter 3-14 cm around the landmark and the optimised trajectory stalls at about 5 cm ATE whatever
the drift (the "centroid floor"). Once the landmark constraints have pulled the estimate close at a revisit,
point-to-plane ICP between the two keyframes' whole depth clouds measures their relative pose to about a
centimetre; the pose graph takes it as a robust relative-pose factor.

Object views alone are too small for this (a view keeps ~100 points; none of 19 registrations at revisits
converged), hence whole frames. Pure numpy/scipy, free of I/O and deterministic (Open3D's ICP differs in the
last bits between calls, which would break replay).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgpack
import numpy as np
from scipy.spatial import cKDTree

from semmap.algorithms.associator.geometry import voxel_downsample  # (one voxel grid: the mean point per voxel)
from semmap.algorithms.dynamic_mask import mask_dynamic
from semmap.core.config import LoopClosureParams
from semmap.core.geometry import rotation_angle
from semmap.core.stamps import reaches

if TYPE_CHECKING:
    from semmap.algorithms.backend.pose_graph import PoseGraph
    from semmap.core.messages import DynamicBox

COARSE_SUBSAMPLE = 4
MIN_POINTS = 200  # fewer than this after downsampling: not a cloud to register (a blank or missing depth image)


# ------------------------------------------------------------------------------------------------ clouds


def depth_to_points(depth: np.ndarray, depth_scale: float, fx: float, fy: float, cx: float, cy: float,
                    stride: int, depth_min_m: float, depth_max_m: float) -> np.ndarray:
    """(N, 3) float64 camera-frame points of every `stride`-th pixel with a depth in range."""
    z = depth[::stride, ::stride].astype(np.float64) * depth_scale
    v, u = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride]
    ok = (z > depth_min_m) & (z < depth_max_m)
    z = z[ok]
    return np.stack([(u[ok] - cx) / fx * z, (v[ok] - cy) / fy * z, z], axis=1)


def estimate_normals(points: np.ndarray, radius: float, max_nn: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """(points, unit normals) for the points with at least 3 neighbours within `radius` (PCA of the
    neighbourhood); normals face the camera at the origin."""
    if len(points) < 3:
        return points.reshape(0, 3), points.reshape(0, 3)
    k = min(max_nn, len(points))
    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius)
    valid = np.isfinite(dist)  # a missing neighbour has index len(points): the zero row below, weight 0
    keep = valid.sum(axis=1) >= 3
    weights = valid[keep].astype(np.float64)[..., None]
    neighbours = np.vstack([points, np.zeros((1, 3))])[idx[keep]]
    mean = (neighbours * weights).sum(axis=1) / weights.sum(axis=1)
    centred = (neighbours - mean[:, None, :]) * weights
    _, vectors = np.linalg.eigh(centred.transpose(0, 2, 1) @ centred)
    points, normals = points[keep], vectors[:, :, 0]
    flip = np.einsum("ij,ij->i", normals, points) > 0
    normals[flip] *= -1.0
    return points, normals


@dataclass
class KeyframeCloud:
    """A keyframe's downsampled depth cloud in its camera frame (float32 to halve memory). Normals are only
    needed when it is the target of a registration, so they are estimated then, once."""

    frame_id: int
    stamp: float
    points: np.ndarray
    normals: np.ndarray | None = None

    def with_normals(self, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """(points that have a normal, their normals), estimated on first use and kept."""
        if self.normals is None:
            points, normals = estimate_normals(self.points.astype(np.float64), radius)
            self.points, self.normals = points.astype(np.float32), normals.astype(np.float32)
        return self.points, self.normals

    @property
    def nbytes(self) -> int:
        return int(self.points.nbytes + (0 if self.normals is None else self.normals.nbytes))


# ------------------------------------------------------------------------------------------------ ICP


@dataclass
class IcpResult:
    transform: np.ndarray  # 4x4: source frame -> target frame
    fitness: float  # share of source points with a correspondence within the distance
    rmse_m: float  # RMS point-to-point distance of those correspondences
    constraint: float  # smallest eigenvalue of the normals' scatter (0: sliding along a plane or a corridor)


def _exp_se3(x: np.ndarray) -> np.ndarray:
    """4x4 of a small twist x = (rotation vector, translation)."""
    w, t = x[:3], x[3:]
    theta = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        rot = np.eye(3) + k
    else:
        rot = np.eye(3) + math.sin(theta) / theta * k + (1.0 - math.cos(theta)) / theta ** 2 * (k @ k)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, t
    return out


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, init: np.ndarray,
                       max_distance: float, max_iterations: int = 30, tree: cKDTree | None = None) -> IcpResult:
    """Point-to-plane ICP (Gauss-Newton on the linearised residuals n . (T p - q)) of source onto target."""
    tree = tree if tree is not None else cKDTree(target)
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    nrm = np.asarray(target_normals, dtype=np.float64)
    transform = np.array(init, dtype=np.float64)
    previous = (-1.0, math.inf)
    for _ in range(max_iterations):
        moved = src @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=max_distance)
        ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        # converged when the correspondences stop changing (Open3D's relative fitness / RMSE criterion)
        fitness, rmse = ok.mean(), float(np.sqrt(np.mean(dist[ok] ** 2)))
        if abs(fitness - previous[0]) < 1e-6 * fitness and abs(rmse - previous[1]) < 1e-6 * rmse:
            break
        previous = (fitness, rmse)
        p, q, n = moved[ok], tgt[idx[ok]], nrm[idx[ok]]
        residual = np.einsum("ij,ij->i", p - q, n)
        jac = np.hstack([np.cross(p, n), n])
        step = np.linalg.lstsq(jac.T @ jac, -(jac.T @ residual), rcond=None)[0]
        transform = _exp_se3(step) @ transform
        if np.linalg.norm(step) < 1e-7:
            break
    moved = src @ transform[:3, :3].T + transform[:3, 3]
    dist, idx = tree.query(moved, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    count = int(ok.sum())
    if count < 6:
        return IcpResult(transform, count / max(len(src), 1), math.inf, 0.0)
    n = nrm[idx[ok]]
    constraint = float(np.linalg.eigvalsh(n.T @ n / count)[0])
    return IcpResult(transform, count / len(src), float(np.sqrt(np.mean(dist[ok] ** 2))), constraint)


# ------------------------------------------------------------------------------------------------ the closer


@dataclass
class LoopClosure:
    """A measured relative pose: frame b (the new keyframe) seen from frame a (the earlier one)."""

    frame_a: int
    frame_b: int
    T_ab: np.ndarray
    fitness: float
    rmse_m: float
    constraint: float
    correction_m: float  # how far the registration moved frame b from where the current estimate had it
    # frame a is a prior map's keyframe (frame_a: the prior run's id) held at this pose of the map: the
    # closure places frame b in the map's frame (a pose prior) instead of relative to a frame of this run
    T_wa: np.ndarray | None = None


def _angle_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> np.ndarray:
    """Rotation angle between batches of rotations (..., 3, 3), degrees."""
    return np.degrees(rotation_angle(rot_a, rot_b))


class LoopCloser:
    """Keeps keyframe clouds and proposes loop closures against the current estimate.

    A keyframe (every `every_n_frames`-th frame) is registered against the nearest earlier keyframe (at least
    `min_gap_s` older, within `max_distance_m` and `max_angle_deg` in the current corrected poses), coarse then
    fine. A closure is accepted with enough overlap (`min_fitness`), a small residual (`max_rmse_m`), geometry
    that pins all three translations (`min_constraint`) and a plausible correction of the estimate
    (`max_correction_m`: a symmetric room can fit well in the wrong place). A keyframe that closed a loop is not
    kept (its place already is); at most `max_keyframes` are kept, the oldest go first. A prior map's keyframes
    (`set_prior`) are fixed targets in the map's frame, tried first once the session is in it.
    """

    def __init__(self, params: LoopClosureParams | None = None) -> None:
        self.params = params or LoopClosureParams()
        self.keyframes: OrderedDict[int, KeyframeCloud] = OrderedDict()
        # a prior map's keyframes and their poses in its frame (set_prior): targets once the session is in it
        self.prior: list[KeyframeCloud] = []
        self.prior_poses = np.zeros((0, 4, 4))
        self.counters: dict[str, int] = {"keyframes": 0, "searched": 0, "registered": 0, "accepted": 0,
                                         "rejected_fitness": 0, "rejected_rmse": 0, "rejected_degenerate": 0,
                                         "evicted": 0, "empty_clouds": 0,
                                         "skipped_precise_odometry": 0, "rejected_correction": 0,
                                         "prior_keyframes": 0, "prior_searched": 0, "prior_accepted": 0}

    def set_prior(self, keyframes: list[tuple[KeyframeCloud, np.ndarray]]) -> None:
        """A prior map's keyframe clouds with their camera-to-world poses in the map's frame (at most
        `max_keyframes`, the newest kept). Why: a session relocalised by its objects alone stays degrees off in
        orientation (object centroids move with the viewpoint); registering its keyframes to the map's whole
        depth frames holds it to the map's trajectory as a revisit within one run would."""
        usable = []
        for cloud, T in keyframes:
            T = np.asarray(T, np.float64)
            finite = np.isfinite(cloud.points).all(axis=1)  # (a damaged journal row must not poison the KD-tree)
            if T.shape == (4, 4) and np.isfinite(T).all() and finite.sum() >= MIN_POINTS:
                usable.append((cloud if finite.all() else KeyframeCloud(cloud.frame_id, cloud.stamp,
                                                                        cloud.points[finite]), T))
        usable = usable[-self.params.max_keyframes:]
        self.prior = [c for c, _ in usable]
        self.prior_poses = np.stack([T for _, T in usable]) if usable else np.zeros((0, 4, 4))
        self.counters["prior_keyframes"] = len(self.prior)

    def wants(self, frame_id: int) -> bool:
        """Whether `frame_id` is a keyframe whose cloud the closer uses."""
        return self.params.enabled and int(frame_id) % self.params.every_n_frames == 0

    def cloud_from_depth(self, frame_id: int, stamp: float, depth: np.ndarray, depth_scale: float, fx: float,
                         fy: float, cx: float, cy: float,
                         dynamic: Sequence[DynamicBox] | None = None) -> KeyframeCloud:
        """The keyframe's depth as a voxel-downsampled camera-frame cloud, the depth of its dynamic objects (the
        tracker's boxes of the frame: people, things seen moving) left out as `params.dynamic_mask` says.

        Why: a person in a keyframe's cloud is structure that is elsewhere by the next visit, and ICP may fit
        it. Off by default (`none`): on Bonn crowd it gave no reliable gain (docs/RESULTS.md)."""
        p = self.params
        if dynamic:
            depth = mask_dynamic(depth, list(dynamic), depth_scale, p.dynamic_mask)
        points = depth_to_points(depth, depth_scale, fx, fy, cx, cy, p.depth_stride, p.depth_min_m, p.depth_max_m)
        return KeyframeCloud(int(frame_id), float(stamp), voxel_downsample(points, p.voxel_m).astype(np.float32))

    def process(self, cloud: KeyframeCloud, frame_ids: np.ndarray, poses: np.ndarray,
                odometry_sigmas: Callable[[int, int], tuple[float, float]] | None = None,
                against_prior: bool = False) -> LoopClosure | None:
        """Try to close a loop from `cloud`'s keyframe, then keep its cloud unless it closed one.

        `frame_ids` (sorted) and `poses` (N, 4, 4) are the current corrected camera-to-world poses; both the new
        keyframe and the earlier ones are looked up there. `odometry_sigmas(a, b)` (m, rad), when given, is what
        the front end declares for the motion between two frames: a registration less certain than that (with
        ground-truth odometry, say) would only blur the trajectory, so such pairs are not tried.
        `against_prior` (the poses are in the prior map's frame): the nearest prior keyframe is tried first, and
        the run's own only when that gives no closure.
        """
        self.counters["keyframes"] += 1
        if len(cloud.points) < MIN_POINTS:
            self.counters["empty_clouds"] += 1
            return None
        frame_ids, poses = np.asarray(frame_ids), np.asarray(poses)
        closure = None
        me = self._lookup(frame_ids, cloud.frame_id)
        if against_prior and len(self.prior) and me is not None:
            closure = self._close_prior(cloud, poses[me])
        if closure is None:
            closure = self._close(cloud, frame_ids, poses, odometry_sigmas)
        if closure is None:
            self.keep(cloud)
        return closure

    def keep(self, cloud: KeyframeCloud) -> None:
        self.keyframes[cloud.frame_id] = cloud
        while len(self.keyframes) > self.params.max_keyframes:
            self.keyframes.popitem(last=False)
            self.counters["evicted"] += 1

    @property
    def nbytes(self) -> int:
        return sum(k.nbytes for k in self.keyframes.values())

    def _lookup(self, frame_ids: np.ndarray, frame_id: int) -> int | None:
        k = int(np.searchsorted(frame_ids, frame_id))
        return k if k < len(frame_ids) and int(frame_ids[k]) == frame_id else None

    def _close(self, cloud: KeyframeCloud, frame_ids: np.ndarray, poses: np.ndarray,
               odometry_sigmas: Callable[[int, int], tuple[float, float]] | None) -> LoopClosure | None:
        p = self.params
        me = self._lookup(frame_ids, cloud.frame_id)
        if me is None:
            return None
        # earlier keyframes with a pose, and its row (vectorised: up to max_keyframes of them every keyframe)
        kept = list(self.keyframes.values())
        kf_ids = np.fromiter((kf.frame_id for kf in kept), np.int64, len(kept))
        kf_old = np.fromiter((reaches(cloud.stamp - kf.stamp, p.min_gap_s) for kf in kept), bool, len(kept))
        found = np.minimum(np.searchsorted(frame_ids, kf_ids), max(len(frame_ids) - 1, 0))
        has = kf_old & (frame_ids[found] == kf_ids) if len(frame_ids) else kf_old & False
        old = [kept[i] for i in np.flatnonzero(has)]
        rows = found[has]
        if not old:
            return None
        their = poses[rows]
        mine = poses[me]
        dist = np.linalg.norm(their[:, :3, 3] - mine[:3, 3], axis=1)
        angle = _angle_deg(their[:, :3, :3], mine[:3, :3][None])
        near = (dist < p.max_distance_m) & (angle < p.max_angle_deg)
        if odometry_sigmas is not None:
            sigma_r = math.radians(p.sigma_rotation_deg)
            for k in np.flatnonzero(near):
                odo_t, odo_r = odometry_sigmas(old[k].frame_id, cloud.frame_id)
                if odo_t <= p.sigma_translation_m and odo_r <= sigma_r:
                    near[k] = False
                    self.counters["skipped_precise_odometry"] += 1
        if not near.any():
            return None
        self.counters["searched"] += 1
        score = np.where(near, dist + angle / 50.0, np.inf)  # 50 deg weigh like a metre
        # the nearest first, then the next ones: a view of the same place that people crowd, or that the drift put
        # outside the ICP's basin, fails its tests where a neighbouring keyframe passes (Bonn crowd: 16 closures
        # accepted of 33 keyframes searched instead of 8-12)
        for best in np.argsort(score, kind="stable")[: min(p.candidates, int(near.sum()))]:
            closure = self._register(cloud, old[int(best)], np.linalg.inv(their[int(best)]) @ mine)
            if closure is not None:
                return closure
        return None

    def _close_prior(self, cloud: KeyframeCloud, mine: np.ndarray) -> LoopClosure | None:
        """Against the nearest prior keyframe (same radius and angle as a revisit; no minimum age)."""
        p = self.params
        dist = np.linalg.norm(self.prior_poses[:, :3, 3] - mine[:3, 3], axis=1)
        angle = _angle_deg(self.prior_poses[:, :3, :3], mine[:3, :3][None])
        near = (dist < p.max_distance_m) & (angle < p.max_angle_deg)
        if not near.any():
            return None
        self.counters["prior_searched"] += 1
        best = int(np.argmin(np.where(near, dist + angle / 50.0, np.inf)))
        T_wa = self.prior_poses[best]
        closure = self._register(cloud, self.prior[best], np.linalg.inv(T_wa) @ mine, T_wa.copy())
        if closure is not None:
            self.counters["prior_accepted"] += 1
        return closure

    def _register(self, cloud: KeyframeCloud, target: KeyframeCloud, init: np.ndarray,
                  target_pose: np.ndarray | None = None) -> LoopClosure | None:
        """ICP of `cloud` onto `target` from `init` (the current estimate of T_target_cloud), coarse then fine,
        and the acceptance tests; `target_pose`: the prior map's pose of a prior keyframe."""
        p = self.params
        points, normals = target.with_normals(p.normal_radius_m)
        tree = cKDTree(points)
        # the coarse pass only needs to get into the fine pass's basin: a quarter of the points do
        coarse = icp_point_to_plane(cloud.points[::COARSE_SUBSAMPLE], points, normals, init, p.coarse_distance_m,
                                    p.max_iterations, tree)
        fine = icp_point_to_plane(cloud.points, points, normals, coarse.transform, p.fine_distance_m,
                                  p.max_iterations, tree)
        self.counters["registered"] += 1
        if fine.fitness < p.min_fitness:
            self.counters["rejected_fitness"] += 1
            return None
        if fine.rmse_m > p.max_rmse_m:
            self.counters["rejected_rmse"] += 1
            return None
        if fine.constraint < p.min_constraint:
            self.counters["rejected_degenerate"] += 1
            return None
        correction = float(np.linalg.norm(fine.transform[:3, 3] - init[:3, 3]))
        if correction > p.max_correction_m:
            self.counters["rejected_correction"] += 1
            return None
        self.counters["accepted"] += 1
        return LoopClosure(target.frame_id, cloud.frame_id, fine.transform, fine.fitness, fine.rmse_m,
                           fine.constraint, correction, target_pose)

    def close(self, graph: PoseGraph, cloud: KeyframeCloud, against_prior: bool = False) -> LoopClosure | None:
        """After `graph.update()` for `cloud`'s frame: look for a closure and, if one is found, add it to the
        graph and update again (so the published poses include it). `against_prior`: the graph is in the prior
        map's frame, so its keyframes are targets too."""
        # only the poses it looks at (the kept keyframes' and its own), not the whole trajectory
        ids, _ = graph.frame_table()
        wanted = np.array(sorted({*self.keyframes, cloud.frame_id}), dtype=np.int64)
        rows = np.minimum(np.searchsorted(ids, wanted), max(len(ids) - 1, 0))
        ok = ids[rows] == wanted if len(ids) else np.zeros(len(wanted), bool)
        # (a pair is tried where the odometry is declared less precise than a closure, however far it has earned
        # trust since: a closure is also the witness of that trust, trust.py)
        closure = self.process(cloud, wanted[ok], graph.corrected_rows(rows[ok]),
                               lambda a, b: graph.odometry_sigmas_between(a, b, declared=True), against_prior)
        if closure is not None:
            self.add_to(graph, closure)
        return closure

    def restore(self, graph: PoseGraph, cloud: KeyframeCloud, closure: LoopClosure | None) -> None:
        """Redo a journalled keyframe (`decode_keyframe`) after `graph.update()` for its frame: the same closure
        goes into the graph, the same cloud is kept."""
        self.counters["keyframes"] += 1
        if closure is not None:
            self.counters["accepted"] += 1
            self.add_to(graph, closure)
        elif len(cloud.points) >= MIN_POINTS:
            self.keep(cloud)

    def add_to(self, graph: PoseGraph, closure: LoopClosure) -> None:
        """Add a closure (found now or read back from a journal) as a relative-pose factor (a pose prior when it
        is to a prior map's keyframe), then update."""
        sigma_t, sigma_r = self.params.sigma_translation_m, math.radians(self.params.sigma_rotation_deg)
        if closure.T_wa is not None:
            graph.add_pose_prior(closure.frame_b, closure.T_wa @ closure.T_ab, sigma_t, sigma_r)
        elif graph.witness_closure(closure.frame_a, closure.frame_b, closure.T_ab, sigma_t, sigma_r):
            # as precise as the closures have shown themselves to be, never more than declared
            sigma_t, sigma_r = graph.trust.closure_sigmas((sigma_t, sigma_r))
            graph.add_relative_pose_constraint(closure.frame_a, closure.frame_b, closure.T_ab, sigma_t, sigma_r)
        else:  # the odometry earned more trust than the closure is precise: it only witnessed
            self.counters["witnessed_only"] = self.counters.get("witnessed_only", 0) + 1
        graph.update()


# ------------------------------------------------------------------------------------------------ journal


def encode_keyframe(cloud: KeyframeCloud, closure: LoopClosure | None) -> bytes:
    """A handled keyframe (its cloud as it was before any use, and the closure it made) for the backend's
    journal: after a crash the graph gets the same closure again and the closer the same clouds, no ICP rerun."""
    record: dict = {"frame_id": cloud.frame_id, "stamp": cloud.stamp,
                    "points": np.ascontiguousarray(cloud.points, dtype="<f4").tobytes(), "closure": None}
    if closure is not None:
        record["closure"] = {"frame_a": closure.frame_a, "T_ab": np.asarray(closure.T_ab, "<f8").tobytes(),
                             "fitness": closure.fitness, "rmse_m": closure.rmse_m,
                             "constraint": closure.constraint, "correction_m": closure.correction_m,
                             "T_wa": None if closure.T_wa is None else np.asarray(closure.T_wa, "<f8").tobytes()}
    return msgpack.packb(record, use_bin_type=True)


def decode_keyframe(body: bytes) -> tuple[KeyframeCloud, LoopClosure | None]:
    record = msgpack.unpackb(body, raw=False)
    points = np.frombuffer(record["points"], dtype="<f4").reshape(-1, 3).copy()
    cloud = KeyframeCloud(int(record["frame_id"]), float(record["stamp"]), points)
    c = record["closure"]
    if c is None:
        return cloud, None
    T_ab = np.frombuffer(c["T_ab"], dtype="<f8").reshape(4, 4).copy()
    T_wa = c.get("T_wa")  # (absent in a journal written before prior-map closures)
    T_wa = None if T_wa is None else np.frombuffer(T_wa, dtype="<f8").reshape(4, 4).copy()
    return cloud, LoopClosure(int(c["frame_a"]), cloud.frame_id, T_ab, float(c["fitness"]), float(c["rmse_m"]),
                              float(c["constraint"]), float(c["correction_m"]), T_wa)

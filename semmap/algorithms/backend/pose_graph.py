"""The backend's incremental pose graph (paper: "semantic landmarks constrain the SLAM trajectory").

Variables: X(frame_id) camera-to-world poses of keyframes and of every frame that carries a landmark factor,
L(j) landmark positions. Factors: a prior on the first node, odometry BetweenFactorPose3 between consecutive
nodes, robust BearingRangeFactor3D landmark observations, zero BetweenFactorPoint3 for merged landmarks and
optional robust BetweenFactorPose3 relative-pose constraints (e.g. from ICP between object clouds).

Why this shape:
- iSAM2, one update per frame: a few ms per frame at 1000 frames (7-Scenes: p50 ~3 ms with the estimate),
  where a batch solve would grow with the whole trajectory.
- Nodes only where needed: non-keyframes without observations keep their odometry and are interpolated
  (corrected(f) = corrected(prev node) @ inv(odom(prev node)) @ odom(f)), so every frame still gets a pose.
- A frame can become a node late (its observations arrive after later frames' odometry, or its landmark only
  becomes trusted later): the odometry factor that spanned it is removed from iSAM2 and replaced by two.
- Landmarks enter the graph only after `min_observations_per_landmark` observations: one spurious detection
  never becomes a variable. Observations of a not-yet-trusted landmark wait and are added when it qualifies.
- Merges keep both variables and join them with a tight zero BetweenFactorPoint3 (no factor re-keying, no
  history rewrite); later observations of the absorbed id are re-keyed to the survivor (union-find).
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Hashable, Iterable
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from semmap.core.config import BackendParams
from semmap.core.geometry import carry_correction, correction, interpolate_pose, inv_rigid, rotation_angle
from semmap.core.messages import Observation, Observations, OdometryPose

from . import factors
from .trust import OdometryTrust

MAX_FRAMES_WAITING_FOR_ODOMETRY = 300  # frames whose observations arrived before their odometry
# a node is read again when its iSAM2 delta changed by more than this (rad or m) since its last read
ESTIMATE_READ_TOLERANCE = 1e-5


RETIRED_PRIOR_SIGMA_M = 1.0  # the loose prior that keeps a retired landmark's variable determined


class PoseGraphError(ValueError):
    """A call the graph cannot honour (unknown frame, bad pose or sigma)."""


def _checked_pose(pose: np.ndarray, sigma_translation: float, sigma_rotation: float, name: str,
                  what: str) -> np.ndarray:
    """A measured pose as float64 4x4, refused when not finite or its sigmas are not positive."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise PoseGraphError(f"{name} must be a finite 4x4")
    if not (sigma_translation > 0 and sigma_rotation > 0):
        raise PoseGraphError(f"{what} sigmas must be positive")
    return pose


def _whitened(expected: np.ndarray, actual: np.ndarray, sigma_t: float, sigma_r: float) -> float:
    """The squared difference of two relative poses in units of their sigmas (translation m, rotation rad)."""
    offset = float(np.linalg.norm((inv_rigid(expected) @ actual)[:3, 3]))
    return (offset / sigma_t) ** 2 + (float(rotation_angle(expected[:3, :3], actual[:3, :3])) / sigma_r) ** 2


@dataclass(slots=True)  # one per frame for the whole run: no per-instance dict
class _Odometry:
    stamp: float
    pose: np.ndarray
    sigma_translation: float
    sigma_rotation: float
    keyframe: bool


class _OdometryTable:
    """Odometry as contiguous arrays for vectorised interpolation: appended in place (the common, in-order
    case), rebuilt from the dict only after an out-of-order or repeated frame."""

    def __init__(self) -> None:
        self._ids = np.zeros(0, np.int64)
        self._stamps = np.zeros(0)
        self._poses = np.zeros((0, 4, 4))
        self._n = 0
        self._stale = False

    def put(self, frame_id: int, stamp: float, pose: np.ndarray, appended: bool) -> None:
        if not appended or self._stale:
            self._stale = True
            return
        if self._n == len(self._ids):
            capacity = max(64, 2 * self._n)
            self._ids = np.resize(self._ids, capacity)
            self._stamps = np.resize(self._stamps, capacity)
            self._poses = np.resize(self._poses, (capacity, 4, 4))
        self._ids[self._n], self._stamps[self._n], self._poses[self._n] = frame_id, stamp, pose
        self._n += 1

    def arrays(self, frames: list[int], odom: dict[int, _Odometry]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, stamps, poses) views in frame order (copy before writing to them)."""
        if self._stale:
            self._ids = np.array(frames, dtype=np.int64)
            self._stamps = np.array([odom[f].stamp for f in frames], dtype=np.float64)
            self._poses = np.stack([odom[f].pose for f in frames]) if frames else np.zeros((0, 4, 4))
            self._n, self._stale = len(frames), False
        return self._ids[: self._n], self._stamps[: self._n], self._poses[: self._n]


class GrowingRows:
    """A growing stack of equally shaped rows: appends are amortised O(1) (the buffer doubles)."""

    def __init__(self, shape: tuple[int, ...], fill: float) -> None:
        self._buf = np.full((64, *shape), fill)
        self._fill = fill
        self.n = 0

    @property
    def rows(self) -> np.ndarray:
        """The rows as a view (valid until the next append or insert)."""
        return self._buf[: self.n]

    def insert(self, i: int, row: np.ndarray) -> None:
        if self.n == len(self._buf):
            grown = np.full((2 * self.n, *self._buf.shape[1:]), self._fill)
            grown[: self.n] = self._buf
            self._buf = grown
        if i < self.n:  # a row in the middle: the rest moves (rare: a frame that became a node late)
            self._buf[i + 1 : self.n + 1] = self._buf[i : self.n].copy()
        self._buf[i] = row
        self.n += 1

    def replace(self, rows: np.ndarray) -> None:
        self._buf = np.concatenate([rows, np.full((max(64, len(rows)), *rows.shape[1:]), self._fill)])
        self.n = len(rows)


class PoseGraph:
    """Incremental iSAM2 graph of odometry and landmark observations. Not thread-safe: one owner calls it."""

    def __init__(self, params: BackendParams | None = None) -> None:
        self.params = params or BackendParams()
        isam_params = gtsam.ISAM2Params()
        isam_params.relinearizeSkip = self.params.relinearize_skip
        isam_params.setRelinearizeThreshold(self.params.relinearize_threshold)
        self._isam_params = isam_params
        self._isam = gtsam.ISAM2(isam_params)
        # odometry: every frame that had one, sorted ids for interpolation and chain noise
        self._odom: dict[int, _Odometry] = {}
        self._frames: list[int] = []
        self._table = _OdometryTable()
        # prefix sums of the per-frame odometry variances over _frames, valid for the first _cum_valid frames
        self._cum_var_t: list[float] = [0.0]
        self._cum_var_r: list[float] = [0.0]
        self._cum_valid = 0
        # pose nodes (in iSAM2 or pending) and those already in iSAM2 (what the estimate holds)
        self._nodes: list[int] = []
        self._node_set: set[int] = set()
        self._isam_nodes: list[int] = []
        self._pending_nodes: list[int] = []
        # factors waiting for the next update; tags name factors that may be replaced later
        self._new_factors: list[tuple[Hashable | None, gtsam.NonlinearFactor | None]] = []
        self._new_tag_pos: dict[Hashable, int] = {}
        self._new_values = gtsam.Values()
        self._factor_ids: dict[Hashable, int] = {}
        self._remove: list[int] = []
        # landmarks: union-find of merges, observation counts, waiting observations, variable of each root
        self._parent: dict[int, int] = {}
        self._count: dict[int, int] = {}
        self._waiting: dict[int, list[tuple[int, Observation]]] = {}
        self._var: dict[int, int] = {}
        self._isam_vars: set[int] = set()
        self._pending_vars: list[int] = []
        self._unposed: dict[int, list[Observation]] = {}  # observations that arrived before their odometry
        # per-node estimates kept up to date incrementally (see _refresh_estimates), aligned with _isam_nodes
        self._est = GrowingRows((4, 4), 0.0)
        self._ref = GrowingRows((6,), np.nan)  # iSAM2's delta of each node when its estimate was last read
        self._moved_nodes: set[int] = set()  # nodes whose estimate changed since `take_moved_nodes()`
        self._obs_tags: dict[int, set[Hashable]] = {}  # root -> tags of its observation factors (to retire them)
        self._obs_seq = 0
        # what settling needs to turn a factor on a settled node into a prior on what stays (see _settle_oldest)
        # frame, root, var, point, sigma, range sigma
        self._obs_records: dict[Hashable, tuple[int, int, int, np.ndarray, float, float]] = {}
        self._rel_records: dict[Hashable, tuple[int, int, np.ndarray, float, float, str]] = {}
        self._rel_seq = 0
        # var -> (information 3x3, information @ point), summed over its observations from settled frames
        self._settled_points: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # the first _n_settled entries of _isam_nodes are settled: their estimate is kept, they are not in iSAM2,
        # and no factor touches a frame up to _settled_horizon any more
        self._n_settled = 0
        self._settled_horizon = -1
        self._retired: set[int] = set()  # roots of landmarks whose object moved: no factor of theirs pulls
        self.last_update_ms = 0.0
        # (m, rad) of the first pose's prior instead of the params': a session relocalised against a prior map
        # holds its start only as well as the fit knew it, and lets the anchored landmarks place it
        self.first_prior: tuple[float, float] | None = None
        self.counters: dict[str, int] = {
            "odometry": 0, "observations": 0, "observation_factors": 0, "observations_dropped": 0,
            "observations_waiting_for_odometry": 0, "merges": 0, "relative_pose_constraints": 0, "updates": 0,
            "factors_replaced": 0, "observations_ignored": 0, "estimates_read": 0, "estimate_full_reads": 0,
            "landmarks_retired": 0, "factors_retired": 0, "observations_retired": 0,
            "nodes_settled": 0, "settles": 0, "observations_settled": 0, "pose_priors": 0,
            "pose_priors_on_settled": 0, "qr_refactorisations": 0,
        }
        self.refactorised_because = ""  # why iSAM2 was rebuilt with QR factorisation, if it was
        self._bridged: list[int] = []  # frames bridged (no measurement) since the last measured one
        self._last_measured: int | None = None
        self._unmeasured: set[int] = set()  # frames whose pose is a stand-in: left out of `measured_poses`
        # how far the odometry is trusted beyond its declared sigmas, as the closures that witnessed it earned
        self.trust = OdometryTrust()
        self.trust_factors = (1.0, 1.0)  # (translation, rotation): the chain sigmas are scaled by these

    # ------------------------------------------------------------------------------------------ inputs

    def add_odometry(self, frame_id: int, stamp: float, pose: np.ndarray, sigma_translation: float,
                     sigma_rotation: float, keyframe: bool = True, bridged: bool = False) -> None:
        """Record a frame's odometry pose (camera-to-world) with the front end's per-frame sigmas (m, rad).

        A keyframe (and the very first frame) becomes a node; a later message for the same frame replaces the
        earlier one (and the node's odometry factors when it is a node). `bridged` frames (the front end measured
        nothing of them) are placed between their measured neighbours once the next measured frame arrives
        (`_place_bridged`).
        """
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise PoseGraphError(f"frame {frame_id}: odometry pose must be a finite 4x4")
        if not (sigma_translation > 0 and sigma_rotation > 0):
            raise PoseGraphError(f"frame {frame_id}: odometry sigmas must be positive")
        frame_id = int(frame_id)
        pose = factors.pose3(pose).matrix()  # re-orthonormalised: interpolation inverts with a transpose
        known = frame_id in self._odom
        self._odom[frame_id] = _Odometry(float(stamp), pose.copy(), float(sigma_translation),
                                         float(sigma_rotation), bool(keyframe))
        self.counters["odometry"] += 1
        if not known:
            bisect.insort(self._frames, frame_id)
        self._cum_valid = min(self._cum_valid, bisect.bisect_left(self._frames, frame_id))  # sums from here on
        self._table.put(frame_id, float(stamp), pose, appended=not known and frame_id == self._frames[-1])
        if frame_id in self._node_set:
            self._rebuild_chains(frame_id)
        elif keyframe or not self._nodes:
            self._ensure_node(frame_id)
        if bridged:
            self._bridged.append(frame_id)
            self._unmeasured.add(frame_id)
        else:
            self._unmeasured.discard(frame_id)
            if self._bridged:
                self._place_bridged(frame_id)
            self._last_measured = frame_id
        waiting = self._unposed.pop(frame_id, None)
        if waiting:
            self.add_observations(frame_id, waiting)

    def closure_agreement(self, frame_ids: Iterable[int], poses: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """How well each relative-pose constraint the graph holds (loop closures: semmap's registrations of
        keyframes, evidence neither odometry was fitted to) agrees with the odometry now, and with `poses` in
        place of the frames' odometry: their squared whitened errors, one pair per constraint."""
        replaced = {int(f): np.asarray(p, dtype=np.float64) for f, p in zip(frame_ids, poses, strict=True)}
        now, then = [], []
        for a, b, T_ab, sigma_t, sigma_r, _ in self._rel_records.values():
            odometry_a, odometry_b = self._odom.get(a), self._odom.get(b)
            if odometry_a is None or odometry_b is None:
                continue
            now.append(_whitened(T_ab, inv_rigid(odometry_a.pose) @ odometry_b.pose, sigma_t, sigma_r))
            then.append(_whitened(T_ab, inv_rigid(replaced.get(a, odometry_a.pose)) @ replaced.get(b, odometry_b.pose),
                                  sigma_t, sigma_r))
        return np.array(now), np.array(then)

    def refine_odometry(self, frame_ids: Iterable[int], poses: Iterable[np.ndarray]) -> int:
        """The front end's odometry of earlier frames again, refined by its SLAM at its end (OdometryRefinement):
        each replaces the frame's odometry pose (its sigmas and keyframe flag stay), the chains of the nodes among
        them are rebuilt, and the next `update` optimises with them. A frame the graph does not hold, or holds as a
        stand-in, is passed over. Settled nodes keep their estimate (`active_window_nodes`): only the frames around
        them follow. Returns how many frames took their refined pose."""
        taken = 0
        nodes: set[int] = set()
        for frame_id, pose in zip(frame_ids, poses, strict=True):
            frame_id = int(frame_id)
            odometry = self._odom.get(frame_id)
            pose = np.asarray(pose, dtype=np.float64)
            usable = pose.shape == (4, 4) and bool(np.all(np.isfinite(pose)))
            if odometry is None or frame_id in self._unmeasured or not usable:
                continue
            odometry.pose = factors.pose3(pose).matrix()
            self._table.put(frame_id, odometry.stamp, odometry.pose, appended=False)
            taken += 1
            if frame_id in self._node_set:
                nodes.add(frame_id)
        for a, b in zip(self._nodes, self._nodes[1:], strict=False):  # (each chain once, not once per end)
            if (a in nodes or b in nodes) and b > self._settled_horizon:
                self._drop(("odo", a, b))
                self._add_chain(a, b)
        self.counters["odometry_refined"] = self.counters.get("odometry_refined", 0) + taken
        return taken

    def _place_bridged(self, frame_id: int) -> None:
        """The frames bridged since the last measured one, placed between it and `frame_id` by time (linear in
        translation, slerp in rotation): a gap is not one step of the motion model's per frame. The stand-in poses
        guessed while the SLAM had lost track are replaced (TUM fr1_rpy, ORB-SLAM3 lost for 5 frames of a fast
        turn: the motion model put them 5-7 cm off)."""
        run, self._bridged = self._bridged, []
        start = self._last_measured
        if start is None or start not in self._odom:
            return
        a, b = self._odom[start], self._odom[frame_id]
        for f in run:
            o = self._odom.get(f)
            if o is None or not a.stamp < o.stamp < b.stamp:
                continue
            o.pose = factors.pose3(interpolate_pose(a.pose, b.pose, (o.stamp - a.stamp) / (b.stamp - a.stamp))).matrix()
            self._table.put(f, o.stamp, o.pose, appended=False)
            self.counters["bridged_placed"] = self.counters.get("bridged_placed", 0) + 1
            if f in self._node_set:
                self._rebuild_chains(f)

    def add_observations(self, frame_id: int, observations: Iterable[Observation]) -> None:
        """Landmark centroids seen from `frame_id` (camera frame). Buffered if that frame has no odometry yet."""
        frame_id = int(frame_id)
        observations = list(observations)
        if frame_id not in self._odom:
            self._unposed.setdefault(frame_id, []).extend(observations)
            self.counters["observations_waiting_for_odometry"] += len(observations)
            while len(self._unposed) > MAX_FRAMES_WAITING_FOR_ODOMETRY:  # odometry that never comes
                self.counters["observations_dropped"] += len(self._unposed.pop(min(self._unposed)))
            return
        if not self.params.landmark_constraints:
            self.counters["observations_ignored"] += len(observations)
            return
        for obs in observations:
            point = np.asarray(obs.point_camera, dtype=np.float64)
            if not np.all(np.isfinite(point)) or np.linalg.norm(point) < max(self.params.observation_min_range_m,
                                                                             1e-6):
                self.counters["observations_dropped"] += 1
                continue
            self.counters["observations"] += 1
            root = self._root(obs.landmark_id)
            if root in self._retired:  # (sent before the retirement reached us, or a replay)
                self.counters["observations_retired"] += 1
                continue
            self._count[root] = self._count.get(root, 0) + 1
            if root in self._var:
                self._add_observation_factor(frame_id, obs, root)
            else:
                self._waiting.setdefault(root, []).append((frame_id, obs))
                if self._count[root] >= self.params.min_observations_per_landmark:
                    self._activate(root)

    def anchor_landmark(self, landmark_id: int, position: np.ndarray, sigma_m: float) -> None:
        """A prior map's landmark, held at `position` (the map's frame) by a prior factor: what ties a relocalised
        session's trajectory to the map it was placed in. It is a variable at once (no observation count)."""
        root = self._root(int(landmark_id))
        position = np.asarray(position, dtype=np.float64)
        if root not in self._var:
            self._var[root] = root
            self._new_values.insert(L(root), position)
            self._pending_vars.append(root)
            for frame_id, obs in self._waiting.pop(root, []):
                self._add_observation_factor(frame_id, obs, root)
        self._push(None, gtsam.PriorFactorPoint3(L(root), position, gtsam.noiseModel.Isotropic.Sigma(3, sigma_m)))
        self.counters["anchors"] = self.counters.get("anchors", 0) + 1

    def merge_landmarks(self, absorbed_id: int, surviving_id: int) -> None:
        """The associator found two landmarks to be one object (often a revisit after drift: a loop closure).

        Both variables stay; a zero BetweenFactorPoint3 (sigma `merge_sigma_m`) joins them, and observations of
        `absorbed_id` from now on go to the survivor's variable. If only the absorbed one is in the graph the
        survivor adopts its variable; waiting observations and counts are pooled.
        """
        a, s = self._root(int(absorbed_id)), self._root(int(surviving_id))
        if a == s or a in self._retired or s in self._retired:  # a retired landmark joins nothing
            return
        self.counters["merges"] += 1
        self._parent[a] = s
        self._obs_tags.setdefault(s, set()).update(self._obs_tags.pop(a, set()))
        self._count[s] = self._count.get(s, 0) + self._count.pop(a, 0)
        va, vs = self._var.pop(a, None), self._var.get(s)
        if va is not None and vs is not None:
            self._push(None, factors.merge_factor(L(va), L(vs), self.params.merge_sigma_m))
        elif va is not None:
            self._var[s] = va
        waiting = self._waiting.pop(a, []) + self._waiting.pop(s, [])
        if s in self._var:
            for frame_id, obs in waiting:
                self._add_observation_factor(frame_id, obs, s)
        elif waiting:
            self._waiting[s] = waiting
            if self._count[s] >= self.params.min_observations_per_landmark:
                self._activate(s)

    def retire_landmark(self, landmark_id: int) -> None:
        """The associator saw the landmark's object move: drop every observation factor of it (and of landmarks
        merged into it) so it stops pulling the trajectory towards where the object was; later observations of
        it are ignored. Its variable stays, held by a loose prior (iSAM2 cannot drop a variable)."""
        root = self._root(int(landmark_id))
        if root in self._retired:
            return
        self._retired.add(root)
        self.counters["landmarks_retired"] += 1
        self._waiting.pop(root, None)
        for tag in self._obs_tags.pop(root, set()):
            self._drop(tag)
            self._obs_records.pop(tag, None)
            if tag[0] == "settled":
                self._settled_points.pop(tag[1], None)
            self.counters["factors_retired"] += 1
        var = self._var.get(root)
        if var is not None:
            self._push(None, factors.point_prior_factor(L(var), self._landmark_estimate(var), RETIRED_PRIOR_SIGMA_M))

    def add_relative_pose_constraint(self, frame_a: int, frame_b: int, T_ab: np.ndarray, sigma_translation: float,
                                     sigma_rotation: float, robust: bool = True) -> None:
        """A measured pose of frame b in frame a (`inv(T_a) @ T_b`), e.g. from ICP between an observation's
        cloud and its landmark's cloud. Robust (`relative_pose_kernel`) by default: a wrong ICP must not wreck it."""
        for f in (frame_a, frame_b):
            if int(f) not in self._odom:
                raise PoseGraphError(f"relative pose constraint on frame {f}, which has no odometry")
        T_ab = _checked_pose(T_ab, sigma_translation, sigma_rotation, "T_ab", "relative pose")
        if int(frame_a) == int(frame_b):
            raise PoseGraphError("a relative pose constraint needs two different frames")
        self._ensure_node(int(frame_a))
        self._ensure_node(int(frame_b))
        kernel = self.params.relative_pose_kernel if robust else "none"
        tag = ("rel", self._rel_seq)
        self._rel_seq += 1
        self._rel_records[tag] = (int(frame_a), int(frame_b), T_ab, float(sigma_translation), float(sigma_rotation),
                                  kernel)
        factor = self._relative_factor(tag)
        if factor is not None:
            self._push(tag, factor)
        self.counters["relative_pose_constraints"] += 1

    def add_pose_prior(self, frame_id: int, pose: np.ndarray, sigma_translation: float, sigma_rotation: float,
                       robust: bool = True) -> None:
        """A measured world pose of a frame, e.g. from ICP against a prior map's keyframe whose pose the map
        holds fixed. Robust (`relative_pose_kernel`) by default. On a settled frame it has nothing left to move
        and is dropped (counted)."""
        frame_id = int(frame_id)
        if frame_id not in self._odom:
            raise PoseGraphError(f"pose prior on frame {frame_id}, which has no odometry")
        pose = _checked_pose(pose, sigma_translation, sigma_rotation, "a pose prior", "pose prior")
        if frame_id <= self._settled_horizon:
            self.counters["pose_priors_on_settled"] += 1
            return
        self._ensure_node(frame_id)
        kernel = self.params.relative_pose_kernel if robust else "none"
        # tagged "prior": when its node settles, the factor goes with it (see _settle_oldest)
        self._push(("prior", "pose", self._rel_seq), factors.prior_factor(
            X(frame_id), pose, float(sigma_translation), float(sigma_rotation), kernel, self.params.robust_k))
        self._rel_seq += 1
        self.counters["pose_priors"] += 1

    def add_odometry_message(self, msg: OdometryPose) -> None:
        self.add_odometry(msg.frame_id, msg.stamp, msg.pose, msg.sigma_translation, msg.sigma_rotation, msg.keyframe,
                          msg.bridged)

    def add_observations_message(self, msg: Observations) -> None:
        """Merges first (the message's observations may already use surviving ids), then observations."""
        for absorbed, surviving in msg.merges:
            self.merge_landmarks(absorbed, surviving)
        for landmark_id in msg.retired:
            self.retire_landmark(landmark_id)
        self.add_observations(msg.frame_id, msg.observations)

    # ------------------------------------------------------------------------------------------ solving

    def update(self) -> None:
        """One iSAM2 step with everything added since the last call (call once per frame)."""
        start = time.perf_counter()
        self._isam_update(self._new_values)
        for node in sorted(self._pending_nodes):
            i = bisect.bisect_left(self._isam_nodes, node)
            self._isam_nodes.insert(i, node)
            self._est.insert(i, np.eye(4))  # (read in _refresh_estimates below: its reference delta is NaN)
            self._ref.insert(i, np.full(6, np.nan))
        self._isam_vars.update(self._pending_vars)
        self._new_values = gtsam.Values()
        self._pending_nodes, self._pending_vars = [], []
        # the nodes' estimates are needed every frame (new nodes start from them, the service publishes them);
        # reading them is iSAM2's deferred back-substitution, so it belongs to the update's time
        self._refresh_estimates()
        window = self.params.active_window_nodes
        if window and len(self._isam_nodes) - self._n_settled >= window + self.params.settle_batch_nodes:
            self._settle_oldest(window)
        self.counters["updates"] += 1
        self.last_update_ms = (time.perf_counter() - start) * 1e3

    def _isam_update(self, values: gtsam.Values) -> None:
        """Hand the pending factors, removals and `values` to iSAM2 and remember where the tagged factors went."""
        graph = gtsam.NonlinearFactorGraph()
        tags: list[Hashable | None] = []
        for tag, factor in self._new_factors:
            if factor is not None:
                graph.add(factor)
                tags.append(tag)
        slots_before = self._isam.getFactorsUnsafe().size()
        try:
            result = self._isam.update(graph, values, self._remove)
        except RuntimeError as exc:
            if "Indeterminate" not in str(exc):
                raise
            self._refactor_by_qr(tags, slots_before, str(exc).strip().splitlines()[0])
        else:
            for tag, index in zip(tags, result.getNewFactorsIndices(), strict=True):
                if tag is not None:
                    self._factor_ids[tag] = int(index)
        self._new_factors, self._new_tag_pos, self._remove = [], {}, []

    def _refactor_by_qr(self, new_tags: list[Hashable | None], slots_before: int, why: str) -> None:
        """iSAM2's Cholesky gave up on a graph that is solvable but badly conditioned: rebuild it from the same
        factors and values, factorised by QR from now on (slower, numerically stable).

        Why it happens: a long chain anchored only at its start (a street: 300 m in 330 frames) leaves its newest
        poses and landmarks free to swing together by tens of metres (Hessian eigenvalues ~2e-4) while each step is
        pinned to millimetres (~3e7): a condition number of 1e11, which Levenberg-Marquardt and QR solve and
        Cholesky's pivot test refuses ("Indeterminate linear system"). The failed update has already taken the
        new factors (appended after `slots_before`) and values, so the rebuild reads everything from it.
        """
        self.refactorised_because = why  # (counted in `qr_refactorisations`; the backend's status shows both)
        index_tag = {index: tag for tag, index in self._factor_ids.items()}
        index_tag.update({slots_before + i: tag for i, tag in enumerate(new_tags) if tag is not None})
        removed = set(self._remove)
        failed = self._isam.getFactorsUnsafe()
        graph, tags = gtsam.NonlinearFactorGraph(), []
        for index in range(failed.size()):
            factor = failed.at(index)
            if factor is None or index in removed:
                continue
            graph.add(factor)
            tags.append(index_tag.get(index))
        values = gtsam.Values(self._isam.getLinearizationPoint())
        self._isam_params.setFactorization("QR")
        self._isam = gtsam.ISAM2(self._isam_params)
        result = self._isam.update(graph, values)
        self._factor_ids = {tag: int(index) for tag, index in zip(tags, result.getNewFactorsIndices(), strict=True)
                            if tag is not None}
        self._ref.rows[self._n_settled :] = np.nan  # a new iSAM2: read every live node again
        self.counters["qr_refactorisations"] += 1

    # ------------------------------------------------------------------------------------------ settling

    def _settle_oldest(self, window: int) -> None:
        """Settle every node but the newest `window`: bounded cost per update, however long the trajectory.

        Why: iSAM2 re-eliminates the path from a touched variable to the root, and landmarks and loop closures tie
        the newest node to the whole trajectory, so an update grew with it (19 ms p95 after 10,000 frames against
        1 ms after 1,000). A settled node keeps its last estimate (frames riding on it too) and leaves iSAM2; each
        factor that tied it to what stays becomes a prior on what stays, with the settled estimate as a constant:
        the odometry into the window a pose prior on its first node, a loop closure a pose prior on its live end,
        and every observation from a settled node part of one isotropic prior per landmark variable (information
        summed, each weighted by the robust kernel at the current estimate). iSAM2 cannot drop variables, so it is
        rebuilt from the factors that stay: one batch solve of the window every `settle_batch_nodes` nodes.
        This is conditioning, not marginalisation: settled poses count as exact, which is what a map that keeps
        its landmarks fixed does; the landmarks still move with what the window sees.
        """
        s = self._n_settled
        newly = self._isam_nodes[s : len(self._isam_nodes) - window]
        estimate = self._isam.calculateEstimate()
        self._settled_horizon = newly[-1]
        self._n_settled += len(newly)
        settled_keys = {X(n) for n in newly}
        index_tag = {index: tag for tag, index in self._factor_ids.items()}
        self._factor_ids, self._remove = {}, []
        old = self._isam.getFactorsUnsafe()
        kept: list[tuple[Hashable | None, gtsam.NonlinearFactor]] = []
        touched: dict[int, int] = {}  # landmark variable -> its root, whose settled prior is to be rewritten
        for index in range(old.size()):
            factor = old.at(index)
            if factor is None:  # removed earlier
                continue
            tag = index_tag.get(index)
            if settled_keys.isdisjoint(factor.keys()):  # noqa: SIM118 (a gtsam factor, not a dict)
                kept.append((tag, factor))
                continue
            kind = tag[0] if isinstance(tag, tuple) else None
            if kind == "odo":
                self._add_chain(tag[1], tag[2])
            elif kind == "rel":
                relative = self._relative_factor(tag)
                if relative is not None:
                    self._push(tag, relative)
            elif kind == "obs":
                frame_id, root, var, point, sigma, range_sigma = self._obs_records.pop(tag)
                self._obs_tags.get(self._root(root), set()).discard(tag)
                self._settle_observation(frame_id, root, var, point, sigma, range_sigma, estimate.atPoint3(L(var)))
                touched[var] = root
            elif kind != "prior":  # (every factor on a pose node is tagged: this would be a bookkeeping bug)
                raise PoseGraphError(f"cannot settle an untagged factor on keys {factor.keys()}")
        for var, root in touched.items():
            self._push_settled_prior(var, root)
        replaced = {tag for tag, _ in self._new_factors if tag is not None}
        self._new_factors = [(t, f) for t, f in kept if t is None or t not in replaced] + self._new_factors
        values = gtsam.Values(estimate)
        for node in newly:
            values.erase(X(node))
        self._isam = gtsam.ISAM2(self._isam_params)
        self._isam_update(values)
        self._ref.rows[self._n_settled :] = np.nan  # a new iSAM2: read every live node again
        self._refresh_estimates()
        self.counters["nodes_settled"] += len(newly)
        self.counters["settles"] += 1

    def _landmark_estimate(self, var: int) -> np.ndarray:
        key = L(var)
        if self._new_values.exists(key):
            return np.asarray(self._new_values.atPoint3(key), dtype=np.float64)
        return np.asarray(self._isam.calculateEstimatePoint3(key), dtype=np.float64)

    def _settle_observation(self, frame_id: int, root: int, var: int, point: np.ndarray, sigma: float,
                            range_sigma: float, landmark: np.ndarray) -> None:
        """Fold one observation from a settled frame into its landmark variable's settled prior (its information
        in the world frame, weighted by the robust kernel at its whitened residual)."""
        if self._root(root) in self._retired:
            return
        pose = self._frame_pose(frame_id)
        world = pose[:3, :3] @ point + pose[:3, 3]
        r = world - np.asarray(landmark, dtype=np.float64)
        if range_sigma > sigma:  # looser along the ray (`observation_range_sigma_size_factor`)
            info = factors.observation_information(pose[:3, :3] @ point, sigma, range_sigma)
            residual = math.sqrt(max(float(r @ info @ r), 0.0))
        else:
            info = np.eye(3) / sigma**2
            residual = float(np.linalg.norm(r)) / sigma
        info = factors.robust_weight(self.params.robust_kernel, self.params.robust_k, residual) * info
        total, weighted = self._settled_points.get(var, (np.zeros((3, 3)), np.zeros(3)))
        self._settled_points[var] = (total + info, weighted + info @ world)
        self.counters["observations_settled"] += 1

    def _push_settled_prior(self, var: int, root: int) -> None:
        if var not in self._settled_points:
            return
        total, weighted = self._settled_points[var]
        tag = ("settled", var)
        self._drop(tag)
        diagonal = total[0, 0]
        if not np.any(total - np.diag(np.diag(total))) and total[1, 1] == diagonal == total[2, 2]:  # isotropic
            prior = factors.point_prior_factor(L(var), weighted / diagonal, 1.0 / math.sqrt(diagonal))
        else:
            prior = factors.point_prior_factor(L(var), np.linalg.solve(total, weighted), total)
        self._push(tag, prior)
        self._obs_tags.setdefault(self._root(root), set()).add(tag)

    # ------------------------------------------------------------------------------------------ outputs

    def corrected_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(frame_ids int64 (N,), stamps (N,), poses (N,4,4)) for every frame with odometry, in frame order.

        Nodes come from the estimate; other frames ride on the previous node (the first node for frames before
        it). Nodes added since the last `update()` are treated like other frames.
        """
        ids, stamps, odom = self._table.arrays(self._frames, self._odom)
        ids, stamps = ids.copy(), stamps.copy()
        if not self._isam_nodes:
            return ids, stamps, odom.copy()
        node_ids = np.array(self._isam_nodes, dtype=np.int64)
        corrected_nodes = self._est.rows
        k = np.clip(np.searchsorted(node_ids, ids, side="right") - 1, 0, None)
        odom_nodes = odom[np.searchsorted(ids, node_ids)]
        per_node = correction(corrected_nodes, odom_nodes)  # per node: corrected <- odometry frame
        poses = per_node[k] @ odom
        is_node = node_ids[k] == ids
        poses[is_node] = corrected_nodes[k[is_node]]
        return ids, stamps, poses

    def measured_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`corrected_poses` without the frames no front end measured (bridged: the SLAM had lost track). Their
        stand-in poses serve the map while it is built, but a trajectory lists what was measured, as the SLAM's own
        does: an interpolated guess where the SLAM was failing is no estimate of where the camera was (TUM fr1_rpy,
        5 frames of a fast turn lost, 4-8 cm off)."""
        ids, stamps, poses = self.corrected_poses()
        if not self._unmeasured:
            return ids, stamps, poses
        keep = ~np.isin(ids, np.fromiter(self._unmeasured, dtype=np.int64))
        return ids[keep], stamps[keep], poses[keep]

    @property
    def num_unmeasured(self) -> int:
        """Frames whose pose is a stand-in (bridged), left out of `measured_poses`."""
        return len(self._unmeasured)

    def frame_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(frame_ids, stamps) of every frame with odometry, ascending (views: do not modify)."""
        ids, stamps, _ = self._table.arrays(self._frames, self._odom)
        return ids, stamps

    def corrected_rows(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), 4, 4) corrected poses of the frames at these rows of `frame_table()`, as
        `corrected_poses` computes them, at a cost in the number of rows (not of frames)."""
        ids, _, odom = self._table.arrays(self._frames, self._odom)
        rows = np.asarray(rows, dtype=np.int64)
        if not self._isam_nodes:
            return odom[rows].copy()
        nodes = np.asarray(self._isam_nodes, dtype=np.int64)
        k = np.maximum(np.searchsorted(nodes, ids[rows], side="right") - 1, 0)  # each row's node (vectorised)
        node_rows = np.searchsorted(ids, nodes[k])
        est = self._est.rows[k]
        poses = carry_correction(est, odom[node_rows], odom[rows])
        is_node = node_rows == rows
        poses[is_node] = est[is_node]
        return poses

    def corrected_pose(self, frame_id: int) -> np.ndarray:
        """The corrected 4x4 of one frame (KeyError if it never had odometry)."""
        frame_id = int(frame_id)
        if frame_id not in self._odom:
            raise KeyError(f"frame {frame_id} has no odometry")
        if not self._isam_nodes:
            return self._odom[frame_id].pose.copy()
        i = max(bisect.bisect_right(self._isam_nodes, frame_id) - 1, 0)
        node = self._isam_nodes[i]
        corrected = self._est.rows[i].copy()
        if node == frame_id:
            return corrected
        return carry_correction(corrected, self._odom[node].pose, self._odom[frame_id].pose)

    def odometry_pose(self, frame_id: int) -> np.ndarray:
        """The odometry 4x4 of one frame as the graph took it (KeyError if it never had odometry)."""
        return self._odom[int(frame_id)].pose.copy()

    def witness_closure(self, frame_a: int, frame_b: int, T_ab: np.ndarray, sigma_translation: float,
                        sigma_rotation: float) -> bool:
        """A closure's measured relative pose of two frames, first as a witness of the odometry (trust.py): it
        updates the trust the odometry earned (and the chain factors with it, when that changed by a quarter).
        Returns whether the closure still says more than the odometry between the two frames, i.e. whether it
        belongs in the graph."""
        a, b = int(frame_a), int(frame_b)
        odometry = inv_rigid(self._odom[a].pose) @ self._odom[b].pose
        self.trust.witness(odometry, np.asarray(T_ab, float), self.odometry_sigmas_between(a, b, declared=True),
                           (sigma_translation, sigma_rotation))
        factors_now = self.trust.factors()
        if any(abs(math.log(new / old)) > math.log(1.25) for new, old in zip(factors_now, self.trust_factors,
                                                                             strict=True)):
            self.trust_factors = factors_now
            self._rebuild_all_chains()
        self.counters["trust_translation_pct"] = round(100 * self.trust_factors[0])
        self.counters["trust_rotation_pct"] = round(100 * self.trust_factors[1])
        sigma_t, sigma_r = self.odometry_sigmas_between(a, b)
        return sigma_t > sigma_translation or sigma_r > sigma_rotation

    def _rebuild_all_chains(self) -> None:
        """Every odometry factor between live nodes again, with the current trust factors."""
        for a, b in zip(self._nodes, self._nodes[1:], strict=False):
            if b > self._settled_horizon:
                self._drop(("odo", a, b))
                self._add_chain(a, b)
        self.counters["trust_rebuilds"] = self.counters.get("trust_rebuilds", 0) + 1

    def odometry_sigmas_between(self, a: int, b: int, declared: bool = False) -> tuple[float, float]:
        """(m, rad) sigmas of the motion from frame a to frame b (a < b, both with odometry): the front end's
        per-frame variances add up (frames without odometry count with b's sigmas), scaled by the trust the
        odometry earned (`trust_factors`) unless `declared`."""
        i0, i1 = bisect.bisect_right(self._frames, a), bisect.bisect_right(self._frames, b)
        # prefix sums of the variances, extended lazily: O(log frames) for any span (a loop closure's spans
        # over thousands of frames, once per candidate, made this the loop-closure step's growing cost)
        cum_t, cum_r = self._cum_var_t, self._cum_var_r
        del cum_t[self._cum_valid + 1 :], cum_r[self._cum_valid + 1 :]
        for f in self._frames[len(cum_t) - 1 : i1]:
            o = self._odom[f]
            cum_t.append(cum_t[-1] + o.sigma_translation**2)
            cum_r.append(cum_r[-1] + o.sigma_rotation**2)
        self._cum_valid = len(cum_t) - 1
        missing = (b - a) - (i1 - i0)
        last = self._odom[b]
        var_t = cum_t[i1] - cum_t[i0] + missing * last.sigma_translation**2
        var_r = cum_r[i1] - cum_r[i0] + missing * last.sigma_rotation**2
        k_t, k_r = (1.0, 1.0) if declared else self.trust_factors
        return k_t * math.sqrt(max(var_t, 0.0)), k_r * math.sqrt(max(var_r, 0.0))

    def landmark_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids int64 (M,), positions (M,3)) of landmarks in the graph, by surviving id (absorbed ids omitted)."""
        items = sorted((lid, var) for lid, var in self._var.items()
                       if var in self._isam_vars and lid not in self._retired)
        if not items:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        positions = np.array([self._isam.calculateEstimatePoint3(L(var)) for _, var in items],
                             dtype=np.float64).reshape(-1, 3)
        return np.array([lid for lid, _ in items], dtype=np.int64), positions

    def resolve_landmark(self, landmark_id: int) -> int:
        """The surviving id a (possibly merged) landmark id now stands for."""
        return self._root(int(landmark_id))

    @property
    def num_nodes(self) -> int:
        return len(self._nodes)

    @property
    def num_landmarks(self) -> int:
        return len(self._var)

    @property
    def num_frames(self) -> int:
        return len(self._frames)

    # ------------------------------------------------------------------------------------------ internals

    def take_moved_nodes(self) -> list[int]:
        """The nodes (frame ids, ascending) whose estimate changed since the last call: new nodes and those iSAM2
        moved (relinearised or re-solved). Frames between two nodes ride on the earlier one."""
        moved, self._moved_nodes = sorted(self._moved_nodes), set()
        return moved

    def node_ids(self) -> list[int]:
        """Frame ids of the pose nodes in iSAM2, ascending (a view: do not modify)."""
        return self._isam_nodes

    def _refresh_estimates(self) -> None:
        """Bring the per-node estimates up to date, reading only the nodes whose iSAM2 delta changed.

        Why: the whole estimate (`calculateEstimate`) costs O(graph) every frame (27 ms at 10,000 poses here),
        although iSAM2 leaves settled parts alone. An estimate is the linearisation point retracted by the delta,
        and a relinearised node gets a new delta too, so a node whose delta is unchanged has an unchanged
        estimate. The delta comes as one vector ordered by key (landmarks 'l' before poses 'x'); comparing it to
        the delta each node had when last read is a vectorised pass, and only the nodes that moved (by more than
        ESTIMATE_READ_TOLERANCE, accumulated) are read. When many moved (a loop closed)
        one whole read is cheaper than many single ones.
        """
        s = self._n_settled  # settled nodes come first and never move
        n = len(self._isam_nodes) - s
        if n == 0:
            return
        vec = self._isam.getDelta().vector()
        start = 3 * len(self._isam_vars)
        if len(vec) != start + 6 * n:  # another kind of variable in the graph: read everything
            self._read_all_nodes(None)
            return
        delta = vec[start:].reshape(n, 6)
        tol = ESTIMATE_READ_TOLERANCE
        with np.errstate(invalid="ignore"):
            stale = np.flatnonzero(~(np.abs(delta - self._ref.rows[s:]).max(axis=1) <= tol))  # NaN: a new node
        if len(stale) > max(64, n // 8):
            self._read_all_nodes(delta)
            return
        est = self._est.rows
        for k in stale:
            est[s + k] = self._isam.calculateEstimatePose3(X(self._isam_nodes[s + k])).matrix()
        self._ref.rows[s + stale] = delta[stale]
        self._moved_nodes.update(self._isam_nodes[s + k] for k in stale)
        self.counters["estimates_read"] += len(stale)

    def _read_all_nodes(self, delta: np.ndarray | None) -> None:
        """Read every node still in iSAM2 (the settled ones keep their rows)."""
        s = self._n_settled
        rows = gtsam.utilities.extractPose3(self._isam.calculateEstimate())  # key order == frame order (only X)
        est = self._est.rows[s:]
        if len(rows) != len(est):
            raise PoseGraphError(f"iSAM2 holds {len(rows)} poses, the graph expects {len(est)}")
        est[:, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
        est[:, :3, 3] = rows[:, 9:]
        est[:, 3, :3] = 0.0
        est[:, 3, 3] = 1.0
        self._ref.rows[s:] = delta if delta is not None else np.nan
        self._moved_nodes.update(self._isam_nodes[s:])
        self.counters["estimate_full_reads"] += 1

    def _root(self, landmark_id: int) -> int:
        root = landmark_id
        while root in self._parent:
            root = self._parent[root]
        while landmark_id != root:  # path compression
            self._parent[landmark_id], landmark_id = root, self._parent[landmark_id]
        return root

    def _push(self, tag: Hashable | None, factor: gtsam.NonlinearFactor) -> None:
        if tag is not None:
            self._new_tag_pos[tag] = len(self._new_factors)
        self._new_factors.append((tag, factor))

    def _drop(self, tag: Hashable) -> None:
        """Remove a tagged factor, whether still pending or already inside iSAM2."""
        if tag in self._new_tag_pos:
            self._new_factors[self._new_tag_pos.pop(tag)] = (None, None)
        elif tag in self._factor_ids:
            self._remove.append(self._factor_ids.pop(tag))
            self.counters["factors_replaced"] += 1

    def _frame_pose(self, frame_id: int) -> np.ndarray:
        """A frame's current pose: its node's estimate (pending or solved), else interpolated."""
        if frame_id in self._node_set:
            return self._node_pose(frame_id)
        return self.corrected_pose(frame_id)

    def _node_pose(self, node: int) -> np.ndarray:
        key = X(node)
        if self._new_values.exists(key):
            return self._new_values.atPose3(key).matrix()
        return self._est.rows[bisect.bisect_left(self._isam_nodes, node)].copy()

    def _ensure_node(self, frame_id: int) -> None:
        if frame_id in self._node_set or frame_id <= self._settled_horizon:  # (a settled frame gets no new node)
            return
        i = bisect.bisect_left(self._nodes, frame_id)
        prev = self._nodes[i - 1] if i > 0 else None
        nxt = self._nodes[i] if i < len(self._nodes) else None
        odom = self._odom[frame_id].pose
        if prev is None and nxt is None:
            initial = odom
            sigma_t, sigma_r = self.first_prior or (self.params.prior_sigma_translation_m,
                                                    math.radians(self.params.prior_sigma_rotation_deg))
            self._push(("prior", frame_id), factors.prior_factor(X(frame_id), odom, sigma_t, sigma_r))
        else:
            ref = prev if prev is not None else nxt
            initial = carry_correction(self._node_pose(ref), self._odom[ref].pose, odom)
        self._new_values.insert(X(frame_id), factors.pose3(initial))
        self._nodes.insert(i, frame_id)
        self._node_set.add(frame_id)
        self._pending_nodes.append(frame_id)
        if prev is not None and nxt is not None:
            self._drop(("odo", prev, nxt))
        if prev is not None:
            self._add_chain(prev, frame_id)
        if nxt is not None:
            self._add_chain(frame_id, nxt)

    def _rebuild_chains(self, node: int) -> None:
        i = bisect.bisect_left(self._nodes, node)
        if i > 0:
            self._drop(("odo", self._nodes[i - 1], node))
            self._add_chain(self._nodes[i - 1], node)
        if i + 1 < len(self._nodes):
            self._drop(("odo", node, self._nodes[i + 1]))
            self._add_chain(node, self._nodes[i + 1])

    def _add_chain(self, a: int, b: int) -> None:
        """Odometry between consecutive nodes, with the sigmas of `odometry_sigmas_between`."""
        if b <= self._settled_horizon:  # both settled: nothing to constrain
            return
        sigma_t, sigma_r = self.odometry_sigmas_between(a, b)
        relative = inv_rigid(self._odom[a].pose) @ self._odom[b].pose
        if a <= self._settled_horizon:  # from a settled node: a prior on b where the odometry puts it
            factor = factors.prior_factor(X(b), self._frame_pose(a) @ relative, sigma_t, sigma_r)
        else:
            factor = factors.between_factor(X(a), X(b), relative, sigma_t, sigma_r)
        self._push(("odo", a, b), factor)

    def _relative_factor(self, tag: Hashable) -> gtsam.NonlinearFactor | None:
        """A relative-pose constraint as a factor: between two live nodes, a prior on the live one when the other
        is settled, nothing when both are (the record is then forgotten)."""
        a, b, T_ab, sigma_t, sigma_r, kernel = self._rel_records[tag]
        k = self.params.robust_k
        settled_a, settled_b = a <= self._settled_horizon, b <= self._settled_horizon
        if settled_a and settled_b:
            del self._rel_records[tag]
            return None
        if settled_a:
            return factors.prior_factor(X(b), self._frame_pose(a) @ T_ab, sigma_t, sigma_r, kernel, k)
        if settled_b:
            return factors.prior_factor(X(a), self._frame_pose(b) @ inv_rigid(T_ab), sigma_t, sigma_r, kernel, k)
        return factors.between_factor(X(a), X(b), T_ab, sigma_t, sigma_r, kernel, k)

    def _observation_sigma(self, obs: Observation) -> float:
        p = self.params
        depth = max(float(obs.point_camera[2]), 0.0)
        model = (p.observation_sigma_floor_m + p.observation_sigma_per_m_depth * depth
                 + p.observation_sigma_size_factor * max(float(obs.size), 0.0))
        return max(float(obs.sigma), model, 1e-4)

    def _observation_range_sigma(self, obs: Observation, sigma: float) -> float:
        """Along the ray: the visible surface's centre lies in front of the object's by up to half the depth the
        view could not see, and every view from that side shares the offset, so it does not average out over the
        views; the bearing keeps `sigma`. With `depth_unseen` (the associator's estimate, bounded by the object's
        footprint: observation.py `depth_unseen`) the range is loosened by
        `observation_range_sigma_unseen_factor` x that; without (an older sender), by
        `observation_range_sigma_size_factor` x size. On the street world along KITTI 00 the car views' centres lay
        1.09 m (0.33 x size) in front of the cars' along the ray, 3.5 of the isotropic sigmas, and 1.1 sigmas
        across it (docs/RESULTS.md)."""
        p = self.params
        if obs.depth_unseen is not None and p.observation_range_sigma_unseen_factor > 0.0:
            unseen = p.observation_range_sigma_unseen_factor * max(float(obs.depth_unseen), 0.0)
        else:
            unseen = p.observation_range_sigma_size_factor * max(float(obs.size), 0.0)
        return math.hypot(sigma, unseen) if unseen > 0.0 else sigma

    def _add_observation_factor(self, frame_id: int, obs: Observation, root: int) -> None:
        var, point, sigma = self._var[root], np.asarray(obs.point_camera, float), self._observation_sigma(obs)
        range_sigma = self._observation_range_sigma(obs, sigma)
        if frame_id <= self._settled_horizon:  # seen from a settled frame (a late message): straight into the prior
            self._settle_observation(frame_id, root, var, point, sigma, range_sigma, self._landmark_estimate(var))
            self._push_settled_prior(var, root)
            return
        self._ensure_node(frame_id)
        factor = factors.observation_factor(X(frame_id), L(var), point, sigma, self.params.robust_kernel,
                                            self.params.robust_k, range_sigma)
        tag = ("obs", self._obs_seq)
        self._obs_seq += 1
        self._push(tag, factor)
        self._obs_tags.setdefault(root, set()).add(tag)
        self._obs_records[tag] = (frame_id, root, var, point, sigma, range_sigma)
        self.counters["observation_factors"] += 1

    def _activate(self, root: int) -> None:
        """A landmark seen often enough: create its variable at the median of its world points, add its factors."""
        waiting = self._waiting.pop(root, [])
        for frame_id, _ in waiting:
            self._ensure_node(frame_id)
        poses = [self._frame_pose(f) for f, _ in waiting]
        world = [T[:3, :3] @ np.asarray(o.point_camera, float) + T[:3, 3]
                 for T, (_, o) in zip(poses, waiting, strict=True)]
        self._var[root] = root
        self._new_values.insert(L(root), np.median(np.array(world), axis=0))
        self._pending_vars.append(root)
        for frame_id, obs in waiting:
            self._add_observation_factor(frame_id, obs, root)

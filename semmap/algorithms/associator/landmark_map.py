"""The landmark map: objects with stable ids, their stored views, fused world clouds, and serialisable state.

Why views and not just a cloud: a landmark keeps each contributing view in *its own camera frame* (a thinned
cloud and a centroid) plus the frame id, so when the backend corrects poses the landmark is re-projected from
its views with the new poses instead of carrying the drift it was built with. At most `max_views` are kept:
when one more arrives, the view whose camera position is closest to another stored view's goes (it adds the
least new viewpoint), so a landmark seen for minutes keeps a spread of viewpoints at bounded cost.

Class: a detector's class for one object flips between views (a laptop seen as tv or microwave). A landmark
keeps a histogram of the classes of the measurements that fed it (`class_votes`); its reported class is the
majority (ties keep the current one), and candidates of any class it has been voted for may join it. A prior
map's landmark in a relocalised session (`anchor`, prior_anchor.py) keeps its prior class while it stands in
its prior place.

Derived state (MAP centroid, inlier views, voxelised world cloud, robust extent, KD-tree) is recomputed by
`LandmarkMapper` when views or poses change; the KD-tree is cached per cloud version, rebuilt lazily.
`to_state()` holds plain lists, numbers and bytes (msgpack / SQLite friendly); `from_state()` restores a map
that continues with the same ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from semmap.core.messages import Landmark

from .candidate import View
from .prior_anchor import PriorAnchor

STATE_VERSION = 1
MAX_FRAMES = 4000  # frame ids remembered per landmark for co-visibility


@dataclass
class LandmarkState:
    """One mapped object (all positions in the world frame of the current poses)."""

    id: int
    class_name: str
    views: list[View] = field(default_factory=list)
    tracks: list[int] = field(default_factory=list)  # track ids that fed it, in order
    frames: set[int] = field(default_factory=set)  # every frame id it was measured in (co-visibility)
    measurements: int = 0
    class_votes: dict[str, int] = field(default_factory=dict)  # measurements per detected class
    first_seen: float = 0.0
    last_seen: float = 0.0
    last_assoc: float = 0.0  # stamp of the last association / feed (the gate's dt runs from here)
    last_obs_sent: float = float("-inf")
    absent_streak: int = 0  # detected frames in a row it was in plain view but not detected
    absent_total: int = 0
    # derived
    map_centroid: np.ndarray = field(default_factory=lambda: np.zeros(3))
    centroid: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extent: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size: float = 0.0
    cloud: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    cloud_version: int = 0
    views_at_full: int = 0  # views at the last full re-estimate (MAP, inliers, cloud)
    last_full: float = float("-inf")  # stamp of that re-estimate
    added_since_full: int = 0
    anchor: PriorAnchor | None = None  # a prior map's landmark in a relocalised session: its prior place and class
    _tree: cKDTree | None = field(default=None, repr=False)
    _tree_version: int = -1

    @property
    def radius(self) -> float:
        return self.size / 2.0

    def tree(self) -> cKDTree:
        """KD-tree of the world cloud, rebuilt only when the cloud changed."""
        if self._tree is None or self._tree_version != self.cloud_version:
            self._tree = cKDTree(self.cloud if len(self.cloud) else np.zeros((1, 3)) + 1e9)
            self._tree_version = self.cloud_version
        return self._tree

    def set_cloud(self, cloud: np.ndarray) -> None:
        self.cloud = cloud
        self.cloud_version += 1

    def add_views(self, views: list[View], max_views: int) -> None:
        for v in views:
            self.views.append(v)
            self.frames.add(v.frame_id)
            if v.track_id not in self.tracks:
                self.tracks.append(v.track_id)
            self.measurements += 1
            self.last_seen = max(self.last_seen, v.stamp)
        if len(self.views) > len(views) and views and views[0].stamp < self.views[-len(views) - 1].stamp:
            self.views.sort(key=lambda v: (v.stamp, v.frame_id, v.track_id))
        while self.over_cap(max_views):
            self._drop_redundant_view()
        if len(self.frames) > MAX_FRAMES:  # co-visibility only matters for recent frames
            self.frames = set(sorted(self.frames)[-MAX_FRAMES // 2 :])

    def _own_views(self) -> list[int]:
        """Indices of the views the `max_views` cap applies to: all, but for a prior landmark in a relocalised
        session (`anchor`) only this session's. Its prior views (frozen: negative frame ids) keep their weight:
        the newest views win the cap, and on the second 7-Scenes session would thin a prior landmark's views until those
        left put its centre 15-23 cm from where all of them had."""
        if self.anchor is None:
            return list(range(len(self.views)))
        return [k for k, v in enumerate(self.views) if v.frame_id >= 0]

    def over_cap(self, max_views: int) -> bool:
        """More views than `max_views` of those it caps (`_own_views`): one must go."""
        return len(self._own_views()) > max_views

    def _drop_redundant_view(self) -> None:
        """Drop the older of the two capped views (`_own_views`) whose camera positions are closest (never the
        newest)."""
        own = self._own_views()
        pos = np.stack([self.views[k].pose[:3, 3] for k in own])
        d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)
        d[np.arange(len(pos)), np.arange(len(pos))] = np.inf
        d[-1, :] = d[:, -1] = np.inf  # keep the newest view
        i, j = np.unravel_index(int(np.argmin(d)), d.shape)
        del self.views[own[min(i, j)]]

    def vote(self, class_name: str, count: int) -> None:
        """Count `count` measurements of `class_name`; the class becomes the majority (ties keep the current)."""
        if count <= 0:
            return
        self.class_votes[class_name] = self.class_votes.get(class_name, 0) + count
        self._elect()

    def absorb_votes(self, other: dict[str, int]) -> None:
        for name, n in other.items():
            self.class_votes[name] = self.class_votes.get(name, 0) + n
        self._elect()

    def _elect(self) -> None:
        if self.anchor is not None and not self.anchor.moved:  # in its prior place: its prior class
            self.class_name = self.anchor.class_name
            return
        best = max(sorted(self.class_votes), key=lambda c: self.class_votes[c])  # sorted: ties by name
        if self.class_votes[best] > self.class_votes.get(self.class_name, 0):
            self.class_name = best

    def set_moved(self, moved: bool) -> None:
        """A prior landmark's evidence says it moved (or no longer does): its class is then elected by its votes
        (or is its prior class again)."""
        if self.anchor is not None and self.anchor.moved != moved:
            self.anchor.moved = moved
            if self.class_votes:
                self._elect()
            else:
                self.class_name = self.anchor.class_name

    def remove_track(self, track_id: int) -> None:
        """Forget the views of one track (it turned out to be a moving object)."""
        self.views = [v for v in self.views if v.track_id != track_id]
        if track_id in self.tracks:
            self.tracks.remove(track_id)

    def to_message(self) -> Landmark:
        c, e = self.centroid, self.extent
        return Landmark(
            self.id,
            self.class_name,
            (float(c[0]), float(c[1]), float(c[2])),
            float(self.radius),
            (float(e[0]), float(e[1]), float(e[2])),
            int(self.measurements),
            float(self.first_seen),
            float(self.last_seen),
        )


class CentroidIndex:
    """Which landmarks lie near a point: a KD-tree over their centroids, for one pass over a map that does not
    change meanwhile (rebuild it after a merge). Why: merging and association against a street-scale map of
    thousands of landmarks must not compare every pair (a refine re-merges every landmark that moved)."""

    def __init__(self, landmarks: list[LandmarkState]) -> None:
        self.landmarks = landmarks
        self.max_radius = max((lm.radius for lm in landmarks), default=0.0)
        centroids = np.stack([lm.centroid for lm in landmarks]) if landmarks else np.zeros((0, 3))
        self._tree = cKDTree(centroids)

    def within(self, point: np.ndarray, distance: float) -> list[LandmarkState]:
        """The landmarks whose centroid lies within `distance` of `point`, in the order they were given."""
        if not self.landmarks:
            return []
        return [self.landmarks[i] for i in sorted(self._tree.query_ball_point(point, distance))]


class LandmarkMap:
    """Landmarks by id (ids increase, never reused), iterated in id order."""

    def __init__(self) -> None:
        self._landmarks: dict[int, LandmarkState] = {}
        self._in_order: list[LandmarkState] | None = None  # all() cached until a landmark comes or goes
        self.next_id = 0

    def __len__(self) -> int:
        return len(self._landmarks)

    def __contains__(self, landmark_id: int) -> bool:
        return landmark_id in self._landmarks

    def __getitem__(self, landmark_id: int) -> LandmarkState:
        return self._landmarks[landmark_id]

    def get(self, landmark_id: int) -> LandmarkState | None:
        return self._landmarks.get(landmark_id)

    def create(self, class_name: str, stamp: float) -> LandmarkState:
        lm = LandmarkState(self.next_id, class_name, first_seen=stamp, last_seen=stamp, last_assoc=stamp)
        self._landmarks[lm.id] = lm
        self._in_order = None
        self.next_id += 1
        return lm

    def remove(self, landmark_id: int) -> None:
        self._landmarks.pop(landmark_id, None)
        self._in_order = None

    def insert(self, lm: LandmarkState) -> None:
        """A landmark made elsewhere (a prior map's) under its own id; later ids come after it."""
        if lm.id in self._landmarks:
            raise ValueError(f"landmark {lm.id} exists already")
        self._landmarks[lm.id] = lm
        self._in_order = None
        self.next_id = max(self.next_id, lm.id + 1)

    def all(self) -> list[LandmarkState]:
        """Every landmark in id order (a new list; the order is cached, as every candidate asks for it)."""
        if self._in_order is None:
            self._in_order = [self._landmarks[i] for i in sorted(self._landmarks)]
        return list(self._in_order)

    def of_class(self, class_name: str) -> list[LandmarkState]:
        return [lm for lm in self.all() if lm.class_name == class_name]

    def voted_for(self, class_name: str) -> list[LandmarkState]:
        """Landmarks reported as `class_name` or fed by measurements of it (a class that flips between views)."""
        return [lm for lm in self.all() if lm.class_name == class_name or class_name in lm.class_votes]

    def landmarks(self) -> list[Landmark]:
        """Every landmark as its wire message, in id order."""
        return [lm.to_message() for lm in self.all()]

    # ---- persistence

    def to_state(self) -> dict[str, Any]:
        return {
            "version": STATE_VERSION,
            "next_id": self.next_id,
            "landmarks": [_landmark_state(lm) for lm in self.all()],
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> LandmarkMap:
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"landmark map state version {state.get('version')!r}, expected {STATE_VERSION}")
        m = cls()
        m.next_id = int(state["next_id"])
        for d in state["landmarks"]:
            lm = _landmark_from_state(d)
            m._landmarks[lm.id] = lm
        return m


# ---------------------------------------------------------------------------------------------------------
# plain-data conversion (lists, numbers, bytes)


def _arr(a: np.ndarray, dtype: str) -> dict[str, Any]:
    a = np.ascontiguousarray(a, dtype=dtype)
    return {
        "dtype": dtype,
        "shape": list(a.shape),
        "data": a.astype(np.dtype(dtype).newbyteorder("<")).tobytes(),
    }


def _unarr(d: dict[str, Any]) -> np.ndarray:
    dt = np.dtype(d["dtype"]).newbyteorder("<")
    return np.frombuffer(d["data"], dtype=dt).reshape(d["shape"]).astype(np.dtype(d["dtype"]))


def view_to_state(v: View) -> dict[str, Any]:
    return {
        "frame_id": v.frame_id,
        "stamp": v.stamp,
        "track_id": v.track_id,
        "points": [_arr(x, "float32") for x in v.alt_points],
        "centroids": _arr(v.alt_centroids, "float64"),
        "depths": [float(x) for x in v.alt_depths],
        "scores": [float(x) for x in v.alt_scores],
        "ray": [float(x) for x in v.ray],
        "metric": v.metric,
        "pose": [float(x) for x in v.pose.reshape(16)],
        "truncated": v.truncated,
        "occluded": v.occluded,
        "choice": v.choice,
        "inlier": v.inlier,
    }


def view_from_state(d: dict[str, Any]) -> View:
    return View(
        int(d["frame_id"]),
        float(d["stamp"]),
        int(d["track_id"]),
        [_unarr(x) for x in d["points"]],
        _unarr(d["centroids"]),
        np.array(d["depths"], dtype=np.float64),
        np.array(d["scores"], dtype=np.float64),
        np.array(d["ray"], dtype=np.float64),
        float(d["metric"]),
        np.array(d["pose"], dtype=np.float64).reshape(4, 4),
        bool(d["truncated"]),
        int(d["choice"]),
        bool(d["inlier"]),
        occluded=bool(d.get("occluded", False)),
    )


def _landmark_state(lm: LandmarkState) -> dict[str, Any]:
    return {
        "id": lm.id,
        "class": lm.class_name,
        "views": [view_to_state(v) for v in lm.views],
        "tracks": list(lm.tracks),
        "frames": sorted(lm.frames),
        "measurements": lm.measurements,
        "class_votes": dict(sorted(lm.class_votes.items())),
        "first_seen": lm.first_seen,
        "last_seen": lm.last_seen,
        "last_assoc": lm.last_assoc,
        "last_obs_sent": None if not np.isfinite(lm.last_obs_sent) else lm.last_obs_sent,
        "map_centroid": [float(x) for x in lm.map_centroid],
        "centroid": [float(x) for x in lm.centroid],
        "extent": [float(x) for x in lm.extent],
        "size": lm.size,
        "cloud": _arr(lm.cloud, "float64"),
        "views_at_full": lm.views_at_full,
        "added_since_full": lm.added_since_full,
        "absent_streak": lm.absent_streak,
        "absent_total": lm.absent_total,
        "last_full": None if not np.isfinite(lm.last_full) else lm.last_full,
        "anchor": None if lm.anchor is None else lm.anchor.to_state(),
    }


def _landmark_from_state(d: dict[str, Any]) -> LandmarkState:
    lm = LandmarkState(int(d["id"]), str(d["class"]))
    lm.views = [view_from_state(v) for v in d["views"]]
    lm.tracks = [int(t) for t in d["tracks"]]
    lm.frames = {int(f) for f in d["frames"]}
    lm.measurements = int(d["measurements"])
    # maps saved before class histograms existed: every measurement voted for the one class
    votes = d.get("class_votes") or {lm.class_name: lm.measurements}
    lm.class_votes = {str(k): int(v) for k, v in votes.items()}
    lm.first_seen, lm.last_seen, lm.last_assoc = (
        float(d["first_seen"]),
        float(d["last_seen"]),
        float(d["last_assoc"]),
    )
    lm.last_obs_sent = float("-inf") if d["last_obs_sent"] is None else float(d["last_obs_sent"])
    lm.map_centroid = np.array(d["map_centroid"], dtype=np.float64)
    lm.centroid = np.array(d["centroid"], dtype=np.float64)
    lm.extent = np.array(d["extent"], dtype=np.float64)
    lm.size = float(d["size"])
    lm.cloud = _unarr(d["cloud"])
    lm.views_at_full, lm.added_since_full = int(d["views_at_full"]), int(d["added_since_full"])
    lm.absent_streak, lm.absent_total = int(d["absent_streak"]), int(d["absent_total"])
    lm.last_full = float("-inf") if d["last_full"] is None else float(d["last_full"])
    lm.anchor = None if d.get("anchor") is None else PriorAnchor.from_state(d["anchor"])  # (absent in older states)
    return lm

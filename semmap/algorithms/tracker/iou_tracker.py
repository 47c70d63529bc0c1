"""IOU tracker after Bochinski et al. (AVSS 2017): detections are chained into tracklets by box overlap alone.

Why this tracker: at 30 Hz an object barely moves between frames, so the overlap of its boxes in consecutive
frames is high and no appearance model or motion prediction is needed; the cost is a few numpy operations
per frame, which is what lets the paper report 0.069 ms for its "candidate proposal" stage.

Rules (paper settings: sigma_iou 0.2, min tracklet size 5, max time since the last detection 0.5 s):
- a detection extends the active tracklet of the same class with the highest IOU >= sigma_iou. Matching is
  greedy over all (tracklet, detection) pairs by decreasing IOU, so each tracklet takes at most one detection
  per frame and each detection feeds at most one tracklet (the original's per-track `max` can hand one
  detection to two tracks); ties are broken by track id, then detection index, so results are deterministic;
- an unmatched detection starts a new tracklet (ids are increasing ints, never reused);
- a tracklet without a detection for more than max_age_s (stamp time, so skipped frames count) ends; it is
  reported in `ended` only if it had become a candidate;
- a tracklet reaching min_length measurements is proposed once as `CandidateUpdate(first=True)` carrying all
  its measurements; every later measurement goes out as `CandidateUpdate(first=False)` with just the new one.
  Measurements of a proposed tracklet are not kept: the associator owns them from then on.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import msgspec
import numpy as np

from semmap.core.config import TrackerParams
from semmap.core.messages import (
    CandidateUpdate,
    Detection,
    DynamicBox,
    Intrinsics,
    Measurement,
    MessageError,
    TrackedBox,
)
from semmap.core.stamps import exceeds


@dataclass
class TrackerOutput:
    """What one frame produced: candidates to associate, ended candidate ids, and this frame's boxes."""

    candidates: list[CandidateUpdate] = field(default_factory=list)
    ended: list[int] = field(default_factory=list)
    boxes: list[TrackedBox] = field(default_factory=list)


@dataclass
class _Tracklet:
    track_id: int
    class_name: str
    class_id: int
    box: tuple[float, float, float, float]
    last_stamp: float
    length: int = 0
    candidate: bool = False
    pending: list[Measurement] = field(default_factory=list)  # measurements not yet sent


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IOU of every box in a (N,4) with every box in b (M,4), boxes as x1, y1, x2, y2."""
    ax1, ay1, ax2, ay2 = (c[:, None] for c in a.T)
    bx1, by1, bx2, by2 = b.T
    iw = np.minimum(ax2, bx2) - np.maximum(ax1, bx1)
    ih = np.minimum(ay2, by2) - np.maximum(ay1, by1)
    inter = np.maximum(iw, 0.0) * np.maximum(ih, 0.0)
    union = (ax2 - ax1) * (ay2 - ay1) + (bx2 - bx1) * (by2 - by1) - inter
    return inter / np.maximum(union, 1e-12)


def occluded_by(boxes: np.ndarray, occluders: np.ndarray, min_overlap: float) -> np.ndarray:
    """(N,) bool: is each box (N,4) covered by at least `min_overlap` of its own area by one of `occluders` (M,4)?
    (Intersection over the box's area, not IOU: a person's box dwarfs the chair it passes.)"""
    if not len(boxes) or not len(occluders):
        return np.zeros(len(boxes), dtype=bool)
    ax1, ay1, ax2, ay2 = (c[:, None] for c in boxes.T)
    bx1, by1, bx2, by2 = occluders.T
    iw = np.maximum(np.minimum(ax2, bx2) - np.maximum(ax1, bx1), 0.0)
    ih = np.maximum(np.minimum(ay2, by2) - np.maximum(ay1, by1), 0.0)
    area = np.maximum((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]), 1e-12)
    return (iw * ih).max(axis=1) / area >= min_overlap


class IouTracker:
    """Frame-by-frame IOU tracking; one instance per robot (see module docstring)."""

    def __init__(
        self, params: TrackerParams | None = None, first_track_id: int = 0, dynamic_classes: Iterable[str] = ()
    ) -> None:
        self.params = params or TrackerParams()
        self.dynamic_classes = frozenset(dynamic_classes)  # their boxes mark the boxes they cover `occluded`
        self._active: list[_Tracklet] = []  # kept in creation (= id) order
        self._next_id = first_track_id
        self._class_ids: dict[str, int] = {}

    def _class_id(self, name: str) -> int:
        return self._class_ids.setdefault(name, len(self._class_ids))

    @property
    def active_count(self) -> int:
        return len(self._active)

    def state(self) -> dict:
        """Everything later frames depend on, as plain data (msgpack-able): a restarted tracker that restores it
        continues every tracklet with the same ids, lengths and unsent measurements, as if it never stopped."""
        return {
            "next_id": self._next_id,
            "class_ids": dict(self._class_ids),
            "active": [
                {"track_id": t.track_id, "class": t.class_name, "class_id": t.class_id, "box": list(t.box),
                 "last_stamp": t.last_stamp, "length": t.length, "candidate": t.candidate,
                 "pending": [m.to_dict() for m in t.pending]}
                for t in self._active
            ],
        }

    @classmethod
    def from_state(
        cls, state: dict, params: TrackerParams | None = None, dynamic_classes: Iterable[str] = ()
    ) -> IouTracker:
        """The tracker `state()` described (a MessageError if it is not one)."""
        try:
            tracker = cls(params, first_track_id=int(state["next_id"]), dynamic_classes=dynamic_classes)
            tracker._class_ids = {str(k): int(v) for k, v in state["class_ids"].items()}
            tracker._active = [
                _Tracklet(int(t["track_id"]), str(t["class"]), int(t["class_id"]),
                          tuple(float(v) for v in t["box"]), float(t["last_stamp"]), int(t["length"]),
                          bool(t["candidate"]), [Measurement.from_dict(m) for m in t["pending"]])
                for t in state["active"]
            ]
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise MessageError(f"not a tracker state: {type(exc).__name__}: {exc}") from None
        return tracker

    def active_ids(self) -> set[int]:
        """Ids of the tracklets still alive (detected within max_age_s)."""
        return {t.track_id for t in self._active}

    def _age(self, stamp: float) -> list[int]:
        """End tracklets not detected for more than max_age_s; the ids of ended candidates."""
        ended: list[int] = []
        alive: list[_Tracklet] = []
        for t in self._active:
            if exceeds(stamp - t.last_stamp, self.params.max_age_s):
                if t.candidate:
                    ended.append(t.track_id)
            else:
                alive.append(t)
        self._active = alive
        return ended

    def skip(self, frame_id: int, stamp: float) -> TrackerOutput:
        """A frame that was not detected: only ages tracklets."""
        return TrackerOutput(ended=self._age(stamp))

    def update(
        self,
        frame_id: int,
        stamp: float,
        detections: list[Detection],
        intrinsics: Intrinsics,
        depth_scale: float,
    ) -> TrackerOutput:
        """Feed one detected frame; returns candidates (new and fed), ended candidates and tracked boxes."""
        out = TrackerOutput(ended=self._age(stamp))
        n_t, n_d = len(self._active), len(detections)
        assigned: list[_Tracklet | None] = [None] * n_d
        if n_t and n_d:
            tb = np.array([t.box for t in self._active], dtype=np.float64)
            db = np.array([d.box for d in detections], dtype=np.float64)
            tcls = np.fromiter((t.class_id for t in self._active), dtype=np.int64, count=n_t)
            dcls = np.fromiter((self._class_id(d.class_name) for d in detections), dtype=np.int64, count=n_d)
            iou = iou_matrix(tb, db)
            ti, di = np.nonzero((tcls[:, None] == dcls[None, :]) & (iou >= self.params.sigma_iou))
            if ti.size == 1:
                assigned[int(di[0])] = self._active[int(ti[0])]
            elif ti.size:
                # Greedy by IOU, ties by track order then detection index (lexsort: last key is primary).
                order = np.lexsort((di, ti, -iou[ti, di]))
                used_t: set[int] = set()
                for a, b in zip(ti[order].tolist(), di[order].tolist(), strict=True):
                    if a in used_t or assigned[b] is not None:
                        continue
                    used_t.add(a)
                    assigned[b] = self._active[a]
        occluded = self._occluded(detections)
        for j, det in enumerate(detections):
            track = assigned[j]
            if track is None:
                track = _Tracklet(
                    self._next_id, det.class_name, self._class_id(det.class_name), det.box, stamp
                )
                self._next_id += 1
                self._active.append(track)
            track.box = det.box
            track.last_stamp = stamp
            track.length += 1
            track.pending.append(Measurement(frame_id, stamp, det, intrinsics, depth_scale, bool(occluded[j])))
            if track.candidate or track.length >= self.params.min_length:
                out.candidates.append(
                    CandidateUpdate(
                        track.track_id, track.class_name, track.pending, first=not track.candidate
                    )
                )
                track.candidate = True
                track.pending = []
            out.boxes.append(
                TrackedBox(track.track_id, track.class_name, det.box, track.length, track.candidate)
            )
        out.candidates.sort(key=lambda c: c.track_id)
        return out

    def _occluded(self, detections: list[Detection]) -> np.ndarray:
        """Per detection: covered by a box of a dynamic class (not its own) in this frame."""
        dynamic = [i for i, d in enumerate(detections) if d.class_name in self.dynamic_classes]
        if not dynamic:
            return np.zeros(len(detections), dtype=bool)
        boxes = np.array([d.box for d in detections], dtype=np.float64).reshape(-1, 4)
        depth = np.array([d.depth_m for d in detections], dtype=np.float64)
        covered = np.zeros(len(detections), dtype=bool)
        for k in dynamic:
            # in front of the object, or close enough behind it to show through it (a chair's back, a plant's
            # leaves); a person metres behind is outside the object's depth band anyway
            near = (depth <= 0) | (depth[k] <= 0) | (depth[k] <= depth + self.params.occlusion_depth_margin_m)
            covered |= near & occluded_by(boxes, boxes[[k]], self.params.occlusion_min_overlap)
        covered[dynamic] = False  # a person among people is tracked, never mapped: nothing to spare it from
        return covered


def depth_range(det: Detection, depth_scale: float, band_m: float) -> tuple[float, float]:
    """The depth range (metres) of the object's surface in a box: the 2-98 percentile of the box's valid depths
    within `band_m` of its median depth (the detector's `depth_m`); (0, 0) without depth. A consumer that
    leaves out only these depths keeps the static background behind a person."""
    patch = det.depth_patch
    if patch is None or det.depth_m <= 0:
        return 0.0, 0.0
    z = patch.depth[patch.depth > 0].astype(np.float64) * depth_scale
    z = z[np.abs(z - det.depth_m) <= band_m]
    if z.size == 0:
        return 0.0, 0.0
    lo, hi = np.percentile(z, [2.0, 98.0])
    return float(lo), float(hi)


HELD_BOX_MIN_DEPTH_M = 0.5  # a held box without a valid depth grows as if the object were this close


def held_dynamic_box(box: DynamicBox, elapsed_s: float, speed_mps: float, intrinsics: Intrinsics) -> DynamicBox:
    """A dynamic object's last detected box, held for a frame that did not detect it, grown on every side by how
    far the object may have moved in the image since: `speed_mps` x `elapsed_s` at its nearest depth, through
    the focal length, and its depth range by the same distance. Why: a box held as it was masks where the person
    stood, not where the person is. On Bonn crowd a walker 1.1 m away went undetected for 7 frames while the
    box stayed put; he walked 120 px out of it, and semmap's registration, which leaves the box's depth out, was
    dragged 2-5 cm a frame by him (a camera that moves 3 mm a frame). Grown, the box still covers him: what the
    mask loses is some static background for a few frames, which the registration can spare."""
    if not (speed_mps > 0.0 and elapsed_s > 0.0 and math.isfinite(speed_mps * elapsed_s)):
        return msgspec.structs.replace(box, held=True)  # (a stamp that says nothing: the box as it was)
    reach_m = speed_mps * elapsed_s
    depth = max(box.depth_min_m, HELD_BOX_MIN_DEPTH_M)  # (0 where the box held no valid depth)
    dx, dy = intrinsics.fx * reach_m / depth, intrinsics.fy * reach_m / depth
    x1, y1, x2, y2 = box.box
    grown = (max(0.0, x1 - dx), max(0.0, y1 - dy), min(float(intrinsics.width), x2 + dx),
             min(float(intrinsics.height), y2 + dy))
    lo, hi = box.depth_min_m, box.depth_max_m
    if hi > 0.0:  # (0, 0: the box held no valid depth, and a `range` mask leaves out all of it)
        lo, hi = max(0.0, lo - reach_m), hi + reach_m
    return DynamicBox(box.track_id, box.class_name, grown, lo, hi, box.reason, held=True)

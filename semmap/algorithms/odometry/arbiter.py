"""Which of two estimates of the camera's recent motion the static scene supports: the SLAM's or semmap's.

When the SLAM's step and semmap's own registration of the same frames disagree, one of them is wrong, and a
rule that always believes one side is wrong somewhere: semmap's dense registration is the better one where people
drag a SLAM (Bonn "crowd": the SLAM's path is 10x the true one), the SLAM is the better one under fast rotation and
motion blur (TUM fr1_rpy: the registration's steps are 25 mm off, the SLAM's 4 mm). The arbiter asks evidence that
neither estimate was fitted to:

- **sparse features**: ORB keypoints on the static pixels (every dynamic object's box left out) of the current
  frame and of a frame `window` frames back, matched by descriptor. The registration was fitted to dense depth and
  intensity of consecutive frames, the SLAM to its own map; neither to these matches between frames further
  apart.
- **over a few frames, not one**: per frame the two disagree by millimetres, which a noisy depth image does not
  resolve (Bonn: a 28 mm sideways step with a compensating half degree of rotation fits one frame pair as well as
  the true 4 mm step). A dragged SLAM is dragged frame after frame, so over three frames the disagreement has
  grown past the noise, while one noisy frame of either estimate has not.
- **image and depth together**: each match scores both motions by its reprojection error (pixels, both
  directions) and its 3D distance (in units of the sensor's depth noise at that range); the rotation-translation
  ambiguity of a far scene fools the first, not the second.

Each match's robust cost (log(1 + e^2) per term) under each motion gives a paired difference; semmap's motion wins
only when the mean difference is `min_t` standard errors in its favour. Anything less, too few matches included,
is weak evidence: the SLAM keeps its step. Pure computation on images held in memory (OpenCV's ORB).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from semmap.algorithms.dynamic_mask import dynamic_pixels
from semmap.core.messages import DynamicBox


@dataclass(frozen=True)
class ArbiterParams:
    """How the evidence is gathered and weighed (the `odometry.arbiter_*` settings)."""

    window_frames: int = 3  # the reference frame is this many frames back
    long_window_frames: int = 0  # ... and a second judgement from this far back (a slow drag shows over half a second)
    min_t: float = 3.0  # semmap's motion must be better by this many standard errors of the paired difference
    min_matches: int = 40  # fewer static matches: weak evidence
    features: int = 1000
    max_reprojection_px: float = 6.0  # a match this far off under both motions is a wrong match, not evidence
    walker_prior: float = 6.0
    evidence_memory: float = 0.9  # each judgement adds its t to the sum of the earlier ones, faded by this
    evidence_clip: float = 10.0  # ... at most this much: no single frame pair outweighs a few others
    sparse_min_inliers: int = 80  # a step fitted to the static matches (`sparse_step`) witnesses with this many
    sparse_reprojection_px: float = 2.0  # ... matches within this of the fitted motion


@dataclass(frozen=True)
class Verdict:
    """The evidence of one judgement: `t` > 0 favours semmap's motion (in standard errors), < 0 the SLAM's."""

    t: float
    matches: int
    slam_px: float  # median reprojection error of the matches under the SLAM's motion
    semmap_px: float  # ... and under semmap's
    t_long: float = 0.0  # the long window's t, where it was judged too

    def favours_semmap(self, params: ArbiterParams) -> bool:
        return self.matches >= params.min_matches and self.t >= params.min_t

    def favours_slam(self, params: ArbiterParams) -> bool:
        return self.matches >= params.min_matches and self.t <= -params.min_t


@dataclass
class _Frame:
    image: np.ndarray  # as pushed (colour or grey): made grey only when judged (`gray`)
    depth: np.ndarray
    depth_scale: float
    intrinsics: np.ndarray  # 3x3
    boxes: list[DynamicBox]
    dynamic: np.ndarray | None = None  # its dynamic objects' pixels by their depth band (`by_depth`), once needed
    _gray: np.ndarray | None = None

    @property
    def gray(self) -> np.ndarray:
        """The grey image, converted once when first needed. Why not on push: a frame is held for every step, but
        only judged ones are matched, and in real time, behind the video, hardly any are."""
        if self._gray is None:
            image = self.image
            self._gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        return self._gray


# the depth noise of a structured-light / time-of-flight RGB-D sensor grows with the square of the range (m)
def depth_sigma(z: np.ndarray) -> np.ndarray:
    return 0.0012 + 0.0019 * np.square(np.maximum(z - 0.4, 0.0))


class StepArbiter:
    """Remembers the last frames (`push`: as many as the longer window needs) and judges two motions from a frame
    `steps` back to the newest (`judge`). Features are computed only when a judgement needs them (most frames need
    none), once per frame."""

    def __init__(self, params: ArbiterParams | None = None, hold_frames: int = 0) -> None:
        self.params = params or ArbiterParams()
        # frames held: as many as the longer window needs, or `hold_frames` back if more (`sparse_step` over them)
        self._hold = max(self.params.window_frames, self.params.long_window_frames, hold_frames) + 1
        self._frames: OrderedDict[int, _Frame] = OrderedDict()
        # (frame id, by_depth) -> the frame's static features
        self._features: dict[tuple[int, bool], tuple[np.ndarray, np.ndarray | None]] = {}
        self._orb = cv2.ORB_create(self.params.features)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self._pinned: dict[str, tuple[int, _Frame]] = {}  # a frame per role kept beyond the window (`pin`)
        # the pair last matched since the newest frame came, (ref id, newest id, by_depth), and its matches
        self._matched: tuple[tuple[int, int, bool], tuple[np.ndarray, np.ndarray]] | None = None
        self.judged = 0

    def push(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, depth_scale: float,
             intrinsics: np.ndarray, boxes: list[DynamicBox]) -> None:
        self._matched = None
        self._frames[int(frame_id)] = _Frame(rgb, depth, float(depth_scale), np.asarray(intrinsics, float),
                                             list(boxes))
        while len(self._frames) > self._hold:
            old, _ = self._frames.popitem(last=False)
            if not self._is_pinned(old):
                self._forget(old)

    def pin(self, frame_id: int, role: str = "anchor") -> None:
        """Keep this held frame (and its features) after the window has moved on, until another is pinned in its
        `role`: the reference of a judgement `from_frame` it (a SLAM back after a gap, judged from where it was last
        believed: `anchor`, or from where it left: `gap`). One frame's images a role: no cost unless judged."""
        frame = self._frames.get(int(frame_id))
        if frame is None:
            return
        before = self._pinned.get(role)
        self._pinned[role] = (int(frame_id), frame)
        if before is not None and before[0] not in self._frames and not self._is_pinned(before[0]):
            self._forget(before[0])

    def _is_pinned(self, frame_id: int) -> bool:
        return any(pinned_id == frame_id for pinned_id, _ in self._pinned.values())

    @property
    def frames_held(self) -> int:
        return len(self._frames)

    def _forget(self, frame_id: int) -> None:
        for by_depth in (False, True):
            self._features.pop((frame_id, by_depth), None)

    def held_back(self, steps: int) -> int | None:
        """The id of the held frame `steps` before the newest (None: fewer are held)."""
        ids = list(self._frames)
        return ids[-steps - 1] if len(ids) > steps else None

    def holds(self, frame_id: int) -> bool:
        return self._frame(int(frame_id)) is not None

    def reset(self) -> None:
        self._frames.clear()
        self._features.clear()
        self._matched = None
        self._pinned.clear()

    def judge(self, slam_motion: np.ndarray, semmap_motion: np.ndarray, steps: int,
              from_frame: int | None = None, by_depth: bool = False) -> Verdict:
        """Both motions from the frame `steps` back (or from the held frame `from_frame`) to the newest
        (T_ref^-1 T_cur, camera-to-world convention); `by_depth`: see `_static_matches`."""
        self.judged += 1
        ids = list(self._frames)
        if from_frame is not None:
            if not ids or not self.holds(from_frame) or int(from_frame) == ids[-1]:
                return Verdict(0.0, 0, math.nan, math.nan)
            ref_id = int(from_frame)
        elif len(ids) < steps + 1:
            return Verdict(0.0, 0, math.nan, math.nan)
        else:
            ref_id = ids[-steps - 1]
        ref, cur = self._frame(ref_id), self._frames[ids[-1]]
        assert ref is not None
        ua, ub = self._static_matches(ref_id, ids[-1], by_depth)
        if len(ua) < self.params.min_matches:
            return Verdict(0.0, len(ua), math.nan, math.nan)
        K = cur.intrinsics
        xa, za = _backproject(ua, ref.depth, ref.depth_scale, K)
        xb, zb = _backproject(ub, cur.depth, cur.depth_scale, K)
        costs, pixels = [], []
        for motion in (slam_motion, semmap_motion):
            cost, px = _match_costs(np.asarray(motion, float), xa, za, xb, zb, ua, ub, K)
            costs.append(cost)
            pixels.append(px)
        valid = (np.isfinite(costs[0]) & np.isfinite(costs[1])
                 & (np.fmin(pixels[0], pixels[1]) < self.params.max_reprojection_px))
        n = int(valid.sum())
        if n < self.params.min_matches:
            return Verdict(0.0, n, math.nan, math.nan)
        diff = costs[0][valid] - costs[1][valid]  # > 0: semmap's motion explains the match better
        sd = float(np.std(diff, ddof=1))
        t = float(np.mean(diff) / (sd / math.sqrt(n))) if sd > 0 else 0.0
        return Verdict(t, n, float(np.median(pixels[0][valid])), float(np.median(pixels[1][valid])))

    def sparse_step(self, steps: int = 1, by_depth: bool = False) -> tuple[np.ndarray | None, int]:
        """The camera's motion from the held frame `steps` back (the previous one by default) to the newest, fitted
        to their static ORB matches (the earlier frame's points by their depth, the newest's pixels: PnP in RANSAC),
        and its inlier count; (None, 0) where it cannot be fitted; `by_depth`: see `_static_matches`. Why: where
        people fill most of the view, semmap's dense registration has too few pixels left to be trusted, yet the
        background's corners still fix the step (Bonn crowd, frames 125-140: 100-230 inliers, 3-20 mm off the
        ground truth a step where ORB-SLAM3, dragged, was 20-67 mm off)."""
        ids = list(self._frames)
        if len(ids) < steps + 1:
            return None, 0
        ref, cur = self._frames[ids[-steps - 1]], self._frames[ids[-1]]
        ua, ub = self._static_matches(ids[-steps - 1], ids[-1], by_depth)
        if len(ua) < 6:
            return None, 0
        xa, za = _backproject(ua, ref.depth, ref.depth_scale, ref.intrinsics)
        has_depth = np.isfinite(za)
        if int(has_depth.sum()) < 6:
            return None, 0
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            np.ascontiguousarray(xa[has_depth]), np.ascontiguousarray(ub[has_depth]), cur.intrinsics, None,
            iterationsCount=200, reprojectionError=self.params.sparse_reprojection_px, confidence=0.999)
        if not found or inliers is None:
            return None, 0
        world_to_cur = np.eye(4)  # (the previous frame's points in the newest frame: its inverse is the step)
        world_to_cur[:3, :3] = cv2.Rodrigues(rvec)[0]
        world_to_cur[:3, 3] = np.asarray(tvec, float).ravel()
        step = np.linalg.inv(world_to_cur)
        return (step, len(inliers)) if np.all(np.isfinite(step)) else (None, 0)

    def _static_matches(self, ref_id: int, cur_id: int, by_depth: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The pixels of the two frames' ORB matches outside every dynamic box of either (static in both), as two
        (n, 2) arrays in match order; empty where either frame has fewer than 2 such features. `by_depth`: outside
        the dynamic objects' pixels by their depth band instead (the wall behind a person stays; where people fill
        the view, whole boxes leave no match: Bonn crowd frames 119-167 over three frames, 0-35), either frame's
        at the keypoint's pixel in both."""
        key = (ref_id, cur_id, by_depth)
        if self._matched is not None and self._matched[0] == key:  # (a fit and its judgement of one frame)
            return self._matched[1]
        ref, cur = self._frame(ref_id), self._frames[cur_id]
        assert ref is not None
        if by_depth:
            a_mask, b_mask = _dynamic(ref), _dynamic(cur)
            pa, da = _off_mask(*self._static_features(ref_id, ref, by_depth), a_mask, b_mask)
            pb, db = _off_mask(*self._static_features(cur_id, cur, by_depth), b_mask, a_mask)
        else:
            boxes = ref.boxes + cur.boxes
            pa, da = _outside(*self._static_features(ref_id, ref), boxes)
            pb, db = _outside(*self._static_features(cur_id, cur), boxes)
        if da is None or db is None or len(pa) < 2 or len(pb) < 2:
            return np.empty((0, 2)), np.empty((0, 2))
        matches = self._matcher.match(da, db)
        ia = np.fromiter((m.queryIdx for m in matches), np.int64, len(matches))
        ib = np.fromiter((m.trainIdx for m in matches), np.int64, len(matches))
        self._matched = (key, (pa[ia], pb[ib]))
        return self._matched[1]

    def _frame(self, frame_id: int) -> _Frame | None:
        """A frame of the window, or the pinned one; None if neither."""
        if frame_id in self._frames:
            return self._frames[frame_id]
        return next((frame for pinned_id, frame in self._pinned.values() if pinned_id == frame_id), None)

    def _static_features(self, frame_id: int, frame: _Frame,
                         by_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame's keypoints and descriptors outside its own dynamic boxes (`by_depth`: their depth bands),
        computed once per frame."""
        cached = self._features.get((frame_id, by_depth))
        if cached is not None:
            return cached
        mask = np.full(frame.gray.shape, 255, np.uint8)
        h, w = mask.shape
        if by_depth:
            mask[_dynamic(frame)] = 0
        else:
            for b in frame.boxes:
                x0, y0, x1, y1 = (int(round(v)) for v in b.box)
                mask[max(0, y0):min(h, y1), max(0, x0):min(w, x1)] = 0
        keypoints, descriptors = self._orb.detectAndCompute(frame.gray, mask)
        points = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
        self._features[(frame_id, by_depth)] = (points, descriptors)
        return points, descriptors


def _dynamic(frame: _Frame) -> np.ndarray:
    """The frame's dynamic pixels by depth band and its boxes' pixels without depth (as ORB-SLAM3's `range` mask),
    computed once per frame."""
    if frame.dynamic is None:
        frame.dynamic = dynamic_pixels(frame.depth, frame.boxes, frame.depth_scale, "range", depthless=True)
    return frame.dynamic


def _off_mask(points: np.ndarray, descriptors: np.ndarray | None, own: np.ndarray,
              other: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The keypoints on neither frame's dynamic pixels (`_dynamic`, at the keypoint's pixel in each)."""
    if descriptors is None or len(points) == 0:
        return points, descriptors
    u = np.clip(np.round(points[:, 0]).astype(np.int64), 0, own.shape[1] - 1)
    v = np.clip(np.round(points[:, 1]).astype(np.int64), 0, own.shape[0] - 1)
    keep = ~(own[v, u] | other[v, u])
    return points[keep], descriptors[keep]


def _outside(points: np.ndarray, descriptors: np.ndarray | None,
             boxes: list[DynamicBox]) -> tuple[np.ndarray, np.ndarray | None]:
    """The keypoints outside every box (the other frame's dynamic objects: where they are now or were)."""
    if descriptors is None or not boxes:
        return points, descriptors
    keep = np.ones(len(points), bool)
    for b in boxes:
        x0, y0, x1, y1 = b.box
        keep &= ~((points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0) & (points[:, 1] < y1))
    return points[keep], descriptors[keep]


def _backproject(pixels: np.ndarray, depth: np.ndarray, depth_scale: float,
                 K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of keypoints (nearest depth pixel) and their depths (NaN where the depth is missing)."""
    u = np.clip(np.round(pixels[:, 0]).astype(np.int64), 0, depth.shape[1] - 1)
    v = np.clip(np.round(pixels[:, 1]).astype(np.int64), 0, depth.shape[0] - 1)
    z = depth[v, u].astype(np.float64) * depth_scale
    z[z <= 0.2] = np.nan  # (the sensor's near limit: no depth)
    points = np.stack([(pixels[:, 0] - K[0, 2]) * z / K[0, 0], (pixels[:, 1] - K[1, 2]) * z / K[1, 1], z], axis=1)
    return points, z


def _project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(points[:, 2] > 0.1, points[:, 2], np.nan)
        return np.stack([K[0, 0] * points[:, 0] / z + K[0, 2], K[1, 1] * points[:, 1] / z + K[1, 2]], axis=1)


def _match_costs(motion: np.ndarray, xa: np.ndarray, za: np.ndarray, xb: np.ndarray, zb: np.ndarray,
                 pa: np.ndarray, pb: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per match: the robust cost of `motion` (reprojection a->b and b->a in pixels, 3D distance in depth-noise
    units; NaN where a term has no depth) and the mean reprojection error in pixels."""
    inverse = np.linalg.inv(motion)
    a_in_b = xa @ inverse[:3, :3].T + inverse[:3, 3]  # the reference frame's points seen from the current frame
    b_in_a = xb @ motion[:3, :3].T + motion[:3, 3]
    with np.errstate(invalid="ignore"):
        e_ab = np.linalg.norm(_project(a_in_b, K) - pb, axis=1)
        e_ba = np.linalg.norm(_project(b_in_a, K) - pa, axis=1)
        e_3d = np.linalg.norm(a_in_b - xb, axis=1) / (depth_sigma(za) + depth_sigma(zb))
    pixels = 0.5 * (e_ab + e_ba)
    return np.log1p(np.square(pixels)) + np.log1p(np.square(e_3d)), pixels

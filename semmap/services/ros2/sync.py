"""Approximate-time matching of colour, depth and camera pose into semmap frames, without ROS (unit-testable).

A frame is a colour image, the depth image nearest to it in time (header stamps within `tolerance_s`), the
latest camera info, and the camera pose at the colour stamp: the pose stamped within `tolerance_s`, or the two
poses around it (no further apart than `pose_max_gap_s`) interpolated. Messages are converted on arrival, so a bad
one (unsupported encoding, short buffer, NaN pose) is counted and dropped at once; a colour image that can no
longer be matched (a newer depth or pose has passed it, or it is older than `max_wait_s` behind the newest input)
is counted and dropped too. Nothing here raises on bad input.

Messages lost before they reach the bridge (a DDS reader's full history, a lost UDP fragment) leave holes in
each stream's stamps: `StampGaps` finds them from the stream's median period and counts the frames missing.
`flush()` (at the end of a recording, or when the inputs go quiet) matches what is still held with what there
is: the last frame of a recording is sent, not held for a closer depth image that never comes.
"""

from __future__ import annotations

import bisect
import contextlib
import math
import statistics
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from semmap.core.stamps import exceeds
from semmap.datasets.ros_convert import (
    ConversionError,
    camera_info_intrinsics,
    colour_to_rgb,
    compressed_to_rgb,
    depth_to_mm,
    pose_at,
    pose_message,
    stamp_seconds,
)


class StampGaps:
    """Holes in a stream of header stamps. The stream's period is the shortest step that recurs (at least
    `min_support` of the last `window` steps within 20 % of it, their median): losses make steps longer, never
    shorter, so the period is found even when most messages are lost. A step longer than `factor` x the period is
    a gap of round(step / period) - 1 missing messages; steps taken before the period is known are counted once it
    is. Repeated or backward stamps are counted apart (`out_of_order`)."""

    def __init__(self, factor: float = 1.5, window: int = 61, min_support: int = 3) -> None:
        self.factor = float(factor)
        self.min_support = int(min_support)
        self.steps: deque[float] = deque(maxlen=int(window))
        self._unchecked: list[float] = []
        self.first: float | None = None
        self.last: float | None = None
        self.gaps = 0
        self.missing = 0
        self.out_of_order = 0

    @property
    def period(self) -> float | None:
        ordered = sorted(self.steps)
        for i, step in enumerate(ordered):
            j = bisect.bisect_right(ordered, 1.2 * step)
            if j - i >= self.min_support:
                return statistics.median(ordered[i:j])
        return None

    def add(self, stamp: float) -> int:
        """Record a stamp; return how many messages are missing before it (0 if none)."""
        if self.last is None:
            self.first = self.last = stamp
            return 0
        step = stamp - self.last
        if step <= 0:
            self.out_of_order += 1
            return 0
        self.last = stamp
        self.steps.append(step)
        period = self.period
        if period is None or period <= 0:
            self._unchecked.append(step)
            return 0
        missing = 0
        for earlier in [*self._unchecked, step]:
            if earlier > self.factor * period:
                missing += max(1, round(earlier / period) - 1)
                self.gaps += 1
        self._unchecked.clear()
        self.missing += missing
        return missing

    def as_dict(self) -> dict:
        period = self.period
        return {
            "gaps": self.gaps,
            "missing": self.missing,
            "out_of_order": self.out_of_order,
            "period_s": round(period, 6) if period is not None else None,
            "first": self.first,
            "last": self.last,
        }


class CameraFrames:
    """The frames a camera sent, as far as the bridge can tell: every stamp seen on the colour or the camera-info
    stream (a camera publishes its camera info with each colour image, at the same stamp; it is small and rarely
    lost), plus the holes in that joint stream (`StampGaps`). `colour_missing()`: those frames of which no colour
    image arrived. Stamps are kept for `horizon_s` behind the newest, then only counted."""

    def __init__(self, horizon_s: float = 30.0) -> None:
        self.horizon_s = float(horizon_s)
        self._seen: dict[int, bool] = {}  # stamp (0.1 ms) -> a colour image arrived for it
        self._newest = -math.inf
        self._old_frames = 0
        self._old_colour = 0
        self.gaps = StampGaps()

    def add(self, stamp: float, colour: bool) -> None:
        key = round(stamp * 1e4)
        if key not in self._seen:
            if stamp < self._newest - self.horizon_s:
                return  # far older than anything kept: already counted, or never will be
            self._seen[key] = False
            self.gaps.add(stamp)
        if colour:
            self._seen[key] = True
        if stamp > self._newest:
            self._newest = stamp
            horizon = round((stamp - self.horizon_s) * 1e4)
            if next(iter(self._seen)) < horizon:
                for old in [k for k in self._seen if k < horizon]:
                    self._old_frames += 1
                    self._old_colour += self._seen.pop(old)

    def frames(self) -> int:
        return self._old_frames + len(self._seen) + self.gaps.missing

    def colour_missing(self) -> int:
        return self.frames() - self._old_colour - sum(self._seen.values())


def missing_at_ends(colour: dict, others: list[dict]) -> int:
    """Colour images lost before the first or after the last one received, which no gap shows: the streams the
    camera sends with every colour image (depth, camera info; same rate) started earlier or went on later."""
    period = colour.get("period_s")
    if not period or colour.get("first") is None:
        return 0
    missing = 0
    for other in others:
        if other.get("first") is None or not other.get("period_s") or abs(other["period_s"] - period) > 0.1 * period:
            continue  # another rate: not one message per colour image
        head = round((colour["first"] - other["first"]) / period)
        tail = round((other["last"] - colour["last"]) / period)
        missing = max(missing, max(head, 0) + max(tail, 0))
    return missing


@dataclass
class MatchedFrame:
    """One semmap frame: RGB, depth in mm registered to it, the optical camera-to-world pose, the intrinsics."""

    stamp: float
    rgb: np.ndarray
    depth_mm: np.ndarray
    pose: np.ndarray
    intrinsics: tuple[float, float, float, float, int, int]  # fx, fy, cx, cy, width, height
    camera_frame: str
    world_frame: str


@dataclass
class _Image:
    stamp: float
    array: np.ndarray
    frame_id: str


class FrameSync:
    """Colour + depth + pose -> `MatchedFrame`s in stamp order (see module docstring). Not thread-safe: call it
    from one thread (the ROS executor's)."""

    def __init__(
        self,
        tolerance_s: float = 0.02,
        pose_max_gap_s: float = 0.5,
        max_wait_s: float = 2.0,
        pose_to_optical: np.ndarray | None = None,
    ) -> None:
        self.tolerance_s = float(tolerance_s)
        self.pose_max_gap_s = float(pose_max_gap_s)
        self.max_wait_s = float(max_wait_s)
        self.pose_to_optical = np.eye(4) if pose_to_optical is None else np.asarray(pose_to_optical, float)
        self.counters: Counter[str] = Counter()
        self.intrinsics: tuple[float, float, float, float, int, int] | None = None
        self.world_frame = ""
        self._colours: list[_Image] = []
        self._depths: list[_Image] = []
        self._pose_stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self._newest = -np.inf
        self._final = False  # flush(): match what is held with what there is, wait for nothing
        self.gaps = {"colour": StampGaps(), "depth": StampGaps(), "pose": StampGaps(), "camera_info": StampGaps()}
        self.camera_frames = CameraFrames()

    # -- inputs ------------------------------------------------------------------------------------------------
    def add_camera_info(self, msg: Any) -> list[MatchedFrame]:
        try:
            self.intrinsics = camera_info_intrinsics(msg)
        except (ConversionError, AttributeError, TypeError, ValueError):
            self.counters["bad_camera_info"] += 1
            return []
        with contextlib.suppress(AttributeError, TypeError, ValueError):  # without a stamp: still the intrinsics
            stamp = stamp_seconds(msg.header.stamp)
            self.gaps["camera_info"].add(stamp)
            self.camera_frames.add(stamp, colour=False)
        return self._match()

    def add_colour(self, msg: Any, compressed: bool = False) -> list[MatchedFrame]:
        try:
            stamp = stamp_seconds(msg.header.stamp)
            if compressed:
                rgb = compressed_to_rgb(str(msg.format), msg.data)
            else:
                rgb = colour_to_rgb(str(msg.encoding), int(msg.height), int(msg.width), int(msg.step), msg.data)
        except (ConversionError, AttributeError, TypeError, ValueError):
            self.counters["bad_colour"] += 1
            return []
        self.counters["colour"] += 1
        self.gaps["colour"].add(stamp)
        self.camera_frames.add(stamp, colour=True)
        _insert(self._colours, _Image(stamp, rgb, str(msg.header.frame_id)))
        return self._seen(stamp)

    def add_depth(self, msg: Any) -> list[MatchedFrame]:
        try:
            stamp = stamp_seconds(msg.header.stamp)
            mm = depth_to_mm(
                str(msg.encoding), int(msg.height), int(msg.width), int(msg.step), msg.data, bool(msg.is_bigendian)
            )
        except (ConversionError, AttributeError, TypeError, ValueError):
            self.counters["bad_depth"] += 1
            return []
        self.counters["depth"] += 1
        self.gaps["depth"].add(stamp)
        _insert(self._depths, _Image(stamp, mm, str(msg.header.frame_id)))
        return self._seen(stamp)

    def add_pose(self, msg: Any, msgtype: str) -> list[MatchedFrame]:
        try:
            stamp, _, matrix = pose_message(msg, msgtype)
        except (ConversionError, AttributeError, TypeError, ValueError):
            self.counters["bad_pose"] += 1
            return []
        self.counters["pose"] += 1
        self.gaps["pose"].add(stamp)
        self.world_frame = str(msg.header.frame_id) or self.world_frame
        i = bisect.bisect_right(self._pose_stamps, stamp)
        self._pose_stamps.insert(i, stamp)
        self._poses.insert(i, matrix @ self.pose_to_optical)
        return self._seen(stamp)

    def flush(self) -> list[MatchedFrame]:
        """No more input for now (the end of a recording, or the inputs went quiet): every colour image held
        for a closer depth image or a newer pose is matched with what there is. Nothing is dropped here: an image
        with no depth or pose at all keeps waiting (its pose may be late), and `finish()` counts what is left."""
        self._final = True
        try:
            out = self._match()
        finally:
            self._final = False
        return out

    def finish(self) -> list[MatchedFrame]:
        """The end: flush, then count what is still held (colour images that could never be matched)."""
        out = self.flush()
        self.counters["colour_unmatched_at_end"] += len(self._colours)
        self.counters["depth_unmatched"] += len(self._depths)
        self._colours.clear()
        self._depths.clear()
        return out

    def pending(self) -> int:
        """Colour images held, waiting for their depth or pose."""
        return len(self._colours)

    # -- matching ----------------------------------------------------------------------------------------------
    def _seen(self, stamp: float) -> list[MatchedFrame]:
        self._newest = max(self._newest, stamp)
        return self._match()

    def _drop(self, why: str) -> None:
        self.counters[why] += 1
        self._colours.pop(0)

    def _match(self) -> list[MatchedFrame]:
        out: list[MatchedFrame] = []
        tol = self.tolerance_s
        while self._colours:
            colour = self._colours[0]
            stale = exceeds(self._newest - colour.stamp, self.max_wait_s)
            if self.intrinsics is None:
                if stale:
                    self._drop("no_camera_info")
                    continue
                break
            depth_index = _nearest(self._depths, colour.stamp)
            if depth_index is None or abs(self._depths[depth_index].stamp - colour.stamp) > tol:
                passed = bool(self._depths) and self._depths[-1].stamp > colour.stamp + tol
                if passed or stale:
                    self._drop("colour_without_depth")
                    continue
                break
            if (
                self._depths[depth_index].stamp < colour.stamp - 1e-6
                and self._depths[-1].stamp < colour.stamp
                and self._newest <= colour.stamp + tol
                and not stale
                and not self._final
            ):
                break  # a depth image closer in time may still come
            pose = pose_at(self._pose_stamps, self._poses, colour.stamp, self.pose_max_gap_s)
            if pose is None:
                pose = self._nearest_pose(colour.stamp)
            if pose is None:
                passed = bool(self._pose_stamps) and exceeds(self._pose_stamps[-1] - colour.stamp, self.pose_max_gap_s)
                if passed or stale:
                    self._drop("colour_without_pose")
                    continue
                break
            depth = self._depths[depth_index]
            fx, fy, cx, cy, width, height = self.intrinsics
            if colour.array.shape[:2] != (height, width) or depth.array.shape != (height, width):
                self._drop("size_mismatch")
                continue
            self._colours.pop(0)
            self.counters["depth_unmatched"] += depth_index  # older depth images no colour image took
            del self._depths[: depth_index + 1]
            self._prune_poses(colour.stamp)
            self.counters["matched"] += 1
            out.append(
                MatchedFrame(
                    colour.stamp, colour.array, depth.array, pose, self.intrinsics, colour.frame_id, self.world_frame
                )
            )
        self._prune_depths()
        return out

    def _nearest_pose(self, t: float) -> np.ndarray | None:
        """Outside the series (no pose on one side yet): the nearest pose if it is within the tolerance."""
        if not self._pose_stamps:
            return None
        i = min(range(len(self._pose_stamps)), key=lambda k: abs(self._pose_stamps[k] - t))
        if abs(self._pose_stamps[i] - t) > self.tolerance_s:
            return None
        if t > self._pose_stamps[-1] and self._newest - t <= self.tolerance_s and not self._final:
            return None  # a newer pose may still come to interpolate with
        return self._poses[i].copy()

    def _prune_poses(self, t: float) -> None:
        """Keep the last pose before `t` (the next frame may interpolate from it) and everything after."""
        keep = max(0, bisect.bisect_left(self._pose_stamps, t) - 1)
        del self._pose_stamps[:keep]
        del self._poses[:keep]

    def _prune_depths(self) -> None:
        horizon = self._newest - self.max_wait_s
        while self._depths and self._depths[0].stamp < horizon:
            self._depths.pop(0)
            self.counters["depth_unmatched"] += 1


def _insert(items: list[_Image], item: _Image) -> None:
    """Keep images sorted by stamp (they nearly always arrive in order: append)."""
    if not items or items[-1].stamp <= item.stamp:
        items.append(item)
    else:
        items.insert(bisect.bisect_right([x.stamp for x in items], item.stamp), item)


def _nearest(items: list[_Image], t: float) -> int | None:
    if not items:
        return None
    stamps = [x.stamp for x in items]
    i = bisect.bisect_left(stamps, t)
    candidates = [k for k in (i - 1, i) if 0 <= k < len(items)]
    return min(candidates, key=lambda k: abs(stamps[k] - t))

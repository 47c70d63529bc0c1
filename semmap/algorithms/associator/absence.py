"""Negative evidence (part of the mapper's `update_merge` stage): landmarks in plain view that nothing detects."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from semmap.core.messages import Intrinsics, TrackedBox

from .geometry import inverse_transform
from .landmark_map import LandmarkState
from .params import MapperParams


def absent_landmarks(
    landmarks: list[LandmarkState],
    frame_id: int,
    T: np.ndarray | None,
    k: Intrinsics | None,
    boxes: Sequence[TrackedBox],
    p: MapperParams,
) -> list[int]:
    """Count landmarks that should be visible in this detected frame but are not detected; returns the ids of
    those to remove, in map order.

    In view: the centroid projects into the image's central part (`absence_margin` kept clear) at a
    depth in [absence_min_depth_m, absence_max_depth_m], its sphere spans at least `absence_min_px`
    pixels, and no other landmark's sphere lies in front of it on the line of sight (occlusion, judged
    from the map itself). Detected: a box of its class (tentative tracklets too) meets its projected
    disk. A landmark is removed when its current streak
    of in-view misses has become improbable under its own detection rate r = (n_seen + 1) /
    (n_seen + n_missed + 2): (1 - r)^streak < absence_p, and streak >= absence_min_frames. A person who
    stood still long enough to be mapped and walked off goes within a few frames of looking there again;
    a table that the detector finds in one frame of five needs a long, unexplained absence.
    Off by default: occluders that are not landmarks (a wall edge, a person) and objects a detector
    finds only from some sides make absence evidence unsafe within one pass over a scene; it pays in
    long sessions with revisits.
    """
    lms = [lm for lm in landmarks if lm.views]
    if T is None or k is None or not lms:
        return []
    c = np.stack([lm.centroid for lm in lms])
    cam = inverse_transform(np.asarray(T, dtype=np.float64), c)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam[:, 0] / z * k.fx + k.cx
        v = cam[:, 1] / z * k.fy + k.cy
    mu, mv = p.absence_margin * k.width, p.absence_margin * k.height
    radius = np.array([lm.radius for lm in lms])
    visible = (
        (z >= p.absence_min_depth_m)
        & (z <= p.absence_max_depth_m)
        & (u >= mu)
        & (u <= k.width - mu)
        & (v >= mv)
        & (v <= k.height - mv)
        & (radius * k.fx >= p.absence_min_px * z)
    )
    if not visible.any():
        return []
    dist = np.linalg.norm(cam, axis=1)
    rows = np.flatnonzero(visible)  # occlusion only for the landmarks in view: (in view) x (all), not all x all
    dirs = cam[rows] / np.maximum(dist[rows], 1e-9)[:, None]
    along = dirs @ cam.T  # along[r, j]: depth of landmark j along the line of sight to landmark rows[r]
    perp = np.sqrt(np.maximum(np.square(dist)[None, :] - along**2, 0.0))
    blocks = (perp < radius[None, :]) & (along + radius[None, :] < (dist - radius)[rows][:, None]) & (along > 0)
    blocks[np.arange(len(rows)), rows] = False
    gone: list[int] = []
    for r, i in enumerate(rows):
        lm = lms[i]
        if frame_id in lm.frames or blocks[r].any():
            continue
        r_px = max(2.0, lm.radius * k.fx / z[i])  # its disk on the image meets a box of its class
        seen = any(
            b.class_name == lm.class_name
            and b.box[0] - r_px <= u[i] <= b.box[2] + r_px
            and b.box[1] - r_px <= v[i] <= b.box[3] + r_px
            for b in boxes
        )
        if seen:
            lm.absent_streak = 0
            continue
        lm.absent_streak += 1
        lm.absent_total += 1
        rate = (lm.measurements + 1.0) / (lm.measurements + lm.absent_total + 2.0)
        needed = max(p.absence_min_frames, math.log(p.absence_p) / math.log(max(1.0 - rate, 1e-9)))
        if lm.absent_streak >= needed:
            gone.append(lm.id)
    return gone

"""Leaving a frame's dynamic objects (people, things seen moving: the tracker's `dynamic` boxes) out of its depth.

One home for the rule, because three consumers apply it to the same boxes: semmap's own RGB-D registration (the
`rgbd` front end, the repair of a SLAM's steps), the ORB-SLAM3 front end's masks, and the loop closer's keyframe
clouds (a person in a keyframe's cloud is structure that is elsewhere by the next visit)."""

from __future__ import annotations

import numpy as np

from semmap.core.messages import DynamicBox

DYNAMIC_MASKS = ("box", "range", "none")


def dynamic_pixels(depth: np.ndarray, boxes: list[DynamicBox], depth_scale: float, how: str,
                   depthless: bool = False) -> np.ndarray:
    """Which pixels the dynamic objects cover (bool, the depth's shape): the whole box (`box`, or a box without a
    depth band), or only its pixels in the object's depth band (`range`: the background behind a person stays);
    `none` covers nothing. `depthless`: with `range`, a box's pixels without depth too (a person's edges and hair
    read none on most sensors: what ORB-SLAM3's masks and the arbiter's static matches leave out). The `rgbd`
    registration and the ORB-SLAM3 front end mask with it."""
    mask = np.zeros(depth.shape, dtype=bool)
    if how == "none":
        return mask
    h, w = depth.shape
    for b in boxes:
        x0, y0 = max(0, int(np.floor(b.box[0]))), max(0, int(np.floor(b.box[1])))
        x1, y1 = min(w, int(np.ceil(b.box[2]))), min(h, int(np.ceil(b.box[3])))
        if x1 <= x0 or y1 <= y0:
            continue
        if how == "box" or b.depth_max_m <= 0:
            mask[y0:y1, x0:x1] = True
        else:
            z = depth[y0:y1, x0:x1].astype(np.float64) * depth_scale
            mask[y0:y1, x0:x1] |= (z >= b.depth_min_m) & (z <= b.depth_max_m) | (depthless & (z == 0))
    return mask


def mask_dynamic(depth: np.ndarray, boxes: list[DynamicBox], depth_scale: float, how: str) -> np.ndarray:
    """A copy of `depth` (uint16) with the dynamic objects left out (0 = invalid), as `dynamic_pixels` says."""
    if how == "none" or not boxes:
        return depth
    out = depth.copy()
    out[dynamic_pixels(depth, boxes, depth_scale, how)] = 0
    return out

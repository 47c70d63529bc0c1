"""semmap's own measurement of a frame-to-frame motion (Open3D RGB-D odometry, dynamic objects left out)."""

from __future__ import annotations

import cv2
import msgspec
import numpy as np

from semmap.algorithms.dynamic_mask import DYNAMIC_MASKS, mask_dynamic
from semmap.core.messages import DynamicBox

from .base import OdometryError, OdometryInput


class PairRegistration:
    """semmap's own measurement of a frame-to-frame motion: Open3D multi-scale RGB-D odometry (hybrid) between the
    previous frame and this one, the depth of both frames' dynamic objects left out (a person moving between the
    two frames leaves out where it was and where it is, in each). `register` returns (T_prev^-1 T_cur, fitness)
    or (None, 0) for the first frame or a pair Open3D cannot register. The `rgbd` front end chains these steps;
    the repair of an external SLAM (repair.py) checks the SLAM's steps against them."""

    def __init__(self, dynamic_mask: str = "box", scale: int = 1) -> None:
        import open3d as o3d  # heavy: only when a front end that registers is chosen

        if dynamic_mask not in DYNAMIC_MASKS:
            raise OdometryError(f"odometry.dynamic_mask must be one of {DYNAMIC_MASKS}, got {dynamic_mask!r}")
        self.o3d = o3d
        self.dynamic_mask = dynamic_mask
        self.scale = max(1, int(scale))  # register images downscaled by this (real time: a quarter of the pixels)
        # the previous frame: colour (uint8 RGB), raw depth, dynamic boxes
        self._prev: tuple[np.ndarray, np.ndarray, list[DynamicBox]] | None = None
        self._criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in (10, 5, 3)]
        self.failed = 0

    def reset(self) -> None:
        """Forget the previous frame (after a restart: the next frame starts a new chain)."""
        self._prev = None

    @property
    def has_previous(self) -> bool:
        """Whether the next `register` has a previous frame to register to."""
        return self._prev is not None

    def _scaled(self, rgb: np.ndarray, depth: np.ndarray, boxes: list[DynamicBox]) -> tuple[object, np.ndarray,
                                                                                            list[DynamicBox]]:
        """Colour (Open3D), raw depth and boxes at the registration's scale (depth by nearest pixel: no mixing of
        a person's depth with the wall's behind)."""
        if self.scale == 1:
            return _color(self.o3d, rgb), depth, boxes
        s = self.scale
        small = cv2.resize(rgb, (rgb.shape[1] // s, rgb.shape[0] // s), interpolation=cv2.INTER_AREA)
        boxes = [msgspec.structs.replace(b, box=tuple(v / s for v in b.box)) for b in boxes]
        return _color(self.o3d, small), np.ascontiguousarray(depth[::s, ::s]), boxes

    def _image(self, color: object, depth: np.ndarray, boxes: list[DynamicBox], depth_scale: float) -> object:
        o3d = self.o3d
        raw = mask_dynamic(depth, boxes, depth_scale, self.dynamic_mask)
        return o3d.t.geometry.RGBDImage(color, o3d.t.geometry.Image(np.ascontiguousarray(raw)))

    def remember(self, frame: OdometryInput) -> None:
        """Keep the frame as the next registration's previous one without registering it (a step nobody asks
        about costs nothing; the next one can still be measured)."""
        if frame.rgb is None or frame.depth is None or frame.intrinsics is None:
            raise OdometryError("RGB-D registration needs RGB, depth and intrinsics")
        self._prev = (frame.rgb, frame.depth, list(frame.dynamic or []))

    def register(self, frame: OdometryInput) -> tuple[np.ndarray | None, float]:
        if frame.rgb is None or frame.depth is None or frame.intrinsics is None:
            raise OdometryError("RGB-D registration needs RGB, depth and intrinsics")
        o3d = self.o3d
        boxes = list(frame.dynamic or [])
        result: tuple[np.ndarray | None, float] = (None, 0.0)
        if self._prev is not None:
            prev_rgb, prev_depth, prev_boxes = self._prev
            pair = prev_boxes + boxes
            current = self._image(*self._scaled(frame.rgb, frame.depth, pair), frame.depth_scale)
            previous = self._image(*self._scaled(prev_rgb, prev_depth, pair), frame.depth_scale)
            k = np.asarray(frame.intrinsics, dtype=np.float64).copy()
            k[:2] /= self.scale
            K = o3d.core.Tensor(k, o3d.core.Dtype.Float64)
            try:
                out = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                    current, previous, K, o3d.core.Tensor(np.eye(4)), 1.0 / frame.depth_scale, 4.0,
                    self._criteria, o3d.t.pipelines.odometry.Method.Hybrid)
                relative = out.transformation.numpy()
                if not np.all(np.isfinite(relative)):
                    raise RuntimeError("non-finite odometry")
                result = (relative, float(out.fitness))
            except RuntimeError:
                self.failed += 1
        self._prev = (frame.rgb, frame.depth, boxes)
        return result


def _color(o3d: object, rgb: np.ndarray) -> object:
    return o3d.t.geometry.Image(np.ascontiguousarray(rgb.astype(np.float32) / 255.0))

"""Back-projection of a box's depth patch: geometry, patch indexing, foreground selection, bounds, speed."""

from __future__ import annotations

import time

import numpy as np

from semmap.algorithms.associator.backproject import (
    BackprojectParams,
    extract_surfaces,
    extract_view,
    measurement_points,
)
from semmap.core.messages import DepthPatch, Intrinsics
from tests.associator.helpers import K_SMALL, box_measurement, patch_measurement

K_VGA = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def test_plane_points_lie_on_the_plane_at_the_right_pixels() -> None:
    box = (40.0, 30.0, 100.0, 80.0)
    m = box_measurement(lambda u, v: np.full(u.shape, 2.0), box)
    pts = measurement_points(m)
    assert len(pts) > 100
    assert np.allclose(pts[:, 2], 2.0)
    u = pts[:, 0] / pts[:, 2] * K_SMALL.fx + K_SMALL.cx
    v = pts[:, 1] / pts[:, 2] * K_SMALL.fy + K_SMALL.cy
    assert np.allclose(u, np.round(u), atol=1e-6) and np.allclose(v, np.round(v), atol=1e-6)
    assert u.min() >= box[0] and u.max() < box[2] and v.min() >= box[1] and v.max() < box[3]


def test_tilted_plane_is_recovered() -> None:
    # The plane z = 1.5 + 0.3 x (x, z metres, camera frame) has depth 1.5 / (1 - 0.3 (u - cx) / fx) per pixel.
    m = box_measurement(
        lambda u, v: 1.5 / (1.0 - 0.3 * (u - K_SMALL.cx) / K_SMALL.fx), (30.0, 20.0, 130.0, 100.0)
    )
    pts = measurement_points(m, BackprojectParams(band_factor=5.0, band_max_m=5.0))
    assert len(pts) == 500
    assert np.max(np.abs(pts[:, 2] - (1.5 + 0.3 * pts[:, 0]))) < 2e-3  # mm quantisation only


def test_patch_offset_and_stride_are_honoured() -> None:
    # A patch that starts left of and above the box, stride 3: pixel (x0 + j*3, y0 + i*3) has depth[i, j].
    j = np.arange(30)
    depth = np.tile((1000 + 10 * j).astype(np.uint16), (20, 1))  # 1 cm per patch column
    patch = DepthPatch(10, 20, 3, depth)
    m = patch_measurement(patch, (12.0, 22.0, 100.0, 80.0))
    view = extract_view(m, BackprojectParams(band_min_m=0.5, max_points=10_000))
    assert view is not None
    u = view.points[:, 0] / view.points[:, 2] * K_SMALL.fx + K_SMALL.cx
    v = view.points[:, 1] / view.points[:, 2] * K_SMALL.fy + K_SMALL.cy
    col = np.rint((u - 10) / 3).astype(int)
    assert np.allclose((u - 10) / 3, col) and np.allclose((v - 20) / 3, np.rint((v - 20) / 3))
    assert np.allclose(view.points[:, 2], 1.0 + 0.01 * col)
    assert u.min() >= 12.0 and u.max() < 100.0 and v.min() >= 22.0 and v.max() < 80.0
    assert len(view.points) == 29 * 19  # columns 1..29 (x 13..97), rows 1..19 (y 23..77)


def test_foreground_object_is_kept_and_background_dropped() -> None:
    # A 0.3 m square at 1.0 m in front of a wall at 3.0 m, in a tight box and in a box 10% larger per side.
    def scene(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        inside = (np.abs(u - 80) < 21) & (np.abs(v - 60) < 21)
        return np.where(inside, 1.0, 3.0)

    for box in ((59.0, 39.0, 101.0, 81.0), (55.0, 35.0, 105.0, 85.0)):
        pts = measurement_points(box_measurement(scene, box))
        assert len(pts) > 200 and np.all(np.abs(pts[:, 2] - 1.0) < 1e-6)


def test_thin_object_wins_over_more_background_in_the_box() -> None:
    # A bottle: a vertical strip 7 px wide at 1.2 m in a 9 px wide box; the wall at 2.5 m behind it fills the
    # box as well (both reach all four sides): the nearer of the equally good surfaces is the object.
    def scene(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        strip = (np.abs(u - 80) < 4) & (v >= 20) & (v < 100)
        return np.where(strip, 1.2, 2.5)

    for box in ((77.0, 20.0, 84.0, 100.0), (76.0, 18.0, 85.0, 102.0)):
        assert np.allclose(measurement_points(box_measurement(scene, box))[:, 2], 1.2)


def test_an_occluder_in_front_that_misses_the_box_sides_loses() -> None:
    # A far object (2.8 m) fills its box; a bar at 1.5 m crosses the box's middle rows only (a table edge).
    def scene(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        obj = (np.abs(u - 80) < 20) & (np.abs(v - 60) < 30)
        bar = np.abs(v - 60) < 12
        return np.where(bar, 1.5, np.where(obj, 2.8, 4.0))

    got = extract_surfaces(box_measurement(scene, (60.0, 30.0, 100.0, 90.0)))
    assert got is not None
    assert abs(got.surfaces[0].ref_depth - 2.8) < 0.05
    assert any(abs(s.ref_depth - 1.5) < 0.05 for s in got.surfaces[1:])  # kept as an alternative


def test_invalid_depth_is_ignored_and_empty_patch_gives_no_points() -> None:
    def holes(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.where((u.astype(int) + v.astype(int)) % 2 == 0, 0.0, 1.7)

    pts = measurement_points(box_measurement(holes, (40.0, 40.0, 80.0, 80.0)))
    assert len(pts) > 0 and np.allclose(pts[:, 2], 1.7)
    assert measurement_points(
        box_measurement(lambda u, v: np.zeros(u.shape), (40.0, 40.0, 80.0, 80.0))
    ).shape == (0, 3)
    too_far = measurement_points(
        box_measurement(lambda u, v: np.full(u.shape, 30.0), (40.0, 40.0, 80.0, 80.0))
    )
    assert too_far.shape == (0, 3)  # beyond the paper's 25 m range


def test_points_are_capped_and_deterministic() -> None:
    m = box_measurement(lambda u, v: 1.0 + 0.001 * v, (0.0, 0.0, 160.0, 120.0))
    a = measurement_points(m, BackprojectParams(max_points=500))
    b = measurement_points(m, BackprojectParams(max_points=500))
    assert len(a) == 500 and np.array_equal(a, b)


def test_backprojection_is_fast_on_a_large_box() -> None:
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    depth = np.where((np.abs(u - 320) < 150) & (np.abs(v - 240) < 120), 1.8 + 0.0005 * u, 3.5)
    box = (150.0, 100.0, 490.0, 380.0)
    m = box_measurement(lambda uu, vv: depth, box, k=K_VGA, stride=2)
    extract_view(m)
    times = []
    for _ in range(20):
        t0 = time.perf_counter()
        extract_view(m)
        times.append(time.perf_counter() - t0)
    assert float(np.median(times)) < 5e-3  # ~0.4 ms here; generous for loaded CI machines

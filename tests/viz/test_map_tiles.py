"""The viewer draws the map in tiles so that an update costs the same in a kitchen and on a street."""

from __future__ import annotations

import numpy as np

from semmap.core.messages import Landmark
from semmap.services.viz.service import MAP_TILE_M, MapTiles, label_anchors, map_tile


def _landmark(lid: int, x: float, y: float = 0.0) -> Landmark:
    return Landmark(lid, "car", (x, y, 0.5), 2.0, (4.0, 1.8, 1.5), 5, 0.0, 1.0)


def test_tiles_are_named_by_cube_without_minus_signs() -> None:
    assert map_tile((0.1, 0.1, 0.1)) == "tile_0_0_0"
    assert map_tile((-0.1, MAP_TILE_M + 0.1, 0.0)) == "tile_m1_1_0"


def test_an_update_touches_only_the_tiles_it_changed() -> None:
    # a street of 2000 cars along x, 2 m apart: 4 km, 250 tiles
    landmarks = {i: _landmark(i, 2.0 * i + 0.5) for i in range(2000)}
    tiles = MapTiles()
    first = tiles.place(set(landmarks), landmarks)
    assert len(first) == 250 and sum(len(ids) for ids in first.values()) == 2000

    landmarks[1999] = _landmark(1999, 2.0 * 1999 + 1.0)  # refined in place: its own tile only
    assert list(tiles.place({1999}, landmarks)) == [map_tile(landmarks[1999].centroid)]

    moved = _landmark(5, 100.0)  # moved into another tile: the one it left and the one it joined
    landmarks[5] = moved
    touched = tiles.place({5}, landmarks)
    assert set(touched) == {"tile_0_0_0", map_tile(moved.centroid)}
    assert 5 in touched[map_tile(moved.centroid)] and 5 not in touched["tile_0_0_0"]

    gone = [i for i in landmarks if map_tile(landmarks[i].centroid) == "tile_1_0_0"]
    for i in gone:
        del landmarks[i]
    assert tiles.place(set(gone), landmarks) == {"tile_1_0_0": []}  # emptied: the viewer clears it
    assert "tile_1_0_0" not in tiles.members


def test_labels_of_near_objects_stack_and_far_ones_stay_put() -> None:
    up = np.array([0.0, 0.0, 1.0])
    centres = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [5.0, 0.0, 0.0]])
    anchors = label_anchors(centres, centres + [0.0, 0.0, 0.1], up)
    assert np.allclose(anchors[0], [0.0, 0.0, 0.15]) and np.allclose(anchors[2], [5.0, 0.0, 0.15])
    assert anchors[1][2] > anchors[0][2] and np.linalg.norm(anchors[1] - anchors[0]) >= 0.12

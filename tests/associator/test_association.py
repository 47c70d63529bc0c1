"""The validation gate and the candidate-to-landmark decision."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.algorithms.associator.association import decide, gate_floor, gate_radius
from semmap.algorithms.associator.geometry import voxel_downsample
from semmap.algorithms.associator.landmark_map import LandmarkMap
from semmap.algorithms.associator.params import MapperParams

P = MapperParams()


def test_gate_follows_the_paper_above_its_floor() -> None:
    # r = sqrt(dt / u * s), u = 10
    assert gate_radius(10.0, 1.0, P) == pytest.approx(1.0)
    assert gate_radius(40.0, 0.9, P) == pytest.approx(math.sqrt(40.0 / 10.0 * 0.9))
    # dt -> 0: the floor max(gate_min_m, gate_size_factor * s) instead of 0
    assert gate_radius(0.0, 0.1, P) == pytest.approx(0.1)
    assert gate_radius(0.0, 1.0, P) == pytest.approx(0.5)
    assert gate_floor(0.4, P) == pytest.approx(0.2)
    radii = [gate_radius(dt, 0.5, P) for dt in (0.0, 1.0, 5.0, 20.0, 100.0)]
    assert radii == sorted(radii) and radii[-1] == pytest.approx(math.sqrt(5.0))
    assert gate_radius(30.0, 0.5, MapperParams(gate_u=5.0)) > gate_radius(30.0, 0.5, P)


def sphere_cloud(centre: np.ndarray, radius: float, n: int = 400, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return np.asarray(centre) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def make_map(objects: list[tuple[str, np.ndarray, float]], stamp: float = 0.0) -> LandmarkMap:
    m = LandmarkMap()
    for cls, c, r in objects:
        lm = m.create(cls, stamp)
        lm.views = [object()]  # type: ignore[list-item]  # decide() only checks that a landmark has views
        lm.centroid = np.asarray(c, float)
        lm.set_cloud(voxel_downsample(sphere_cloud(c, r), 0.01))
        lm.size = 2 * r * math.sqrt(3)
        lm.frames = {100 + lm.id}
    return m


def test_no_landmark_in_the_gate_makes_a_new_one() -> None:
    m = make_map([("cup", np.array([0.0, 0.0, 0.8]), 0.04)])
    d = decide(np.array([0.5, 0.0, 0.8]), 0.1, {1, 2}, lambda: np.zeros((0, 3)), m.of_class("cup"), 0.5, 5, P)
    assert d.kind == "new" and d.in_gate == []


def test_one_clearly_close_landmark_is_joined_without_a_cloud_check() -> None:
    m = make_map([("cup", np.array([0.0, 0.0, 0.8]), 0.04)])

    def no_cloud() -> np.ndarray:
        raise AssertionError("the cloud step must not run")

    d = decide(np.array([0.02, 0.0, 0.8]), 0.1, {1}, no_cloud, m.of_class("cup"), 0.5, 5, P)
    assert d.kind == "associate" and d.landmark_id == 0 and d.nn_ms == 0.0


def test_other_classes_are_never_candidates() -> None:
    m = make_map([("bowl", np.array([0.0, 0.0, 0.8]), 0.04)])
    d = decide(np.array([0.0, 0.0, 0.8]), 0.1, {1}, lambda: np.zeros((0, 3)), m.of_class("cup"), 0.5, 5, P)
    assert d.kind == "new"


def test_several_in_the_gate_pick_the_nearest_cloud() -> None:
    # Two large landmarks whose gates both hold the candidate; its cloud lies on the second one.
    a, b = np.array([0.0, 0.0, 0.5]), np.array([0.5, 0.0, 0.5])
    m = make_map([("chair", a, 0.25), ("chair", b, 0.25)])
    cand = sphere_cloud(b + [0.01, 0.0, 0.0], 0.25, seed=3)
    d = decide(np.array([0.3, 0.0, 0.5]), 0.8, {1}, lambda: cand, m.of_class("chair"), 30.0, 8, P)
    assert set(d.in_gate) == {0, 1} and d.kind == "associate" and d.landmark_id == 1
    assert d.nn[1] < d.nn[0] and d.nn_ms > 0.0


def test_ambiguous_candidate_is_held_then_decided_when_forced() -> None:
    a, b = np.array([0.0, 0.0, 0.5]), np.array([0.4, 0.0, 0.5])
    m = make_map([("chair", a, 0.25), ("chair", b, 0.25)])
    cand = np.concatenate([sphere_cloud(a, 0.25, seed=4), sphere_cloud(b, 0.25, seed=5)])
    args = (np.array([0.2, 0.0, 0.5]), 0.8, {1}, lambda: cand, m.of_class("chair"), 30.0)
    assert decide(*args, 5, P).kind == "hold"
    assert decide(*args, P.hold_max_views, P).kind == "associate"
    assert decide(*args, 5, P, force=True).kind == "associate"


def test_a_nearby_object_whose_cloud_does_not_overlap_gets_its_own_landmark() -> None:
    # Two cups 15 cm apart; the candidate's centroid estimate is off by 7 cm towards the mapped one.
    m = make_map([("cup", np.array([0.0, 0.0, 0.8]), 0.04)])
    cand = sphere_cloud(np.array([0.15, 0.0, 0.8]), 0.04, seed=6)
    d = decide(np.array([0.08, 0.0, 0.8]), 0.1, {1}, lambda: cand, m.of_class("cup"), 0.2, 6, P)
    assert d.in_gate == [0] and d.kind == "new"


def test_co_visible_landmark_is_vetoed() -> None:
    # The mapped cup was measured in frames the candidate was also seen in: a different cup.
    m = make_map([("cup", np.array([0.0, 0.0, 0.8]), 0.04)])
    m[0].frames = {10, 11, 12}
    d = decide(
        np.array([0.01, 0.0, 0.8]), 0.1, {11, 12, 13}, lambda: np.zeros((0, 3)), m.of_class("cup"), 0.2, 6, P
    )
    assert d.kind == "new"


def test_gate_grows_with_time_since_last_association() -> None:
    m = make_map([("tv", np.array([0.0, 0.0, 1.0]), 0.3)], stamp=0.0)
    centroid = np.array([0.7, 0.0, 1.0])  # drifted 0.7 m
    cand = sphere_cloud(centroid, 0.3, seed=7)
    soon = decide(centroid, 1.0, {1}, lambda: cand, m.of_class("tv"), 1.0, 6, P)
    later = decide(centroid, 1.0, {1}, lambda: cand, m.of_class("tv"), 60.0, 6, P)
    assert soon.kind == "new" and later.kind == "associate"

"""Revisits (semmap/algorithms/associator/revisit.py): a street seen again after drift is recognised by its objects,
a street that only looks alike is not, and a room's objects never count as old enough to be revisited."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from semmap.algorithms.associator.landmark_map import LandmarkState
from semmap.algorithms.associator.params import MapperParams
from semmap.algorithms.associator.revisit import RevisitFinder
from tests.associator.helpers import fake_view

CLASSES = ["car", "car", "car", "bench", "potted plant", "car", "traffic light", "car", "bicycle", "car"]
SIZES = {"car": 5.0, "bench": 1.8, "potted plant": 1.2, "traffic light": 1.0, "bicycle": 2.0}


def _street(rng: np.random.Generator, n: int = 10) -> list[tuple[str, np.ndarray]]:
    """Objects on both sides of a 150 m street (x along it), irregularly spaced."""
    xs = np.sort(rng.uniform(0.0, 150.0, n))
    return [(CLASSES[i % len(CLASSES)], np.array([x, rng.choice([-6.0, 6.0]), rng.uniform(0.5, 1.5)]))
            for i, x in enumerate(xs)]


def _landmark(lid: int, cls: str, centre: np.ndarray, first: float, last: float) -> LandmarkState:
    lm = LandmarkState(lid, cls, first_seen=first, last_seen=last, last_assoc=last)
    lm.views = [fake_view(k, first + k, centre, SIZES[cls]) for k in range(5)]
    lm.centroid = lm.map_centroid = np.asarray(centre, float)
    lm.size = SIZES[cls]
    return lm


def _drifted(points: list[tuple[str, np.ndarray]], rng: np.random.Generator) -> list[tuple[str, np.ndarray]]:
    """The same objects as a drifted odometry places them: 15 deg and 12 m off, 0.3 m of centroid noise."""
    R = Rotation.from_euler("z", 15, degrees=True).as_matrix()
    t = np.array([12.0, -5.0, 0.3])
    return [(c, R @ p + t + rng.normal(0.0, 0.3, 3)) for c, p in points]


def test_a_street_seen_again_after_drift_is_recognised_by_its_objects() -> None:
    rng = np.random.default_rng(3)
    street = _street(rng)
    elsewhere = [(c, p + np.array([0.0, 400.0, 0.0])) for c, p in _street(rng)]  # old objects of another street
    old = [_landmark(i, c, p, 0.0, 20.0) for i, (c, p) in enumerate(street + elsewhere)]
    recent = [_landmark(100 + i, c, p, 290.0, 299.0) for i, (c, p) in enumerate(_drifted(street, rng))]
    finder = RevisitFinder(MapperParams())
    assert finder.due(300.0)
    found = finder.search(old + recent, 300.0)
    assert found is not None
    assert len(found.pairs) >= 8 and all(o == r - 100 for r, o in found.pairs)  # each to its own old object
    assert not finder.due(301.0) and finder.due(302.0)  # every revisit_every_s


def test_a_street_that_only_looks_alike_is_not_a_revisit() -> None:
    rng = np.random.default_rng(4)
    old = [_landmark(i, c, p, 0.0, 20.0) for i, (c, p) in enumerate(_street(rng, 40))]
    other = _street(np.random.default_rng(99))  # the same classes, another layout
    recent = [_landmark(100 + i, c, p, 290.0, 299.0) for i, (c, p) in enumerate(other)]
    finder = RevisitFinder(MapperParams())
    assert finder.search(old + recent, 300.0) is None
    assert finder.counters() == {"revisit_searches": 1, "revisits": 0, "revisit_fused_landmarks": 0}


def test_landmarks_seen_within_revisit_old_s_are_not_old() -> None:
    """A room's objects are re-associated through the gate all the time: none is old, nothing is searched."""
    rng = np.random.default_rng(5)
    street = _street(rng)
    seen_lately = [_landmark(i, c, p, 0.0, 250.0) for i, (c, p) in enumerate(street)]
    recent = [_landmark(100 + i, c, p, 290.0, 299.0) for i, (c, p) in enumerate(_drifted(street, rng))]
    finder = RevisitFinder(MapperParams())
    assert finder.search(seen_lately + recent, 300.0) is None and finder.searches == 0


def test_the_clock_survives_a_restart() -> None:
    finder = RevisitFinder(MapperParams())
    finder.search([], 50.0)
    again = RevisitFinder(MapperParams())
    again.restore(finder.to_state())
    assert not again.due(51.0) and again.due(52.0)
    assert RevisitFinder(MapperParams(revisit=False)).due(1e9) is False

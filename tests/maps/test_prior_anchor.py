"""A prior landmark in a relocalised session keeps its place and class unless the evidence says it moved (issue
34; semmap/algorithms/associator/prior_anchor.py): the analytic sphere scene of tests/associator, two sessions,
the second fused into the first's map by `PriorSession.adopt` as a relocalisation does."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from semmap.algorithms.associator.landmark_map import LandmarkMap, LandmarkState
from semmap.algorithms.associator.landmark_update import recompute
from semmap.algorithms.associator.mapper import LandmarkMapper, MapperParams
from semmap.algorithms.associator.prior_anchor import PriorAnchor, held_place
from semmap.algorithms.associator.prior_map import PriorParams, PriorSession, _frozen
from semmap.algorithms.map_merge import merge_maps
from semmap.algorithms.odometry.frontends import frame_offset
from semmap.algorithms.relocalize import RelocResult
from semmap.core.messages import Landmark
from tests.associator.helpers import Sphere, orbit_pose
from tests.associator.test_mapper import RATE, run

SESSION_FRAME = frame_offset([0.5, -0.3, 0.1, 5.0, -8.0, 30.0])  # the session's odometry frame in the prior's


def _relocalised(
    prior_sphere: Sphere, session_sphere: Sphere, registration_error: np.ndarray, params: MapperParams | None = None
) -> tuple[LandmarkState, LandmarkState, LandmarkMapper]:
    """(the prior landmark as the first session left it (a copy), the same landmark in the second session's map, the
    second session's mapper):
    the first session maps `prior_sphere` for 45 frames; the second session maps `session_sphere` for 120 frames in its
    own frame and
    is relocalised with the sphere matched to the prior one, its poses off by `registration_error`."""
    prior_mapper, _ = run(lambda t: [prior_sphere], range(45), mapper=LandmarkMapper(params))
    (before,) = LandmarkMap.from_state(prior_mapper.map.to_state()).all()
    session = LandmarkMapper(params)
    session.map.next_id = prior_mapper.map.next_id
    lookup: Callable[[float], np.ndarray] = lambda t: np.linalg.inv(SESSION_FRAME) @ orbit_pose(t)  # noqa: E731
    session, _ = run(lambda t: [session_sphere], range(45, 165), mapper=session, lookup_at=lookup)
    (mapped,) = session.map.all()
    s = PriorSession(prior_mapper.map, PriorParams())
    fit = RelocResult(SESSION_FRAME.copy(), [(mapped.id, before.id)], 4, 0.02, 0, 1, False)
    s.adopt(session, fit, 165, 45 / RATE, lambda f: registration_error @ orbit_pose(f / RATE))
    return before, session.map[before.id], session


def test_a_prior_landmark_keeps_its_place_and_class_against_the_sessions_views() -> None:
    """The second session boxes the microwave as a laptop (more often than the first session boxed it at all) and its
    poses are 8 cm
    off: the landmark stays within 2.5 cm of its prior place (measured 1.4) and stays a microwave. Without the anchor
    the fused views would put it most of the way to the session's place (7.8 cm: 40 views of the session against 15
    of the prior), and the votes would make it a laptop (as they would the 7-Scenes microwave)."""
    error = frame_offset([0.08, 0.0, 0.0, 0.0, 0.0, 0.0])
    before, lm, session = _relocalised(
        Sphere((0.0, 0.0, 0.8), 0.1, "microwave"), Sphere((0.0, 0.0, 0.8), 0.1, "laptop"), error
    )
    assert lm.anchor is not None and not lm.anchor.moved
    assert lm.class_votes["laptop"] > lm.class_votes["microwave"] and lm.class_name == "microwave"
    assert math.dist(lm.centroid, before.centroid) < 0.025, lm.anchor.session_offset_m
    assert 0.06 < lm.anchor.session_offset_m < 0.10  # what the session's views alone say
    lm.anchor = None  # the same views without it: the fused cloud's centre, pulled towards the session's
    recompute([lm], 0.0, session.params, set())
    assert math.dist(lm.centroid, before.centroid) > 0.05


def test_a_prior_landmark_that_moved_follows_the_session() -> None:
    """The cup stands 35 cm from where the first session saw it (matched to it by the relocalisation): far beyond what
    the
    registration and the cup's size explain, so it takes the session's place and cloud."""
    before, lm, _ = _relocalised(Sphere((0.0, 0.0, 0.8), 0.05, "cup"), Sphere((0.35, 0.0, 0.8), 0.05, "cup"), np.eye(4))
    assert lm.anchor is not None and lm.anchor.moved
    assert math.dist(lm.centroid, (0.35, 0.0, 0.8)) < 0.03
    assert np.linalg.norm(lm.cloud.mean(axis=0) - np.array([0.35, 0.0, 0.8])) < 0.05


def test_prior_views_keep_their_weight() -> None:
    """`max_views` caps this session's views of a prior landmark, not its prior views: the newest views win, and on
    the second 7-Scenes session would thin out the first session's views of a landmark until those left were 15-23 cm
    off."""
    params = MapperParams(max_views=8)
    before, lm, _ = _relocalised(
        Sphere((0.0, 0.0, 0.8), 0.05, "cup"), Sphere((0.0, 0.0, 0.8), 0.05, "cup"), np.eye(4), params
    )
    prior_views = [v for v in lm.views if v.frame_id < 0]
    assert len(prior_views) == len(before.views) == 8
    assert len(lm.views) - len(prior_views) == 8


def test_held_place() -> None:
    prior = np.zeros(3)
    place, moved = held_place(prior, 0.03, np.array([0.1, 0.0, 0.0]), 0.09, 3.0)
    assert not moved and np.allclose(place, [0.01, 0.0, 0.0])  # the estimate's precision share: 0.03^2 / 0.09^2
    place, moved = held_place(prior, 0.03, np.array([0.4, 0.0, 0.0]), 0.09, 3.0)
    assert moved and np.allclose(place, [0.4, 0.0, 0.0])
    place, moved = held_place(prior, 0.03, np.array([0.4, 0.0, 0.0]), 0.09, 3.0, may_move=False)
    assert not moved and np.allclose(place, [0.04, 0.0, 0.0])


def test_the_anchor_is_saved_moved_with_the_map_and_frozen_ids_stay_frozen() -> None:
    m = LandmarkMap()
    lm = m.create("microwave", 0.0)
    lm.anchor = PriorAnchor(np.array([1.0, 2.0, 3.0]), "microwave", 0.03, 0.05)
    restored = LandmarkMap.from_state(m.to_state()).all()[0]
    assert restored.anchor is not None and np.allclose(restored.anchor.centroid, [1.0, 2.0, 3.0])
    assert restored.anchor.class_name == "microwave" and restored.anchor.registration_sigma_m == 0.05
    mapper = LandmarkMapper()
    mapper.map = LandmarkMap.from_state(m.to_state())
    mapper.move_frame(frame_offset([1.0, 0.0, 0.0, 0.0, 0.0, 90.0]))
    assert np.allclose(mapper.map.all()[0].anchor.centroid, [-1.0, 1.0, 3.0])
    # a prior map that was itself a relocalised session's holds views frozen already: they stay frozen
    assert _frozen(7) == -8 and _frozen(_frozen(7)) == -8


def test_merge_holds_as_place_unless_b_says_it_moved() -> None:
    """`semmap merge A B` places a pair as a session relocalised against A would: A's place, unless B's lies far
    beyond what registration and size explain (a cup 25 cm away, within the pairing gate)."""
    cup = Landmark(0, "cup", (1.0, 1.0, 0.8), 0.05, (0.1, 0.1, 0.1), 40, 0.0, 10.0)
    near = Landmark(5, "cup", (1.08, 1.0, 0.8), 0.05, (0.1, 0.1, 0.1), 60, 20.0, 30.0)
    far = Landmark(5, "cup", (1.25, 1.0, 0.8), 0.05, (0.1, 0.1, 0.1), 60, 20.0, 30.0)
    (kept,) = merge_maps([cup], [near])
    assert math.dist(kept.centroid, cup.centroid) < 0.025 and kept.observations == 100
    (moved,) = merge_maps([cup], [far])
    assert math.dist(moved.centroid, far.centroid) < 1e-9

"""Candidate validation (motion, spread), surface consensus and the MAP centroid."""

from __future__ import annotations

import numpy as np

from semmap.algorithms.associator.candidate import (
    MapProblem,
    choose_surfaces,
    coherent_motion,
    map_centroids,
    map_problem,
    triangulate,
    validate,
)
from semmap.algorithms.associator.params import MapperParams
from tests.associator.helpers import fake_view, look_at

P = MapperParams()


def static_views(n: int, scatter: float, size: float = 0.3, seed: int = 0, rate: float = 10.0) -> list:
    rng = np.random.default_rng(seed)
    centre = np.array([1.0, 2.0, 0.8])
    return [fake_view(i, i / rate, centre + rng.normal(0.0, scatter, 3), size=size) for i in range(n)]


def test_static_object_with_centimetre_scatter_passes() -> None:
    for scatter in (0.03, 0.06):
        for seed in range(5):
            v = validate(static_views(30, scatter / np.sqrt(3), seed=seed), P)
            assert v.ok, (scatter, seed, v)


def test_walking_person_is_rejected_by_motion() -> None:
    # 1 m/s for 1.5 s, 10 views per second, centroid noise 3 cm, a person-sized box.
    rng = np.random.default_rng(1)
    views = [
        fake_view(i, i / 10, np.array([0.1 * i, 0.0, 0.9]) + rng.normal(0, 0.03, 3), size=0.9)
        for i in range(15)
    ]
    moving, speed, displacement = coherent_motion(views, P)
    assert moving and 0.7 < speed < 1.3 and displacement > 0.6
    v = validate(views, P)
    assert not v.ok and v.reason == "motion"


def test_slow_drift_of_a_big_partial_view_object_is_not_motion() -> None:
    # A chair whose visible part changes once (a 0.35 m jump halfway): not a steady motion.
    views = [fake_view(i, i / 10, np.array([0.0, 0.0, 0.35 if i < 10 else 0.0]), size=0.5) for i in range(20)]
    assert not coherent_motion(views, P)[0]
    assert validate(views, P).ok


def test_a_switch_of_surface_inside_a_segment_is_one_jump_not_a_steady_motion() -> None:
    """A static chair seen every 4th frame whose views move from its back to its seat (0.35 m lower) half way
    through a segment, one wrong view beside (from the synthetic scene at 15 Hz). The segment's per-axis median
    fell between the surfaces and made the jump two steady steps: the chair was retired as moving."""
    back, seat, wrong = np.array([-0.44, 0.8, 0.8]), np.array([-0.36, 0.61, 0.47]), np.array([0.69, -0.09, 0.78])
    stamps = [0.93, 1.0, 1.4, 1.53, 1.6, 1.73, 1.87, 2.0, 2.13, 2.27, 2.4]
    where = [back] * 5 + [wrong] + [seat] * 5
    views = [fake_view(i, t, c, size=0.8) for i, (t, c) in enumerate(zip(stamps, where, strict=True))]
    assert not coherent_motion(views, P)[0]
    # the same chair carried away steadily is still moving
    carried = [fake_view(i, t, back + np.array([0.0, -0.45 * (t - 0.93), 0.0]), size=0.8)
               for i, t in enumerate(stamps)]
    assert coherent_motion(carried, P)[0]


def test_erratic_object_is_rejected_by_spread() -> None:
    rng = np.random.default_rng(2)
    views = [fake_view(i, i / 10, rng.uniform(-0.6, 0.6, 3), size=0.3) for i in range(20)]
    v = validate(views, P)
    assert not v.ok and v.reason in ("spread", "inconsistent")
    assert v.spread_m > v.spread_limit_m or v.reason == "inconsistent"


def test_a_minority_of_wrong_surface_views_is_tolerated() -> None:
    # 30% of a chair's views latch onto the table top 0.8 m away: the trimmed MAD ignores them.
    views = static_views(20, 0.03, size=0.5)
    for i in range(0, 20, 3):
        views[i] = fake_view(i, i / 10, np.array([1.8, 2.0, 0.8]), size=0.5)
    assert validate(views, P).ok


def test_too_few_views_are_not_condemned() -> None:
    views = [
        fake_view(0, 0.0, np.zeros(3)),
        fake_view(1, 0.1, np.array([0.8, 0.0, 0.0])),
        fake_view(2, 0.2, np.zeros(3)),
    ]
    assert validate(views, P).ok


def test_truncated_views_do_not_count_for_motion() -> None:
    # An object sliding into view: its truncated views' centroids move, the object does not.
    views = [
        fake_view(i, i / 10, np.array([0.05 * i, 0.0, 0.0]), size=0.4, truncated=True) for i in range(15)
    ]
    assert not coherent_motion(views, P)[0]


def test_consensus_picks_the_surface_that_stays_put() -> None:
    # Every view's preferred surface is a table patch that moves with the viewpoint (score 0.7); the
    # object (score 0.5) is always at the same place.
    obj = np.array([0.0, 0.0, 0.5])
    views = []
    for i in range(10):
        a = 0.3 * i
        table = np.array([0.8 * np.cos(a), 0.8 * np.sin(a), 0.75])
        v = fake_view(i, i / 10, table, size=0.45, alternatives=[(obj + 0.02 * np.sin(i), 0.5)])
        v.alt_scores[0] = 0.7
        views.append(v)
    choose_surfaces(views, P)
    assert all(v.choice == 1 for v in views)
    assert validate(views, P).ok


def test_consensus_joins_partial_and_full_views() -> None:
    # Back-only views (centre 0.37 m above the full chair's) and full views of the same chair; a
    # distractor surface far away in the full views.
    full = np.array([0.0, 0.0, 0.48])
    back = full + np.array([0.0, 0.13, 0.35])
    views = [fake_view(i, i / 10, back, size=0.45) for i in range(3)]
    for i in range(3, 6):
        v = fake_view(i, i / 10, full + np.array([1.0, -0.7, 0.4]), size=0.45, alternatives=[(full, 0.45)])
        v.alt_scores[0] = 0.5
        views.append(v)
    choose_surfaces(views, P)
    assert [v.choice for v in views] == [0, 0, 0, 1, 1, 1]


def test_map_centroid_is_close_to_the_truth_under_noise_and_outliers() -> None:
    rng = np.random.default_rng(4)
    truth = np.array([0.5, -1.0, 0.9])
    errs_map, errs_mean = [], []
    for trial in range(10):
        c = truth + rng.normal(0.0, 0.05, (40, 3))
        c[:8] = truth + rng.uniform(0.5, 1.0, (8, 3))  # 20% wrong-surface views on one side
        sig = np.full(40, 0.06)
        start = np.median(c, axis=0)
        m = map_centroids([MapProblem(c, sig, start, (0, trial))], P)[0]
        errs_map.append(np.linalg.norm(m - truth))
        errs_mean.append(np.linalg.norm(c.mean(axis=0) - truth))
    assert np.median(errs_map) < 0.02
    assert np.median(errs_map) < 0.2 * np.median(errs_mean)


def test_map_centroids_batch_matches_single_runs_and_is_deterministic() -> None:
    rng = np.random.default_rng(5)
    problems = [
        MapProblem(rng.normal(i, 0.05, (n, 3)), np.full(n, 0.05), np.full(3, float(i)), (0, i))
        for i, n in enumerate((5, 12, 30))
    ]
    batch = map_centroids(problems, P)
    again = map_centroids(problems, P)
    for b, a, q in zip(batch, again, problems, strict=True):
        assert np.array_equal(a, b)
        single = map_centroids([q], P)[0]
        assert np.linalg.norm(single - b) < 0.01  # same seeds, different padding: nearly identical


def test_triangulation_from_rays_around_an_object() -> None:
    target = np.array([0.3, -0.2, 0.8])
    views = []
    for i in range(8):
        a = i * np.pi / 4
        pose = look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 1.5]), target)
        v = fake_view(i, i / 10, target, pose=pose)
        v.ray = np.array([0.0, 0.0, 1.0])  # the box centre is on the optical axis
        views.append(v)
    point, eig = triangulate(views)
    assert np.linalg.norm(point - target) < 1e-6 and eig > 0.3
    q = map_problem(views, P, (0,))
    assert np.linalg.norm(q.start - target) < 1e-6


def test_views_a_person_covers_do_not_retire_a_landmark_but_still_condemn_a_newcomer() -> None:
    """A chair seen still, then with a person walking behind it whose depth shows through the chair's box: the
    covered views' centroids walk with the person. Flagged occluded (by the tracker), they do not count as
    motion for an established landmark; for a new candidate they do (a cup a person carries is covered by the
    person too, and must not become a landmark)."""
    still = [fake_view(i, i / 10, np.array([-0.45, 0.62, 0.47]), size=0.9) for i in range(10)]
    walking = [np.array([-0.45, 0.62 + 0.05 * k, 0.47 + 0.04 * k]) for k in range(1, 11)]
    views = still + [fake_view(10 + k, (10 + k) / 10, w, size=0.9) for k, w in enumerate(walking)]
    for v in views[10:]:
        v.occluded = True
    assert coherent_motion(views, P)[0] and validate(views, P).reason == "motion"
    assert not coherent_motion(views, P, trust_occluded=False)[0]
    assert not views[-1].shows_motion(trust_occluded=False) and views[0].shows_motion(trust_occluded=False)

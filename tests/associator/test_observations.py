"""Backend observations: what the sensor saw (not what the current estimate predicts), honest sigmas."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.algorithms.associator.mapper import LandmarkMapper, MapperParams
from semmap.algorithms.tracker.iou_tracker import IouTracker
from tests.associator.helpers import K_SMALL, Sphere, detections, orbit_pose

RATE = 30.0
CUP = Sphere((0.0, 0.0, 0.8), 0.05, "cup")
SHIFT = np.array([0.1, 0.0, 0.0])  # the pose estimate's error after frame 120


def observe_with_a_pose_error(params: MapperParams) -> list[tuple[int, np.ndarray]]:
    """Map the cup with exact poses for 4 s, then with poses 10 cm off; (frame, point_camera) of every
    observation sent while the estimate was off."""
    mapper, tracker = LandmarkMapper(params), IouTracker()
    out_obs = []
    for f in range(240):
        t = f / RATE

        def lookup(i: int) -> np.ndarray:
            pose = orbit_pose(i / RATE)
            if i >= 120:
                pose[:3, 3] += SHIFT
            return pose

        out = tracker.update(f, t, detections(orbit_pose(t), [CUP]), K_SMALL, 0.001)
        step = mapper.process(f, t, out.candidates, out.ended, lookup)
        if f >= 120:
            out_obs += [(f, np.array(o.point_camera)) for o in step.observations]
    return out_obs


def test_observations_show_the_pose_error_instead_of_echoing_the_estimate() -> None:
    """The backend must see a pose error in full: the observed centre in the camera frame is where the depth
    data puts the object, whatever pose the associator's estimate has for the frame. (Regression: with the
    view registered to the landmark cloud first, the "measurement" was the landmark as predicted through the
    wrong pose, i.e. no correction: 7-Scenes optimised ATE was worse than the odometry's.)"""
    obs = observe_with_a_pose_error(MapperParams())
    assert len(obs) >= 3
    for f, p in obs:
        true_pose = orbit_pose(f / RATE)
        world = true_pose[:3, :3] @ p + true_pose[:3, 3]
        assert np.linalg.norm(world - np.array(CUP.centre)) < 0.035  # measured 2.2-2.6 cm (the visible cap)
    echoed = observe_with_a_pose_error(MapperParams(observation_register=True))
    err = [np.linalg.norm(orbit_pose(f / RATE)[:3, :3] @ p + orbit_pose(f / RATE)[:3, 3] - CUP.centre)
           for f, p in echoed]
    assert np.median(err) > 0.04  # the old default: measured 4.5-4.9 cm, half the pose error hidden



def test_truncated_views_observe_with_a_larger_sigma() -> None:
    mapper, tracker = LandmarkMapper(), IouTracker()
    for f in range(100):
        t = f / RATE
        out = tracker.update(f, t, detections(orbit_pose(t), [CUP]), K_SMALL, 0.001)
        mapper.process(f, t, out.candidates, out.ended, lambda i: orbit_pose(i / RATE))
    lm = mapper.map.all()[0]
    view = next(v for v in reversed(lm.views) if v.inlier)
    lm.last_obs_sent = -math.inf
    whole = mapper._observation(lm, view.frame_id, view.stamp)
    lm.last_obs_sent = -math.inf
    view.truncated = True
    cut = mapper._observation(lm, view.frame_id, view.stamp)
    assert whole is not None and cut is not None
    assert cut.point_camera == whole.point_camera
    assert cut.sigma == pytest.approx(MapperParams().obs_truncated_sigma_factor * whole.sigma)
    assert MapperParams().obs_truncated_sigma_factor > 1.0


def test_observations_say_how_much_depth_they_did_not_see() -> None:
    """A cup's visible side: as wide as the cup across the ray, less deep along it; what the view may not have seen
    is bounded by its footprint (the backend loosens the range by it)."""
    mapper, tracker = LandmarkMapper(), IouTracker()
    sent = []
    for f in range(120):
        t = f / RATE
        out = tracker.update(f, t, detections(orbit_pose(t), [CUP]), K_SMALL, 0.001)
        sent += mapper.process(f, t, out.candidates, out.ended, lambda i: orbit_pose(i / RATE)).observations
    assert sent
    for o in sent:
        assert o.depth_unseen is not None and 0.06 < o.depth_unseen < 0.15, o  # the 10 cm cup's footprint


def test_extent_along_and_across_the_ray() -> None:
    from semmap.algorithms.associator.observation import depth_unseen, extent_along_across

    rng = np.random.default_rng(0)
    n = 2000
    side = np.c_[rng.uniform(-2.25, 2.25, n), rng.uniform(-0.7, 0.7, n), 8.0 + rng.uniform(0.0, 0.3, n)]
    depth, width = extent_along_across(side, side.mean(axis=0), 5.0)  # a car's side, 8 m ahead
    assert abs(depth - 0.3) < 0.03 and abs(width - 4.5) < 0.15
    assert abs(depth_unseen(side, side, side.mean(axis=0), 5.0) - 4.5) < 0.15  # its footprint
    box = np.c_[rng.uniform(-0.3, 0.3, n), rng.uniform(-0.5, 0.5, n), 3.0 + rng.uniform(0.0, 0.6, n)]
    depth, width = extent_along_across(box, box.mean(axis=0), 5.0)  # a chair seen whole, 3 m ahead
    assert abs(depth - 0.6) < 0.05 and abs(width - 0.6) < 0.05
    assert abs(depth_unseen(box, box, box.mean(axis=0), 5.0) - 0.6) < 0.05
    assert extent_along_across(box[:1], box[0], 5.0) == (0.0, 0.0)

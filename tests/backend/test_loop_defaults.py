"""The settings that make landmark constraints pull: robust kernel, declared odometry sigmas, rates.

Each one was measured in the closed loop (the in-process driver, semmap/runtime/pipeline/inprocess.py) on 7-Scenes; the
figures are in the comments of semmap/core/config (`semmap config show`), pose_graph.py and frontends.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from semmap.algorithms.associator.params import MapperParams
from semmap.algorithms.backend.loop_closure import LoopClosureParams
from semmap.algorithms.backend.pose_graph import BackendParams
from semmap.algorithms.odometry.frontends import DriftingOdometry, OdometryInput, make_frontend
from semmap.core.config import load_config


def test_defaults() -> None:
    assert BackendParams().robust_kernel == "cauchy"
    assert BackendParams().relative_pose_kernel == "huber"  # loop closures arrive with large residuals
    with pytest.raises(ValueError, match="relative_pose_kernel"):
        BackendParams(relative_pose_kernel="tukey")
    assert MapperParams().observation_period_s == 1.0
    assert MapperParams().observation_register is False
    assert BackendParams().min_observations_per_landmark == 3
    assert BackendParams().landmark_constraints is True
    assert LoopClosureParams().enabled is True  # breaks the centroid floor (README, Table 1)
    with pytest.raises(ValueError, match="landmark_constraints"):
        BackendParams(landmark_constraints="no")


def test_a_bias_is_declared_over_its_horizon() -> None:
    """A constant yaw bias b grows to n*b over n frames, a declared random walk only to sqrt(n)*sigma: the
    front end declares sqrt(sigma^2 + horizon * b^2) per frame, which matches the bias at n = horizon."""
    plain = DriftingOdometry(0, 0.003, 0.3, 0.05)
    assert plain.sigmas[1] == pytest.approx(math.radians(math.hypot(0.3, 0.05)))
    horizon = DriftingOdometry(0, 0.003, 0.3, 0.05, bias_horizon_frames=100)
    assert horizon.sigmas[1] == pytest.approx(math.radians(math.sqrt(0.3**2 + 100 * 0.05**2)))
    assert horizon.sigmas[1] * math.sqrt(100) >= math.radians(0.05) * 100  # covers the bias over the horizon
    cfg = load_config(None, []).odometry
    assert make_frontend("gt+drift", cfg).sigmas[1] == pytest.approx(
        math.radians(math.sqrt(cfg.drift_yaw_sigma_deg**2 + cfg.drift_bias_horizon_frames * cfg.drift_yaw_bias_deg**2)))


def test_the_declared_sigma_does_not_change_the_trajectory() -> None:
    """Only what the front end declares changes, not the poses it makes (the drift stays the drift)."""
    a, b = DriftingOdometry(3, 0.003, 0.3, 0.05), DriftingOdometry(3, 0.003, 0.3, 0.05, bias_horizon_frames=100)
    gt = np.eye(4)
    for i in range(50):
        gt = gt @ np.array([[1, 0, 0, 0.01], [0, 1, 0, 0], [0, 0, 1, 0.005], [0, 0, 0, 1.0]])
        assert np.array_equal(a.estimate(OdometryInput(i, i / 30, gt)), b.estimate(OdometryInput(i, i / 30, gt)))

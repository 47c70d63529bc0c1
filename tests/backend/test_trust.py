"""The trust the odometry earns from the loop closures that witness it (semmap/algorithms/backend/trust.py)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from semmap.algorithms.backend.trust import OdometryTrust

CLOSURE = (0.01, np.radians(0.5))  # what a closure declares


def _offset(rng: np.random.Generator, sigma_m: float, sigma_rad: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, sigma_rad, 3)).as_matrix()
    T[:3, 3] = rng.normal(0.0, sigma_m, 3)
    return T


def _witnesses(trust: OdometryTrust, n: int, drift_per_frame: float, closure_noise: float, seed: int = 0) -> None:
    """Closures over gaps of 100-600 frames of an odometry declaring 1 cm / 0.5 deg a frame, whose real error
    over a gap is a random walk of `drift_per_frame` (m, and the same share in rotation), measured by closures
    with `closure_noise` (m)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        gap = int(rng.integers(100, 600))
        chain = (0.01 * np.sqrt(gap), np.radians(0.5) * np.sqrt(gap))
        drift = drift_per_frame * np.sqrt(gap)
        odometry = _offset(rng, drift, drift_per_frame / 0.01 * np.radians(0.5) * np.sqrt(gap))
        measured = _offset(rng, closure_noise, closure_noise / 0.01 * np.radians(0.5))
        trust.witness(odometry, measured, chain, CLOSURE)


def test_no_trust_is_earned_before_enough_witnesses():
    trust = OdometryTrust()
    _witnesses(trust, 2, 0.0, 0.01)
    assert trust.factors() == (1.0, 1.0)


def test_a_slam_that_agrees_with_every_closure_within_its_noise_is_trusted_to_the_floor():
    """A good SLAM (no drift beyond the closures' own noise): its chain is as tight as the floor allows, so
    evidence that only agrees with it within its noise cannot bend it."""
    for n in (4, 20):
        trust = OdometryTrust()
        _witnesses(trust, n, 0.0, 0.01)
        assert trust.factors() == (trust.floor, trust.floor), n


def test_a_drifting_odometry_keeps_its_declared_sigmas():
    """An odometry that really drifts as much as it declares (1 cm a frame, a random walk) earns nothing: the
    closures keep their full pull."""
    trust = OdometryTrust()
    _witnesses(trust, 20, 0.01, 0.01)
    t, r = trust.factors()
    assert t > 0.6 and r > 0.6


def test_the_closures_own_noise_is_measured_once_there_are_enough():
    """Closures noisier than declared (3 cm, not 1): from `regression_witnesses` on their sigma follows what they
    showed, never below the declared one."""
    trust = OdometryTrust()
    _witnesses(trust, 6, 0.0, 0.03)
    assert trust.closure_sigmas(CLOSURE) == CLOSURE
    _witnesses(trust, 20, 0.0, 0.03, seed=1)
    sigma_t, _ = trust.closure_sigmas(CLOSURE)
    assert 0.02 < sigma_t < 0.045
    quiet = OdometryTrust()
    _witnesses(quiet, 20, 0.0, 0.002)
    assert quiet.closure_sigmas(CLOSURE) == CLOSURE


def test_state_restores_the_same_factors():
    trust = OdometryTrust()
    _witnesses(trust, 12, 0.002, 0.01)
    again = OdometryTrust()
    again.restore(trust.state())
    assert again.factors() == trust.factors()

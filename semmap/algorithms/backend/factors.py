"""GTSAM factor builders for the backend: odometry, priors, landmark observations, merges, relative poses.

Why a module of its own: the pose graph's bookkeeping (which frame is a node, which factor replaces which) is
independent of how one measurement becomes a factor, and the noise models are the part people tune.

Conventions: GTSAM's Pose3 tangent is [rotation (rad) x3, translation (m) x3]; poses are camera-to-world.
"""

from __future__ import annotations

from typing import get_args

import gtsam
import numpy as np

from semmap.core.config.sections import RobustKernel

ROBUST_KERNELS: tuple[str, ...] = get_args(RobustKernel)


def pose3(matrix: np.ndarray) -> gtsam.Pose3:
    """A gtsam Pose3 from a 4x4 (the rotation block is re-orthonormalised so drifted inputs stay valid)."""
    m = np.asarray(matrix, dtype=np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        u[:, -1] *= -1.0
        rot = u @ vt
    return gtsam.Pose3(gtsam.Rot3(rot), m[:3, 3].copy())


def pose_sigmas(sigma_translation: float, sigma_rotation: float) -> np.ndarray:
    """Diagonal Pose3 sigmas in GTSAM's tangent order (rotation first)."""
    return np.array([sigma_rotation] * 3 + [sigma_translation] * 3, dtype=np.float64)


def m_estimator(kernel: str, k: float) -> gtsam.noiseModel.mEstimator.Base | None:
    """GTSAM's M-estimator for a kernel name (None for "none")."""
    kernel = kernel.lower()
    if kernel == "none":
        return None
    if kernel == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(k)
    if kernel == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    raise ValueError(f"unknown robust kernel {kernel!r}: use one of {', '.join(ROBUST_KERNELS)}")


def robust(base: gtsam.noiseModel.Base, kernel: str, k: float) -> gtsam.noiseModel.Base:
    """Wrap a Gaussian model in an M-estimator: one wrong association then pulls with bounded force."""
    estimator = m_estimator(kernel, k)
    return base if estimator is None else gtsam.noiseModel.Robust.Create(estimator, base)


def robust_weight(kernel: str, k: float, residual: float) -> float:
    """The M-estimator's weight at a whitened residual (what iSAM2 gives that factor when it linearises)."""
    estimator = m_estimator(kernel, k)
    return 1.0 if estimator is None else float(estimator.weight(residual))


def prior_factor(key: int, pose: np.ndarray, sigma_translation: float, sigma_rotation: float,
                 kernel: str = "none", k: float = 1.345) -> gtsam.NonlinearFactor:
    noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas(sigma_translation, sigma_rotation))
    return gtsam.PriorFactorPose3(key, pose3(pose), robust(noise, kernel, k))


def between_factor(key_a: int, key_b: int, relative: np.ndarray, sigma_translation: float, sigma_rotation: float,
                   kernel: str = "none", k: float = 1.345) -> gtsam.NonlinearFactor:
    """BetweenFactorPose3 measuring pose_b expressed in frame a (`inv(T_a) @ T_b`)."""
    noise = gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas(sigma_translation, sigma_rotation))
    return gtsam.BetweenFactorPose3(key_a, key_b, pose3(relative), robust(noise, kernel, k))


def observation_factor(pose_key: int, point_key: int, point_camera: np.ndarray, sigma: float, kernel: str,
                       k: float, range_sigma: float | None = None) -> gtsam.NonlinearFactor:
    """A camera-frame 3D point as a native `BearingRangeFactor3D` (no Python callback: fast in iSAM2).

    An isotropic sigma at range r is a bearing sigma of sigma / r rad (small-angle) and a range sigma of sigma,
    which is the same Gaussian to first order as a point-to-point factor. `range_sigma` (never below `sigma`)
    loosens the range alone: an object's visible surface lies in front of its centre along the ray, by up to its
    depth, while the bearing to it is hardly biased (`observation_information`).
    """
    p = np.asarray(point_camera, dtype=np.float64)
    rng = float(np.linalg.norm(p))
    bearing_sigma = sigma / rng
    range_sigma = sigma if range_sigma is None else max(float(range_sigma), sigma)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([bearing_sigma, bearing_sigma, range_sigma]))
    return gtsam.BearingRangeFactor3D(pose_key, point_key, gtsam.Unit3(p / rng), rng, robust(noise, kernel, k))


def observation_information(ray_world: np.ndarray, sigma: float, range_sigma: float) -> np.ndarray:
    """The 3x3 information of an `observation_factor` in the world frame (first order): 1 / sigma^2 across the
    ray, 1 / range_sigma^2 along it (`ray_world`, any length)."""
    u = np.asarray(ray_world, dtype=np.float64)
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    along = np.outer(u, u)
    return (np.eye(3) - along) / sigma**2 + along / max(range_sigma, sigma) ** 2


def merge_factor(key_a: int, key_b: int, sigma: float) -> gtsam.NonlinearFactor:
    """Two landmark variables that are one object: a zero BetweenFactorPoint3 (Gaussian, not robust).

    Not robust on purpose: a merge of two copies of one object seen before and after drift is a loop closure and
    must pull with its full weight; the associator owns the decision.
    """
    return gtsam.BetweenFactorPoint3(key_a, key_b, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def point_prior_factor(key: int, point: np.ndarray, sigma: float | np.ndarray) -> gtsam.NonlinearFactor:
    """A landmark variable held near `point`: what keeps a retired landmark (its observation factors dropped)
    determined without it pulling any pose. `sigma`: isotropic (m), or a 3x3 information matrix."""
    if np.ndim(sigma) == 2:
        noise = gtsam.noiseModel.Gaussian.Information(np.asarray(sigma, dtype=np.float64))
    else:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, float(sigma))
    return gtsam.PriorFactorPoint3(key, np.asarray(point, dtype=np.float64), noise)

"""Small vectorised point-cloud helpers shared by the associator modules (no Python loops over points)."""

from __future__ import annotations

import numpy as np

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1


def transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N,3) points (or one (3,) point)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def inverse_transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the inverse of a 4x4 rigid transform to (N,3) points (or one (3,) point)."""
    return (points - pose[:3, 3]) @ pose[:3, :3]


def _quantiles(points: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """Per-column quantiles (percent), linearly interpolated like np.percentile, via one partition."""
    n = len(points)
    pos = np.array(qs) / 100.0 * (n - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    part = np.partition(points, np.unique(np.concatenate([lo, hi])), axis=0)
    frac = (pos - lo)[:, None]
    return part[lo] * (1.0 - frac) + part[hi] * frac


def fast_median(points: np.ndarray) -> np.ndarray:
    """Per-column median of an (n, d) array (np.median's answer, a few times faster for small n)."""
    s = np.sort(points, axis=0)
    n = len(s)
    return s[n // 2].copy() if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def robust_box(points: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre, extent) of the axis-aligned box between the q and 100-q percentiles of each axis.

    The extent is divided by the share of a uniform distribution that those percentiles keep, so a
    uniformly covered object of length L reports L, not 0.9 L (for q = 5).
    """
    lo, hi = _quantiles(points, (q, 100.0 - q))
    return (lo + hi) / 2.0, (hi - lo) / (1.0 - 2.0 * q / 100.0)


def voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 key per point for its voxel (21 bits per axis: +-1e6 voxels, 20 km at 2 cm)."""
    cells = np.floor(points / voxel).astype(np.int64) + _KEY_OFFSET
    cells &= _KEY_MASK
    return (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]


def voxel_downsample(points: np.ndarray, voxel: float, max_points: int = 0) -> np.ndarray:
    """The mean point of every occupied voxel, in voxel-key order (deterministic); capped by thinning."""
    if len(points) == 0:
        return np.zeros((0, 3))
    keys = voxel_keys(points, voxel)
    uniq, inverse = np.unique(keys, return_inverse=True)
    counts = np.bincount(inverse, minlength=len(uniq)).astype(np.float64)
    out = np.empty((len(uniq), 3))
    for axis in range(3):
        out[:, axis] = np.bincount(inverse, weights=points[:, axis], minlength=len(uniq)) / counts
    if max_points and len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.int64)]
    return out


def thin(points: np.ndarray, max_points: int) -> np.ndarray:
    """A deterministic uniform subsample of at most max_points rows."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).astype(np.int64)]

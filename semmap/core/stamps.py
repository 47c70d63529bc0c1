"""Comparing differences of frame stamps with time settings, robust to float rounding on a frame grid.

Cameras stamp frames on a grid (7-Scenes: frame n at n/30 s; ROS headers: integer nanoseconds; TUM: Unix seconds
with microseconds). Settings often fall exactly on that grid: 0.5 s is 15 frames at 30 Hz, 1 s is 30. A difference
of two float stamps then lands a rounding error either side of the setting (15/30 - 0/30 == 0.5 but
(n+15)/30 - n/30 may read 0.49999999999999994 or 0.5000000000000001), so `dt > 0.5` flips with n, and the same
recording stamped in nanoseconds (a bag) takes other decisions than its folder. Every comparison of a stamp
difference with a setting goes through these helpers: a difference within STAMP_TOLERANCE_S of the setting counts
as equal to it.

STAMP_TOLERANCE_S = 10 microseconds: above every rounding of a stamp difference seen in recordings (float64 Unix
stamps near 1.7e9 s: 2.4e-7 s per stamp; a ROS header's half nanosecond; TUM files print Unix seconds with 6
decimals, so a difference of two is off by up to 1.1e-6 s), and far below any frame period (33 ms at 30 Hz; 1 ms at
1 kHz is still 100 times more). Algorithms only: no I/O here.
"""

from __future__ import annotations

import math

import numpy as np

STAMP_TOLERANCE_S = 1e-5


def exceeds(dt: float, limit_s: float) -> bool:
    """dt > limit_s, with dt within the tolerance of limit_s counted as equal (so not more)."""
    return dt > limit_s + STAMP_TOLERANCE_S


def reaches(dt: float, limit_s: float) -> bool:
    """dt >= limit_s, with dt within the tolerance of limit_s counted as equal (so reached)."""
    return dt >= limit_s - STAMP_TOLERANCE_S


def below(dt: float, limit_s: float) -> bool:
    """dt < limit_s, with dt within the tolerance of limit_s counted as equal (so not below): not reaches()."""
    return not reaches(dt, limit_s)


def within(dt: float, limit_s: float) -> bool:
    """dt <= limit_s, with dt within the tolerance of limit_s counted as equal (so within): not exceeds()."""
    return not exceeds(dt, limit_s)


def time_bins(dt: np.ndarray, bin_s: float) -> np.ndarray:
    """floor(dt / bin_s) as int64, a dt within the tolerance below a bin edge counted in the bin that starts there
    (15 frames at 30 Hz with 0.5 s bins: bin 1, whatever the rounding)."""
    if not bin_s > 0 or not math.isfinite(bin_s):
        raise ValueError(f"bin_s must be a positive finite number, got {bin_s}")
    return np.floor((np.asarray(dt, dtype=np.float64) + STAMP_TOLERANCE_S) / bin_s).astype(np.int64)

"""semmap.core.stamps: a stamp difference that is a whole number of frame periods compares equal to a setting of that
many periods, whatever float rounding did to the stamps (n/30 s, nanosecond ROS headers, Unix seconds)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from semmap.core.stamps import STAMP_TOLERANCE_S, below, exceeds, reaches, time_bins, within

T0 = 1311868164.0  # a TUM-like Unix time


def stamp(n: int, rate: float, source: str) -> float:
    """Frame n's stamp as each kind of recording writes it."""
    t = n / rate
    if source == "ns":  # a ROS header: integer nanoseconds
        return round(t * 1e9) / 1e9
    if source == "unix":
        return T0 + t
    if source == "unix_us":  # a TUM file: Unix seconds printed with 6 decimals
        return float(f"{T0 + t:.6f}")
    return t


SOURCES = ("plain", "ns", "unix", "unix_us")


def test_the_rounding_this_guards_against_happens() -> None:
    """Without a tolerance, 15 frames at 30 Hz is sometimes more and sometimes less than 0.5 s."""
    d = [(n + 15) / 30 - n / 30 for n in range(1000)]
    assert any(x > 0.5 for x in d) and any(x < 0.5 for x in d)


@pytest.mark.parametrize("source", SOURCES)
def test_15_frames_at_30_hz_is_exactly_half_a_second_for_every_start(source: str) -> None:
    for n in range(3000):
        dt = stamp(n + 15, 30.0, source) - stamp(n, 30.0, source)
        assert not exceeds(dt, 0.5) and reaches(dt, 0.5) and within(dt, 0.5) and not below(dt, 0.5), (n, dt)
        one_more = stamp(n + 16, 30.0, source) - stamp(n, 30.0, source)
        one_less = stamp(n + 14, 30.0, source) - stamp(n, 30.0, source)
        assert exceeds(one_more, 0.5) and below(one_less, 0.5), n


@settings(max_examples=1000, deadline=None)
@given(
    n=st.integers(0, 2_000_000),
    k=st.integers(1, 600),
    rate=st.sampled_from([5.0, 10.0, 15.0, 25.0, 30.0, 60.0, 90.0]),
    source=st.sampled_from(SOURCES),
)
def test_k_frames_equal_a_setting_of_k_periods(n: int, k: int, rate: float, source: str) -> None:
    limit = k / rate
    dt = stamp(n + k, rate, source) - stamp(n, rate, source)
    assert not exceeds(dt, limit) and reaches(dt, limit)
    assert exceeds(stamp(n + k + 1, rate, source) - stamp(n, rate, source), limit)
    assert below(stamp(n + k - 1, rate, source) - stamp(n, rate, source), limit)
    # binned by the setting, frame n + k starts bin 1 and frame n + k - 1 is still in bin 0
    start = stamp(n, rate, source)
    bins = time_bins(np.array([stamp(n + k - 1, rate, source), stamp(n + k, rate, source)]) - start, limit)
    assert bins.tolist() == [0, 1]


def test_the_tolerance_is_far_below_any_frame_period_and_far_above_rounding() -> None:
    assert STAMP_TOLERANCE_S <= 1e-3 / 100  # 1 kHz still has 100x margin
    assert STAMP_TOLERANCE_S >= 4 * 1e-6  # microsecond-printed Unix stamps (TUM): a difference is off by <= 1.1 us
    assert exceeds(0.5 + 2 * STAMP_TOLERANCE_S, 0.5) and not exceeds(0.5 + 0.5 * STAMP_TOLERANCE_S, 0.5)
    assert below(0.5 - 2 * STAMP_TOLERANCE_S, 0.5) and not below(0.5 - 0.5 * STAMP_TOLERANCE_S, 0.5)


def test_time_bins_refuses_a_bad_bin() -> None:
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="bin_s"):
            time_bins(np.array([0.0]), bad)

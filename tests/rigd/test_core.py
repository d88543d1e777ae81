"""Core data types and the timebase at their extremes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rigd.core import ClockMap, EventArray, EventDataError, SyncError, TriggerEvents, fit_clock_map


def test_event_array_rejects_wrong_dtypes_and_lengths() -> None:
    with pytest.raises(EventDataError, match=r"EventArray\.t has dtype float64"):
        EventArray(
            np.zeros(2, np.uint16), np.zeros(2, np.uint16), np.ones(2, np.int8), np.zeros(2, np.float64)
        )  # type: ignore[arg-type]
    with pytest.raises(EventDataError, match="has 1 entries, expected 2"):
        EventArray(np.zeros(2, np.uint16), np.zeros(1, np.uint16), np.ones(2, np.int8), np.zeros(2, np.int64))


def test_from_arrays_checks_ranges_and_time_type() -> None:
    with pytest.raises(EventDataError, match="out of uint16 range"):
        EventArray.from_arrays([70000], [0], [1], [0])
    with pytest.raises(EventDataError, match="integer microseconds"):
        EventArray.from_arrays([0], [0], [1], [0.5])
    with pytest.raises(EventDataError, match="polarity"):
        EventArray.from_arrays([0], [0], [2], [0])
    ev = EventArray.from_arrays([1, 2], [3, 4], [0, 1], [10, 20])
    assert ev.p.tolist() == [-1, 1]
    assert len(EventArray.concatenate([ev, ev.with_time(ev.t + 100)])) == 4


def test_trigger_rising_filters_channel() -> None:
    tr = TriggerEvents(
        np.array([1, 2, 3], np.int64), np.array([1, 0, 1], np.uint8), np.array([0, 0, 1], np.uint8)
    )
    assert tr.rising(0).t.tolist() == [1]
    assert tr.rising().t.tolist() == [1, 3]


@given(
    ref=st.integers(0, 2**40),
    ppm=st.floats(-1000, 1000),
    frac=st.floats(-0.5, 0.5),
)
def test_clock_map_round_trip_within_a_microsecond(ref: int, ppm: float, frac: float) -> None:
    cmap = ClockMap(ref, 5 * ref // 3, 1.0 + ppm * 1e-6, frac)
    t = ref + np.array([0, 1, 10**6, 3_600 * 10**6, 10 * 3_600 * 10**6], np.int64)
    back = cmap.to_device(cmap.to_rig(t))
    assert np.abs(back - t).max() <= 1


def test_ten_hour_fit_keeps_sub_microsecond_precision() -> None:
    # Timestamps near 2^40 us (12.7 days of uptime), 10 h span: float32 would lose seconds.
    d = (2**40 + np.arange(0, 36_000 * 10**6, 33_333, dtype=np.int64))[::100]
    exact = 123_456_789.25 + (d - d[0]) * (1 - 73e-6)
    fit = fit_clock_map(d, np.rint(exact).astype(np.int64))
    assert fit.rms_us < 0.35  # the rounding of the rig times, nothing more
    err = fit.map.to_rig_float(d) - exact
    assert np.abs(err).max() < 0.05
    assert fit.map.drift_ppm == pytest.approx((1 / (1 - 73e-6) - 1) * 1e6, abs=1e-3)


def test_fit_degenerate_inputs() -> None:
    with pytest.raises(SyncError, match="zero matched pulses"):
        fit_clock_map(np.empty(0, np.int64), np.empty(0, np.int64))
    one = fit_clock_map(np.array([100], np.int64), np.array([5000], np.int64))
    assert one.map.rate == 1.0
    assert one.map.to_rig([100]).tolist() == [5000]
    same = fit_clock_map(np.array([7, 7], np.int64), np.array([9, 11], np.int64))
    assert same.map.rate == 1.0

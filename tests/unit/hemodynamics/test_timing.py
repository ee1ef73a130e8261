"""Frame times from classic and enhanced XA headers; a run without timing is refused, naming the view."""

from __future__ import annotations

import numpy as np
import pytest
from pydicom.dataset import Dataset

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.hemodynamics.timing import (parse_datetime, parse_time_s, read_timing, require_timing,
                                               run_offset_s)


def test_frame_time_gives_regular_times_and_the_start():
    ds = Dataset()
    ds.FrameTime = "250"
    ds.AcquisitionDate, ds.AcquisitionTime = "20240102", "101500.5"
    timing = read_timing(ds, 5)
    assert timing.source == "FrameTime"
    np.testing.assert_allclose(timing.times_s, [0.0, 0.25, 0.5, 0.75, 1.0])
    assert timing.start.isoformat() == "2024-01-02T10:15:00.500000"


def test_frame_time_vector_is_cumulative_and_wins_over_frame_time():
    ds = Dataset()
    ds.FrameTimeVector = [0, 500, 500, 133.3]
    ds.FrameTime = "999"
    timing = read_timing(ds, 4)
    assert timing.source == "FrameTimeVector"
    np.testing.assert_allclose(timing.times_s, [0.0, 0.5, 1.0, 1.1333])


def test_cine_rate():
    ds = Dataset()
    ds.CineRate = 4
    np.testing.assert_allclose(read_timing(ds, 3).times_s, [0.0, 0.25, 0.5])


def test_enhanced_per_frame_datetimes_and_the_offset_between_runs():
    def enhanced(start_s: float, step_s: float, n: int) -> Dataset:
        ds = Dataset()
        groups = []
        for k in range(n):
            content = Dataset()
            seconds = start_s + k * step_s
            content.FrameAcquisitionDateTime = f"20240102101{int(seconds // 10)}{seconds % 10:09.6f}"
            group = Dataset()
            group.FrameContentSequence = [content]
            groups.append(group)
        ds.PerFrameFunctionalGroupsSequence = groups
        return ds

    ap, lat = read_timing(enhanced(0.0, 0.5, 4), 4), read_timing(enhanced(1.25, 0.5, 4), 4)
    assert ap.source == "FrameAcquisitionDateTime"
    np.testing.assert_allclose(ap.times_s, [0.0, 0.5, 1.0, 1.5])
    offset, how = run_offset_s(ap, lat)
    assert offset == pytest.approx(1.25) and "start times" in how


def test_a_run_without_timing_or_a_single_frame_is_refused_naming_the_view():
    assert read_timing(Dataset(), 10) is None
    with pytest.raises(DsaregInputError) as caught:
        require_timing(None, 10, "lat")
    assert caught.value.field == "lat" and "without frame timing" in str(caught.value)
    assert "Frame Time" in caught.value.accepted
    with pytest.raises(DsaregInputError, match="still image"):
        require_timing(read_timing(Dataset(), 1), 1, "ap")


def test_times_that_do_not_increase_are_an_input_error():
    ds = Dataset()
    ds.FrameTimeVector = [0, 100, -200]
    with pytest.raises(DsaregInputError, match="do not increase"):
        read_timing(ds, 3, "ap")


def test_dicom_date_and_time_parsing():
    assert parse_time_s("101500.25") == pytest.approx(36900.25)
    assert parse_time_s("10:15:00") == pytest.approx(36900.0)
    assert parse_time_s("garbage") is None
    assert parse_datetime("20240102101500.5+0100").isoformat() == "2024-01-02T10:15:00.500000"

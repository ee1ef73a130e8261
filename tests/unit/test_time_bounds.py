"""tests/support/time_bounds.py: the timed tests' bounds stretch with the neighbours' load, never on a quiet core."""

from __future__ import annotations

import threading

import pytest

from tests.support import time_bounds


def test_a_quiet_share_moves_no_bound_and_a_busy_one_stretches_them_up_to_the_cap():
    assert time_bounds.factor_for(1.0) == 1.0
    assert time_bounds.factor_for(time_bounds.QUIET_SHARE) == 1.0
    assert time_bounds.factor_for(0.5) == pytest.approx(2.0)
    assert time_bounds.factor_for(0.01) == time_bounds.MAX_FACTOR


def test_the_probe_sees_a_thread_that_takes_half_the_core(monkeypatch):
    monkeypatch.delenv("DSAREG_TEST_TIME_FACTOR", raising=False)
    stop = threading.Event()

    def hog() -> None:  # a second Python thread: the GIL leaves the probe about half of the time
        while not stop.is_set():
            sum(range(2000))

    thread = threading.Thread(target=hog)
    thread.start()
    try:
        share = time_bounds.probe_core_share(0.4)
    finally:
        stop.set()
        thread.join()
    assert share < time_bounds.QUIET_SHARE, share
    assert time_bounds.factor_for(share) > 1.0


def test_allowed_scales_by_the_measured_factor_and_the_setting_fixes_it(monkeypatch):
    monkeypatch.setenv("DSAREG_TEST_TIME_FACTOR", "3")
    try:
        assert time_bounds.measure() == 3.0
        assert time_bounds.allowed(2.0) == 6.0
        monkeypatch.setenv("DSAREG_TEST_TIME_FACTOR", "0.5")  # never below the quiet bound
        assert time_bounds.measure() == 1.0 and time_bounds.allowed(2.0) == 2.0
    finally:
        monkeypatch.setenv("DSAREG_TEST_TIME_FACTOR", "1")
        time_bounds.measure()

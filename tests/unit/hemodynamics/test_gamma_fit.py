"""The gamma-variate fit against curves whose first moment and area are known in closed form."""

from __future__ import annotations

import math

import numpy as np

from dsareg_engine.hemodynamics.gamma_fit import gamma_variate
from dsareg_engine.hemodynamics.parameters import curve_parameters


def _gamma(times, onset, alpha, beta, k):
    tau = np.maximum(times - onset, 0.0)
    return np.where(times > onset, k * tau ** alpha * np.exp(-tau / beta), 0.0)


def test_mtt_and_area_of_sampled_gamma_variates_with_a_recirculation_tail():
    """MTT = (α + 1) β and area = K β^(α+1) Γ(α+1) by the integrals of the gamma density; sampled at 4 fps with
    noise and a late second pass (recirculation) that the first-pass window leaves out."""
    times = np.arange(40) / 4.0
    rng = np.random.default_rng(0)
    truth = [(1.3, 3.0, 0.5, 1.0), (2.1, 2.0, 0.9, 0.6), (0.8, 4.0, 0.35, 2.0), (3.0, 2.5, 0.7, 0.8)]
    curves = np.array([_gamma(times, *p) + 0.15 * _gamma(times, p[0] + 6.0, 2.0, 1.0, p[3] * 0.3)
                       for p in truth]) + rng.normal(0.0, 0.001, (len(truth), len(times)))
    found = curve_parameters(curves, times, np.full(len(truth), 0.001), np.ones(len(truth)), np.ones(len(truth), bool))
    peaks = found.peak_opacity
    mtt, area = gamma_variate(times, curves, found.arrival_s, found.peak_s, peaks)
    for (onset, alpha, beta, k), m, a in zip(truth, mtt, area):
        assert abs(m - (alpha + 1) * beta) < 0.1 * (alpha + 1) * beta, (m, (alpha + 1) * beta)
        expected = k * beta ** (alpha + 1) * math.gamma(alpha + 1)
        assert abs(a - expected) < 0.1 * expected, (a, expected)


def test_no_values_where_the_curve_never_filled():
    times = np.arange(20) / 4.0
    mtt, area = gamma_variate(times, np.zeros((2, 20)), np.full(2, np.nan), np.full(2, np.nan), np.full(2, np.nan))
    assert np.isnan(mtt).all() and np.isnan(area).all()


def test_no_values_where_the_run_ends_before_the_bolus_has_half_passed():
    """A 2.25 s run gave mtt_s 6.08 s: the fit's tail beyond the last frame is a guess. The same bolus seen
    long enough gives its values; cut before its mean time (onset + MTT), none."""
    onset, alpha, beta, k = 0.5, 3.0, 0.9, 1.0  # MTT 3.6 s: mean time 4.1 s
    values = []
    for frames in (40, 10):  # 10 s, then 2.25 s at 4 fps
        times = np.arange(frames) / 4.0
        curves = _gamma(times, onset, alpha, beta, k)[None]
        found = curve_parameters(curves, times, np.full(1, 0.001), np.ones(1), np.ones(1, bool))
        values.append(gamma_variate(times, curves, found.arrival_s, found.peak_s, found.peak_opacity))
    (long_mtt, _), (short_mtt, short_area) = values
    assert abs(long_mtt[0] - (alpha + 1) * beta) < 0.1 * (alpha + 1) * beta
    assert np.isnan(short_mtt[0]) and np.isnan(short_area[0]), (short_mtt, short_area)


def test_no_values_where_the_fitted_bolus_starts_before_the_run():
    """A run that began after the contrast did: the fit's onset lies before the first frame, its values a guess."""
    times = np.arange(24) / 4.0
    curves = _gamma(times, -0.3, 3.0, 0.5, 1.0)[None]  # 9 % of its peak at the first frame
    found = curve_parameters(curves, times, np.full(1, 0.001), np.ones(1), np.ones(1, bool))
    assert np.isfinite(found.arrival_s[0])
    mtt, area = gamma_variate(times, curves, found.arrival_s, found.peak_s, found.peak_opacity)
    assert np.isnan(mtt[0]) and np.isnan(area[0]), (mtt, area)

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

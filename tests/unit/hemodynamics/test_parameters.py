"""Arrival and peak from sampled curves against the analytic curve; a curve that never rises is not filled."""

from __future__ import annotations

import numpy as np

from dsareg_engine.hemodynamics.parameters import curve_parameters, footprint_noise, mean_noise


def gamma_variate(t: np.ndarray, start: float, peak_after: float, alpha: float = 3.0) -> np.ndarray:
    tau = np.clip((t - start) / peak_after, 0.0, None)
    return tau ** alpha * np.exp(alpha * (1.0 - tau))


def half_rise_exact(start: float, peak_after: float, alpha: float = 3.0) -> float:
    fine = np.linspace(start, start + peak_after, 200001)
    return float(fine[np.argmax(gamma_variate(fine, start, peak_after, alpha) >= 0.5)])


def test_arrival_and_peak_within_a_fraction_of_a_frame_at_2_4_and_7_5_fps():
    rng = np.random.default_rng(0)
    for fps in (2.0, 4.0, 7.5):
        times = np.arange(0.0, 12.0, 1.0 / fps)
        starts = rng.uniform(1.0, 4.0, 200)
        peaks = rng.uniform(1.2, 2.5, 200)
        curves = np.stack([gamma_variate(times, s, p) for s, p in zip(starts, peaks)])
        result = curve_parameters(curves, times, np.full(200, 0.01), np.ones(200), np.ones(200, bool))
        assert result.filled.all()
        truth = np.array([half_rise_exact(s, p) for s, p in zip(starts, peaks)])
        frame = 1.0 / fps
        arrival_error = np.abs(result.arrival_s - truth)
        assert np.median(arrival_error) <= 0.5 * frame and np.percentile(arrival_error, 90) <= 2 * frame
        assert np.median(np.abs(result.peak_s - (starts + peaks))) <= 0.5 * frame
        np.testing.assert_allclose(result.peak_opacity, 1.0, atol=0.15)


def test_noise_alone_and_a_faint_partial_curve_are_not_filled():
    rng = np.random.default_rng(1)
    times = np.arange(0.0, 8.0, 0.25)
    noise = 0.02
    filled = gamma_variate(times, 2.0, 1.5)
    curves = np.stack([filled, rng.normal(0.0, noise, len(times)), 0.2 * filled, filled * 0.9])
    curves[[0, 2, 3]] += rng.normal(0.0, noise, (3, len(times)))
    result = curve_parameters(curves, times, np.full(4, noise), np.ones(4), np.ones(4, bool))
    assert result.filled.tolist() == [True, False, False, True]
    assert np.isnan(result.arrival_s[1]) and np.isnan(result.peak_s[2])


def test_footprint_noise_falls_with_the_footprint_size():
    rng = np.random.default_rng(2)
    stack = rng.normal(0.0, 0.1, (6, 128, 128)).astype(np.float32)
    levels = footprint_noise(stack, np.ones((128, 128), bool), np.array([1.0, 2.0, 6.0]))
    assert levels[0] > levels[1] > levels[2]
    assert abs(levels[0] - 0.1 / np.sqrt(5)) < 0.006  # a disc of radius 1 holds 5 pixels
    assert abs(levels[2] - 0.1 / np.sqrt(113)) < 0.004  # a disc of radius 6 holds 113 pixels


def test_the_noise_of_a_mean_follows_its_pixel_count_down_to_one_pixel():
    """A footprint of a few pixels (a thin vessel's) is as noisy as its pixel count says, not as a radius-1 disc."""
    rng = np.random.default_rng(3)
    stack = rng.normal(0.0, 0.1, (6, 128, 128)).astype(np.float32)
    one, two, five, many = mean_noise(stack, np.ones((128, 128), bool), np.array([1.0, 2.0, 5.0, 113.0]))
    assert abs(one - 0.1) < 0.01 and abs(five - 0.1 / np.sqrt(5)) < 0.006 and abs(many - 0.1 / np.sqrt(113)) < 0.004
    assert one > two > five

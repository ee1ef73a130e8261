"""The frames a native run's DSA image is made of: by default the whole arterial phase of a passing bolus."""

from __future__ import annotations

import numpy as np
import pytest

from dsareg_engine.io.image_io import read_image
from dsareg_engine.io.xa_frames import END_FRACTION, TEMPORAL_FRAMES, arterial_phase, choose_frames, combine
from dsareg_engine.io.xa_run import RunReading
from dsareg_engine.simulation.native_run import IODINE_PER_MM
from dsareg_engine.simulation.native_run_bolus import Bolus
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run


def test_phase_ends_below_the_fraction_or_where_opacification_rises_again():
    falling = {3: 10.0, 4: 40.0, 5: 100.0, 6: 70.0, 7: 40.0, 8: 20.0, 9: 5.0}
    first, peak, last, why, after = arterial_phase(falling)
    assert (first, peak, last) == (4, 5, 7) and after == pytest.approx(0.2) and "below" in why
    venous = {3: 10.0, 4: 40.0, 5: 100.0, 6: 60.0, 7: 50.0, 8: 70.0, 9: 80.0}
    assert arterial_phase(venous)[2] == 7 and "rises again" in arterial_phase(venous)[3]
    choice = choose_frames(falling, None, 12, "ap")
    assert choice.combined == "arterial" and choice.frames == [4, 5, 6, 7] and choice.geometry_frame == 5
    assert choice.decision.what == "frames combined" and choice.decision.threshold == END_FRACTION
    assert choose_frames(falling, 6, 12, "ap").frames == [6]


@pytest.fixture(scope="module")
def passing():
    """4 frames/s, contrast reaching the far branches 1.5 s after the root, each pixel's bolus peaking 0.75 s
    after its arrival: the root has washed out before the far branches peak."""
    return make_skull_run(2, SkullRunSettings(size_px=128, bolus=Bolus()))


def _least_filled(pixels: np.ndarray, vessels: np.ndarray) -> float:
    """The 10th percentile over the tree's pixels (path > 0.5 mm) of darkening / full-strength iodine attenuation:
    low where part of the tree is shown before its bolus peaks or after it washed out."""
    tree = vessels > 0.5
    return float(np.percentile((np.median(pixels[vessels == 0]) - pixels[tree]) / (IODINE_PER_MM * vessels[tree]), 10))


def test_default_combines_the_arterial_phase_of_a_passing_bolus(passing):
    image = read_image(passing.files["ap"], "ap.dcm", field_name="ap")
    record = image.reading
    assert record["combined"] == "arterial" and record["frame_index"] == passing.peak_frame
    assert record["frame_indices"][0] < passing.peak_frame < record["frame_indices"][-1]
    assert record["mask_frame_indices"] == list(passing.mask_frames)
    peak = read_image(passing.files["ap"], "ap.dcm", reading=RunReading(frame=passing.peak_frame))
    whole = _least_filled(image.pixels, passing.vessels["ap"])
    single = _least_filled(peak.pixels, passing.vessels["ap"])
    assert whole > single + 0.1, (whole, single)
    decision = next(d for d in image.decisions if d.what == "frames combined")
    assert decision.source == "measured" and decision.chosen.endswith("(arterial phase)")


@pytest.mark.parametrize("n_frames", [1, 2, TEMPORAL_FRAMES, 9])
def test_arterial_combination_is_the_minimum_of_the_running_means(n_frames):
    frames = [np.random.default_rng(n).normal(0.0, 50.0, (16, 12)).astype(np.float32) for n in range(n_frames)]
    if n_frames == 1:
        expected = frames[0]
    elif n_frames < TEMPORAL_FRAMES:
        expected = np.minimum(*frames)
    else:  # every window of TEMPORAL_FRAMES consecutive frames averaged, then the per-pixel minimum
        windows = [np.mean(frames[k:k + TEMPORAL_FRAMES], axis=0) for k in range(n_frames - TEMPORAL_FRAMES + 1)]
        expected = np.min(windows, axis=0)
    combined = combine(frames, "arterial")
    assert combined.dtype == np.float32 and combined.shape == (16, 12)
    assert np.abs(combined - expected).max() < 1e-4
    assert np.array_equal(combine(frames, "minip"), np.min(frames, axis=0))

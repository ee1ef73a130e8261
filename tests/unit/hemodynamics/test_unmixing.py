"""Unmixing's plausibility test: an unmixed curve must peak inside the run's contrast phase."""

from __future__ import annotations

import numpy as np

from dsareg_engine.hemodynamics.parameters import curve_parameters
from dsareg_engine.hemodynamics.unmixing import within_run


def test_an_unmixed_curve_peaking_before_the_run_filled_or_at_its_end_is_not_filled():
    """Three filled-looking curves: a bolus peaking mid-run (kept), a residue peaking at 1 s while contrast reached
    the run at 2 s, a ramp still rising at the last frame (both dropped, every value null)."""
    times = np.arange(32) / 4.0
    bolus = np.exp(-0.5 * ((times - 4.0) / 0.8) ** 2)
    early = np.exp(-0.5 * ((times - 1.0) / 0.4) ** 2)
    rising = np.clip((times - 5.0) / 2.5, 0.0, None)
    curves = np.array([bolus, early, rising])
    found = curve_parameters(curves, times, np.full(3, 0.01), np.ones(3), np.ones(3, bool), typical_per_mm=1.0,
                             gamma_fit=True)
    assert found.filled.all()
    kept = within_run(found, times, run_arrival_s=2.0)
    assert kept.filled.tolist() == [True, False, False]
    assert np.isfinite(kept.arrival_s[0]) and np.isfinite(kept.mtt_s[0])
    for name in ("arrival_s", "peak_s", "peak_opacity", "mtt_s", "area"):
        assert np.isnan(getattr(kept, name)[1:]).all(), name


def test_an_unmixed_point_among_vessel_points_a_clean_view_saw_empty_is_contradicted():
    """A chain of 12 points (edges i – i+1): 0–4 seen clean and empty, 7–11 seen clean and filled, 5 and 6 unmixed.
    Within 3 edges, point 5 sees 2, 3, 4 empty and 7, 8 filled (3 of 5 empty: contradicted); point 6 sees 3, 4
    empty and 7, 8, 9 filled (2 of 5: not)."""
    from dsareg_engine.hemodynamics.unmixing import empty_around

    edges = np.array([[i, i + 1] for i in range(11)])
    known = np.ones(12, bool)
    known[[5, 6]] = False
    known_empty = np.zeros(12, bool)
    known_empty[:5] = True
    contradicted = empty_around(edges, known_empty, known)
    assert contradicted[[0, 1, 2, 3, 4, 5]].all() and not contradicted[[6, 7, 8, 9, 10, 11]].any()


def test_a_measured_curve_is_valued_only_where_its_own_vessel_could_show_it():
    """Three measured curves, all significant: a bolus on a vessel whose footprint path is 2 mm (kept), a one-frame
    noise spike at 0.25 s while contrast reached the run at 2 s (dropped), the same bolus ten times higher than the
    0.05 mm of its own vessel in the footprint can show at 0.5 per mm (dropped: another vessel's contrast); the last
    one again with no own path known (kept: only the timing test applies)."""
    from dsareg_engine.hemodynamics.unmixing import measured_within_run

    times = np.arange(32) / 4.0
    bolus = np.exp(-0.5 * ((times - 4.0) / 0.8) ** 2)
    spike = np.where(np.arange(32) == 1, 1.0, 0.0)
    curves = np.array([bolus, spike, 0.25 * bolus])
    found = curve_parameters(curves, times, np.full(3, 0.01), np.ones(3), np.ones(3, bool), typical_per_mm=0.2)
    assert found.filled.all()
    kept = measured_within_run(found, times, 2.0, np.array([2.0, 2.0, 0.05]), scale=0.5)
    assert kept.filled.tolist() == [True, False, False]
    assert np.isnan(kept.arrival_s[1:]).all() and np.isfinite(kept.arrival_s[0])
    assert measured_within_run(found, times, 2.0, None, scale=0.5).filled.tolist() == [True, False, True]

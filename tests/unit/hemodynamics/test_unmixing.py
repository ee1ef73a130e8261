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

"""The parametric colour-coded maps (dsareg_engine/hemodynamics/parametric.py)."""

from __future__ import annotations


def test_the_map_is_black_off_the_vessels_where_a_region_is_noisier():
    """The AP map showed coloured speckles over the skull: one noise level for the whole run, while the regions
    behind more bone are noisier. Each region's own noise (frames before the contrast) keeps them black."""
    import numpy as np

    from dsareg_engine.hemodynamics.parametric import pixel_arrival

    rng = np.random.default_rng(4)
    frames, size = 9, 96
    sigma = np.where(np.arange(size)[None, :] < size // 2, 0.5, 3.0) * np.ones((size, 1))  # right half: 6x noisier
    vessel = np.zeros((size, size), bool)
    vessel[44:50, 8:88] = True  # across both halves
    fill = np.clip((np.arange(frames) - 3) / 2.0, 0.0, 1.0)  # contrast from frame 4 on
    opacity = fill[:, None, None] * 60.0 * vessel + rng.normal(0.0, 1.0, (frames, size, size)) * sigma
    arrival, _ = pixel_arrival(opacity.astype(np.float32), np.arange(frames) * 0.25)
    near = np.zeros_like(vessel)
    near[41:53, 5:91] = True  # the vessel and the smoothing's reach around it
    assert not np.isfinite(arrival[~near]).any(), int(np.isfinite(arrival[~near]).sum())
    assert np.isfinite(arrival[vessel]).mean() > 0.95

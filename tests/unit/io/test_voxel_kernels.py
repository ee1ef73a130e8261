"""The whole-box kernels (:mod:`dsareg_engine.io.voxel_kernels`) give the numpy steps' voxels; here the CTA's
plateau test (:func:`flat_at`) against :func:`dsareg_engine.io.volume_vessels._plateau`'s numpy path, at limits
equal to voxels' own gradient lengths (ties) and between float32 values. (The face step and the label map: through
``voxel_steps``' tests, run both ways.)"""

import numpy as np
import pytest


def _numpy_plateau(smooth, where, spacing, limit, monkeypatch):
    from dsareg_engine.io import volume_vessels

    monkeypatch.setattr("dsareg_engine.io.volume_kernels.kernels_here", lambda: False)
    try:
        return volume_vessels._plateau(smooth, where, spacing, limit)
    finally:
        monkeypatch.undo()


@pytest.mark.parametrize("order", ["C", "F"])
def test_the_plateau_is_the_numpy_paths(order, monkeypatch):
    from dsareg_engine.io import volume_vessels

    rng = np.random.default_rng(5)
    for n in range(40):
        shape = tuple(int(s) for s in rng.integers(1, 14, 3))
        smooth = np.asarray(rng.normal(300.0, 120.0, shape), np.float32, order=order)
        if n % 4 == 0:
            smooth = np.round(smooth / 50.0).astype(np.float32) * 50.0  # equal neighbours: exact zeros and repeats
        where = rng.random(shape) < 0.6
        spacing = np.array(rng.choice([0.3, 0.45, 0.5, 0.625, 1.1], 3))
        gradient = np.zeros(shape, np.float32)  # the plateau's gradient length: the neighbours clamped at the ends
        for axis, size in enumerate(shape):
            ahead = np.take(smooth, np.minimum(np.arange(size) + 1, size - 1), axis)
            behind = np.take(smooth, np.maximum(np.arange(size) - 1, 0), axis)
            gradient += ((ahead - behind) / (2.0 * spacing[axis])) ** 2
        gradient = np.sqrt(gradient)
        limits = [float(rng.choice(gradient.ravel())) for _ in range(3)] + [float(rng.uniform(0.0, 400.0))]
        limits += [float(np.nextafter(np.float32(limits[0]), np.float32(np.inf))), limits[0] * (1 + 1e-9)]
        for limit in limits:
            expected = _numpy_plateau(smooth, where, spacing, limit, monkeypatch)
            monkeypatch.setattr("dsareg_engine.io.volume_kernels.kernels_here", lambda: True)
            got = volume_vessels._plateau(smooth, where, spacing, limit)
            monkeypatch.undo()
            assert np.array_equal(got, expected), (shape, limit)

"""The search window: the mask's area kept, centred on its bounding box, pixels past the detector zero."""

from __future__ import annotations

import numpy as np

from dsareg_engine.geometry.rig import ViewGeometry
from dsareg_engine.registration.search.window import mask_extent_px, mask_window


def _view(width=400, height=300):
    world_to_view = np.eye(4)
    world_to_view[2, 3] = 700.0
    return ViewGeometry((width, height), (0.4, 0.4), 1100.0, (width / 2, height / 2), world_to_view)


def test_the_window_keeps_the_mask_area_and_centres_it():
    mask = np.zeros((300, 400), bool)
    mask[100:160, 120:200] = True  # 60 × 80 px, centre (159.5, 129.5)
    assert mask_extent_px(mask) == 80
    window = mask_window(_view(), mask, side_px=160.0, window_px=40.0, multiple=4)
    scale = window.level.width / 400
    assert window.coverage.shape == (40, 40) and scale == 0.25
    assert np.isclose(window.coverage.sum(), mask.sum() * scale**2, rtol=1e-5)
    rows, cols = np.indices(window.coverage.shape)
    centroid = np.array([(window.coverage * cols).sum(), (window.coverage * rows).sum()]) / window.coverage.sum()
    assert np.allclose(centroid, [19.5, 19.5], atol=0.5)  # the window centred on the mask
    # the window's own view: the principal point moved by the corner (the same ray lands on the same pixel)
    u0, v0 = window.level.principal_point_px
    assert np.allclose(window.view.principal_point_px, (u0 - window.corner_px[0], v0 - window.corner_px[1]))


def test_pixels_past_the_detector_edge_are_zero():
    mask = np.zeros((300, 400), bool)
    mask[0:20, 0:30] = True  # in the corner: the window reaches past the detector
    window = mask_window(_view(), mask, side_px=120.0, window_px=200.0)
    assert window.corner_px[0] < 0 and window.corner_px[1] < 0
    assert window.coverage[: -window.corner_px[1], :].sum() == 0 and window.coverage[:, : -window.corner_px[0]].sum() == 0
    assert np.isclose(window.coverage.sum(), mask.sum())

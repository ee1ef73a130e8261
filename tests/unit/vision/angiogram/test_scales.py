"""Vessels kept by shape across scales (issue 40's second site: 512² frames of a magnified field, trunks 10–25 px
wide at the working scale, wider than the network was trained on). The network reads the working image and the
image area-averaged by 2; the coarse reading's interior is kept where it continues a fine vessel
(:func:`dsareg_engine.vision.angiogram.learned.across_scales`)."""

import cv2
import numpy as np

from dsareg_engine.vision.angiogram.learned import ScaleReading, across_scales, load_network, vessel_probability
from dsareg_engine.vision.angiogram.vessel_mask import vessel_mask


def _wide_trunk(size: int = 384, seed: int = 0, trunk_px: int = 28):
    """An unsubtracted-looking image: a dark curved trunk ``trunk_px`` wide with four thin branches (3–5 px) on a
    textured background; ``(pixels, the trunk's lumen (its central half), the vessels, the branches)``."""
    rng = np.random.default_rng(seed)
    texture = cv2.resize(rng.normal(0, 1, (5, 5)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    t = np.linspace(0, 1, 60)
    axis = np.stack([size * (0.1 + 0.8 * t), size * (0.35 + 0.12 * np.sin(2.5 * t))], 1)
    polyline = [np.round(axis).astype(np.int32)]
    trunk = np.zeros((size, size), np.float32)
    cv2.polylines(trunk, polyline, False, 1.0, trunk_px, cv2.LINE_AA)
    branches = np.zeros_like(trunk)
    for start, angle in ((15, 1.0), (30, 1.3), (45, 0.8), (22, -2.0)):
        points = [axis[start]]
        for _ in range(25):
            angle += rng.normal(0, 0.1)
            points.append(points[-1] + 6 * np.array([np.cos(angle), np.sin(angle)]))
        cv2.polylines(branches, [np.round(np.array(points)).astype(np.int32)], False, 1.0, int(rng.integers(3, 6)),
                      cv2.LINE_AA)
    vessels = np.clip(cv2.GaussianBlur(np.maximum(trunk, branches), (0, 0), 1.0), 0, 1)
    pixels = (150 + 15 * texture) * (1 - 0.4 * vessels) + rng.normal(0, 3, (size, size))
    lumen = np.zeros_like(trunk)
    cv2.polylines(lumen, polyline, False, 1.0, trunk_px // 2)
    thin = (branches >= 0.5) & ~(cv2.dilate(trunk, np.ones((5, 5), np.uint8)) > 0)
    return np.clip(pixels, 0, 255).astype(np.float32), lumen > 0, vessels >= 0.5, thin


def test_a_wide_trunks_lumen_is_kept_with_its_thin_branches():
    """At the working scale alone the 28-px trunk is read as its two edges (lumen 2 % kept, before this change)."""
    pixels, lumen, vessels, thin = _wide_trunk()
    load_network()
    mask = vessel_mask(*vessel_probability(pixels))[0]
    assert mask[lumen].mean() >= 0.9
    assert mask[thin].mean() >= 0.7
    assert 2 * (mask & vessels).sum() / (mask.sum() + vessels.sum()) >= 0.85
    working_scale_only = vessel_mask(*vessel_probability(pixels, reading=None))[0]
    assert working_scale_only[lumen].mean() < 0.5


def test_the_coarse_reading_adds_only_the_interior_of_what_continues_a_fine_vessel():
    fine = np.zeros((64, 64), np.float32)
    coarse = np.zeros_like(fine)
    fine[10:30, 10:12] = fine[10:30, 22:24] = 0.9        # a wide vessel's two edges, read finely
    coarse[10:30, 10:24] = 0.8                            # its lumen, read coarsely
    coarse[45:60, 40:50] = 0.95                           # a coarse-only blob: no fine vessel to continue
    combined = across_scales(fine, coarse)
    assert (combined[15:25, 13:21] == np.float32(0.8)).all()
    assert (combined[45:60, 40:50] == 0).all()
    assert combined[9, 16] == 0 and combined[10, 16] == 0  # the coarse border (≤ 1 px inside) is not taken
    assert (across_scales(fine, coarse, ScaleReading(border_px=20)) == fine).all()

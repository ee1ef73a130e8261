"""benchmarks/engine/site_emulation.py: the emulated second site (main arteries kept, collimator bands where
drawn, deterministic with a seed), on tiny synthetic images (no ../shared/data)."""

from __future__ import annotations

import numpy as np

from benchmarks.engine.site_emulation import (
    SIDE_PX,
    Blade,
    collimate,
    collimated_field,
    draw_blades,
    main_arteries,
    second_site,
    transmission_map,
)


def _tree() -> np.ndarray:
    """A 120-px label: a thick trunk (11 px wide, rows 20-30) and a thin branch (3 px wide) leaving it."""
    label = np.zeros((120, 120), bool)
    label[20:31, 10:110] = True
    label[31:100, 59:62] = True
    return label


def test_main_arteries_keep_the_thick_trunk_and_drop_the_thin_branch():
    main = main_arteries(_tree())
    assert main[25, 20:100].all()  # the trunk, end to end but its rounded tips
    assert not main[45:100, 59:62].any()  # the thin branch, below where it leaves the trunk
    assert not (main & ~_tree()).any()  # a subset of the label


def test_the_collimator_bands_are_where_they_are_drawn():
    blades = [Blade("left", 40, 0.0, 4.0), Blade("bottom", 30, 0.5, 2.0)]
    transmission = transmission_map((200, 200), blades)
    assert np.allclose(transmission[100, :38], 0.0) and np.allclose(transmission[100, 42:], 1.0)
    assert np.allclose(transmission[:169, 100], 1.0) and np.allclose(transmission[171:, 100], 0.5)
    assert 0.0 < transmission[100, 40] < 1.0  # a soft edge
    inside = collimated_field((200, 200), blades)
    assert not inside[:, :40].any() and inside[:170, 40:].all() and not inside[170:].any()
    pixels = np.full((200, 200), 200.0, np.float32)
    image, (label,) = collimate(pixels, [np.ones((200, 200), bool)], blades)
    assert np.allclose(image[185, 100], 100.0) and image[100, 10] == 0.0
    assert not label[:, :38].any() and label[185, 100]  # nothing visible under the opaque blade, kept under the other


def test_the_blades_and_the_whole_transformation_are_seeded():
    for seed in range(20):
        blades = draw_blades(np.random.default_rng(seed))
        assert blades and all(0.03 * SIDE_PX - 1 <= b.width_px <= 0.15 * SIDE_PX + 1 for b in blades)
    rng = np.random.default_rng(3)
    pixels = rng.uniform(60, 200, (150, 150)).astype(np.float32)
    label = np.pad(_tree(), 15)
    first, again, other = (second_site("7", pixels, label, seed) for seed in (0, 0, 1))
    assert first.pixels.shape == (SIDE_PX, SIDE_PX) and first.label.shape == first.whole.shape == (SIDE_PX, SIDE_PX)
    assert np.array_equal(first.pixels, again.pixels) and np.array_equal(first.label, again.label)
    assert first.framing == again.framing and first.framing != other.framing
    assert all(np.array_equal(main_arteries(label), main_arteries(label)) for _ in range(3))  # its axis is seeded
    assert not (first.label & ~first.whole).any()

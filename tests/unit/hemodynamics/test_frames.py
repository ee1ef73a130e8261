"""A native run's frame stack as hemodynamics subtracts it: the same masks and the same rigid move as registration."""

from __future__ import annotations

import numpy as np

from dsareg_engine.hemodynamics.frames import run_frames
from dsareg_engine.io.image_io import read_image
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run


def test_a_native_run_with_a_turned_head_is_subtracted_as_registration_subtracted_it():
    """No recipe, three still mask frames, then the head turned 0.5° and moved (0.8, −0.5) px: registration's frame
    (its masks found on the ~1 mm grid, the rigid move found) and the hemodynamics stack's same frame are one image;
    a shift-only mask (what hemodynamics did before) leaves the turned skull's edges in."""
    fill = (0.0, 0.0, 0.0, 0.1, 0.3, 0.55, 0.8, 1.0, 1.2, 1.3)
    settings = SkullRunSettings(size_px=256, fill=fill, strength=(1.0,) * 10, mask_frames=(1, 2, 3),
                                motion_px=(0.8, -0.5), rotation_deg=0.5, recipe=False, catheter_mm=2.0)
    data = make_skull_run(1, settings).files["lat"]
    image = read_image(data, "lat.dcm", field_name="lat", frame=7)
    record = image.reading
    assert record["run"] == "native" and record["mask_frame_indices"] == [0, 1, 2] and record["frame_index"] == 7
    assert abs(record["mask_shift_px"]["rotation_deg"]) > 0.3
    frames = run_frames(data, "lat", record)
    assert frames.opacity.shape[0] == len(fill)
    difference = -frames.opacity[7] - image.pixels
    assert np.percentile(np.abs(difference), 99) < 0.02 * np.percentile(np.abs(image.pixels), 99)
    shifted_only = dict(record, mask_shift_px=dict(record["mask_shift_px"], rotation_deg=0.0))
    unturned = -run_frames(data, "lat", shifted_only).opacity[7] - image.pixels
    assert np.percentile(np.abs(unturned), 99) > 5 * np.percentile(np.abs(difference), 99)


def test_the_masks_registration_found_are_reused_and_give_the_stack_finding_them_again_gives():
    """No recipe: the stack built from registration's record (its masks, not found again) is the stack built by
    finding them again, to the bit; a record with a recipe (a list) or without masks is not taken for found masks."""
    from dsareg_engine.hemodynamics.frames import recorded_pairs

    fill = (0.0, 0.0, 0.0, 0.2, 0.6, 1.0, 1.2, 1.1)
    settings = SkullRunSettings(size_px=128, fill=fill, strength=(1.0,) * 8, mask_frames=(1, 2),
                                motion_px=(0.0, 0.0), rotation_deg=0.0, recipe=False, catheter_mm=2.0)
    data = make_skull_run(2, settings).files["ap"]
    record = read_image(data, "ap.dcm", field_name="ap", frame=6).reading
    pairs = recorded_pairs(record, len(fill))
    assert pairs is not None and min(pairs) == len(record["mask_frame_indices"])
    reused = run_frames(data, "ap", record).opacity
    found_again = run_frames(data, "ap", dict(record, mask_frame_indices=None)).opacity
    assert np.array_equal(reused, found_again)
    assert recorded_pairs(dict(record, recipe=["AVG_SUB"]), len(fill)) is None
    assert recorded_pairs(dict(record, mask_frame_indices=[1, 2]), len(fill)) is None

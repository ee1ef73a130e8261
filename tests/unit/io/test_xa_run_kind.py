"""Native or subtracted at a physical scale: a 1024-px native run without a recipe (skull, catheter, a small
rotation between mask and contrast) is native with a wide margin; the same run subtracted is not."""

from __future__ import annotations

import io

import numpy as np
import pydicom
import pytest

from dsareg_engine.io.xa_run import log_domain
from dsareg_engine.io.xa_run_kind import RunKindSettings, decide_run_kind
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run

FILL = (0.0, 0.0, 0.0, 0.1, 0.3, 0.55, 0.8, 1.0, 1.2, 1.3, 1.3, 1.3)
STRENGTH = (1.0,) * 9 + (0.95, 0.85, 0.7)


@pytest.fixture(scope="module")
def lateral():
    """The lateral run of a 12-frame, 3-mask, 12-bit LIN 1024² native run at 0.17 mm with no recipe."""
    settings = SkullRunSettings(size_px=1024, fill=FILL, strength=STRENGTH, mask_frames=(1, 2, 3), motion_px=(0.8, -0.5),
                                rotation_deg=0.5, recipe=False, catheter_mm=2.0)
    dataset = pydicom.dcmread(io.BytesIO(make_skull_run(0, settings).files["lat"]))
    assert "MaskSubtractionSequence" not in dataset and "RecommendedViewingMode" not in dataset
    return dataset, dataset.pixel_array.astype(np.float32)


def test_native_run_without_recipe_is_native_with_margin(lateral):
    dataset, stack = lateral
    kind, why, decision = decide_run_kind(dataset, stack, "lat")
    assert kind == "native" and "anatomy in every frame" in why
    assert decision.source == "measured" and decision.what == "run kind" and decision.input == "lat"
    assert decision.margin > 5 * decision.band and not decision.close


def test_the_same_run_subtracted_is_subtracted(lateral):
    dataset, stack = lateral
    logs, _, _ = log_domain(stack, dataset, "lat")
    subtracted = logs - logs[:3].mean(axis=0)  # what a C-arm stores: every frame minus the mask
    stored = np.round(2048.0 + 4000.0 * subtracted).astype(np.float32)
    kind, _, decision = decide_run_kind(dataset, stored, "lat")
    assert kind == "subtracted" and decision.measure < decision.threshold - decision.band


def test_measure_does_not_depend_on_pixel_size(lateral):
    """Halving the pixel count (2×2 sums, spacing doubled) leaves the measure within 25 %."""
    dataset, stack = lateral
    spacing = float(dataset.ImagerPixelSpacing[0])
    binned = stack.reshape(len(stack), 512, 2, 512, 2).sum(axis=(2, 4))
    coarse = pydicom.Dataset()
    coarse.ImagerPixelSpacing = [2 * spacing, 2 * spacing]
    _, _, fine = decide_run_kind(dataset, stack, "lat")
    _, _, half = decide_run_kind(coarse, binned, "lat")
    assert half.measure == pytest.approx(fine.measure, rel=0.25)
    assert RunKindSettings().threshold < half.measure


@pytest.mark.parametrize("operations, kind", [(["NONE"], "unsubtracted"), (["NONE", "NONE"], "unsubtracted"),
                                              (["NONE", "AVG_SUB"], "native"), (["TID"], "native"),
                                              (["REV_TID"], "native")])
def test_a_recipe_of_none_only_is_unsubtracted(operations, kind):
    """MaskOperation NONE (no subtraction) in every item: the frames are read as stored, told by the tag."""
    from pydicom.dataset import Dataset

    dataset = Dataset()
    dataset.MaskSubtractionSequence = [Dataset() for _ in operations]
    for item, operation in zip(dataset.MaskSubtractionSequence, operations):
        item.MaskOperation = operation
    chosen, why, decision = decide_run_kind(dataset, np.zeros((3, 8, 8), np.float32), "ap")
    assert chosen == kind and decision.chosen == kind and decision.source == "tag"
    assert ("NONE" in why) == (kind == "unsubtracted")

import numpy as np

from dsareg_engine.vision.segmentation import segment_vessels_and_choice
from dsareg_engine.vision.segmentation_choice import EXPLAINED_SHARE, is_mask_like, segmentation_decision
from tests.support.angiogram_images import unsubtracted_angiogram


def test_an_unsubtracted_angiogram_is_segmented_by_the_network(build):
    pixels, vessels, _ = unsubtracted_angiogram(seed=6)
    mask, choice = segment_vessels_and_choice(pixels, "auto")
    assert choice.method == "network"
    assert 2 * (mask & vessels).sum() / (mask.sum() + vessels.sum()) > 0.6
    decision = segmentation_decision("ap", choice)
    assert decision.chosen == "angiogram network" and decision.threshold == EXPLAINED_SHARE and not decision.close


def test_clean_dsa_keeps_the_sub_pixel_border_model(build):
    image, truth = build.dsa()
    mask, choice = segment_vessels_and_choice(image, "auto")
    assert choice.method == "dsa", choice.agreement


def test_mask_like_images_keep_the_old_path():
    mask = np.zeros((64, 64), np.float32)
    mask[20:30, :] = 255.0
    mask[19, :] = 128.0  # anti-aliased
    assert is_mask_like(mask)
    pixels, _, _ = unsubtracted_angiogram(seed=7)
    assert not is_mask_like(pixels)

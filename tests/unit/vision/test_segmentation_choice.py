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


def test_a_process_that_only_checks_inputs_runs_no_network():
    """The service's validator (issue 40): under its address-space limit torch's import would crash it."""
    from dsareg_engine.vision.angiogram import allow_network, segment_angiogram

    pixels, _, _ = unsubtracted_angiogram(seed=8)
    allow_network(False)
    try:
        assert segment_angiogram(pixels, method="network").method == "frangi"
        assert segment_vessels_and_choice(pixels, "auto")[1].method == "dsa"
    finally:
        allow_network(True)
    assert segment_angiogram(pixels, method="network").method == "network"


def test_without_the_network_no_torch_is_imported():
    """The validator runs under an address-space limit that torch's import exceeds (glibc aborts: 'cannot allocate
    memory for thread-local data'); deciding not to run the network must not import it either."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from dsareg_engine.vision.angiogram import allow_network\n"
            "allow_network(False)\n"
            "from dsareg_engine.vision.segmentation import segment_vessels_and_choice\n"
            "from tests.support.angiogram_images import unsubtracted_angiogram\n"
            "pixels = unsubtracted_angiogram(size=96, seed=2)[0]\n"
            "for method in ('auto', 'network'):\n"
            "    segment_vessels_and_choice(pixels, method)\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]

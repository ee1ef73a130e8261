"""Grey-level DSA synthesized from the model: border-accurate segmentation and registration from it."""

import cv2
import numpy as np
import pytest

from dsareg_engine.vision.segmentation import segment_vessels, vessel_coverage
from dsareg_engine.metrics import iou
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.simulation.synthetic_dsa import DsaSettings, synthesize_dsa, vessel_thickness_mm


@pytest.fixture(scope="module")
def grey_case(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 400, 8.0, 8.0)
    images = synthesize_dsa(phantom, rig, np.eye(4), seed=3)
    return rig, masks, {name: np.round(image * 65535).astype(np.uint16) for name, image in images.items()}


def test_thickness_of_a_cylinder_seen_side_on():
    # A straight tube of radius 3 mm along world y through the isocentre; the AP central ray is
    # perpendicular to it, so the path length through its middle is the diameter, 6 mm.
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig
    from dsareg_engine.mesh import TriangleMesh
    from dsareg_engine.simulation.phantom import _tube

    vertices, faces = _tube(np.linspace([0.0, -40.0, 0.0], [0.0, 40.0, 0.0], 8), np.full(8, 3.0), 96)
    view = clinical_biplane_rig(256).views["ap"]
    thickness = vessel_thickness_mm(TriangleMesh(vertices, faces), view, np.eye(4), supersample=5)
    u0, v0 = view.principal_point_px
    assert thickness[round(v0), round(u0) - 1: round(u0) + 2].max() == pytest.approx(6.0, abs=0.1)
    # Across the tube the profile is 2√(R² − x²) (x in mm at the tube, magnification 1100 / 750).
    pixel_mm = view.pixel_spacing_mm[0] * 750.0 / 1100.0
    x = (np.arange(view.width) - u0) * pixel_mm
    expected = 2.0 * np.sqrt(np.clip(9.0 - x**2, 0.0, None))
    inner = np.abs(x) < 2.0
    assert np.abs(thickness[round(v0)][inner] - expected[inner]).max() < 0.2


def test_dsa_border_beats_otsu_and_binary_masks_stay_exact(grey_case):
    _, masks, images = grey_case
    for name, image in images.items():
        near = cv2.dilate(masks[name].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)  # not the catheter
        border = iou(segment_vessels(image, "auto") & near, masks[name])
        otsu = iou(segment_vessels(image, "otsu") & near, masks[name])
        assert border > 0.8 and border > otsu + 0.05, (border, otsu)
        assert np.array_equal(segment_vessels(masks[name].astype(np.uint8) * 255, "auto"), masks[name])


def test_registration_from_grey_levels_is_close_to_masks(phantom, grey_case):
    rig, masks, images = grey_case
    segmented = {name: vessel_coverage(image, "auto") for name, image in images.items()}  # what the product fits
    truth = np.eye(4).tolist()
    from_masks = register(phantom, masks, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=truth))
    from_grey = register(phantom, segmented, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=truth))
    add_masks = from_masks.metrics["ground_truth"]["add_mm"]
    add_grey = from_grey.metrics["ground_truth"]["add_mm"]
    print(f"ADD masks {add_masks:.4f} grey {add_grey:.4f}")
    assert add_grey < max(2.0 * add_masks, 0.05)
    assert from_grey.metrics["confidence"]["verdict"] == "ok"


def test_sub_pixel_coverage_registers_as_accurately_as_true_masks(phantom, synthetic_case):
    # Flat background, little noise, no catheter: what is left is where the border is placed. The
    # binary dsa mask read 0.028 mm here (2.7x the masks' 0.011 mm); the coverage 0.0125 mm.
    rig, masks = synthetic_case(phantom, 400, 8.0, 8.0)
    settings = DsaSettings(background_variation=0.0, noise_sigma=0.002, catheter_mm=0.0)
    images = synthesize_dsa(phantom, rig, np.eye(4), seed=3, settings=settings)
    targets = {name: vessel_coverage(np.round(image * 65535).astype(np.uint16), "auto") for name, image in images.items()}
    assert all(target.dtype == np.float32 for target in targets.values())
    truth = np.eye(4).tolist()
    from_masks = register(phantom, masks, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=truth))
    from_grey = register(phantom, targets, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=truth))
    add_masks = from_masks.metrics["ground_truth"]["add_mm"]
    add_grey = from_grey.metrics["ground_truth"]["add_mm"]
    print(f"ADD masks {add_masks:.4f} coverage {add_grey:.4f}")
    assert add_grey < 1.5 * add_masks
    assert from_grey.metrics["confidence"]["verdict"] == "ok"
    assert min(view.dice for view in from_grey.views.values()) > 0.8


def test_no_catheter_no_noise_settings_are_accepted(phantom, synthetic_case):
    rig, _ = synthetic_case(phantom, 100, 0.0, 0.0)
    images = synthesize_dsa(phantom, rig, np.eye(4), settings=DsaSettings(catheter_mm=0.0, noise_sigma=0.0, blur_px=0.0))
    assert all(image.dtype == np.float32 and image.max() <= 1.0 for image in images.values())


def test_catheter_is_removed_and_no_pose_grey_case_registers(phantom):
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks

    rig = clinical_biplane_rig(512)
    truth = random_visible_pose(phantom, rig, np.random.default_rng(1), 60.0)
    masks = render_masks(phantom, rig, truth)
    images = synthesize_dsa(phantom, rig, truth, seed=1)
    segmented = {name: vessel_coverage(np.round(image * 65535).astype(np.uint16), "auto") for name, image in images.items()}
    for name, coverage in segmented.items():
        mask = coverage >= 0.5
        far = ~cv2.dilate(masks[name].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        assert (mask & far).sum() < 0.02 * masks[name].sum()  # the catheter (~as long as the tree) is gone
    result = register(phantom, segmented, rig, RegistrationOptions(ground_truth_mesh_to_world=truth.tolist()))
    assert result.metrics["initialization"]["method"] == "search"
    assert result.metrics["ground_truth"]["add_mm"] < 1.0
    assert result.metrics["confidence"]["verdict"] in ("ok", "check")

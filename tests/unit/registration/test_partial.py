"""Partial visibility: a model holding more vessels than the images show (clinical-like rig, no initial pose)."""

import numpy as np
import pytest

from dsareg_engine.geometry.vessel_tree import vessel_tree
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.confidence import assess
from dsareg_engine.registration.partial import (
    explained_faces,
    looks_partial,
    match_fractions,
    refit_faces,
    trimmed_weight,
)
from dsareg_engine.registration.solver import register
from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks
from dsareg_engine.simulation.partial_filling import foreign_territory, selective_injection
from dsareg_engine.simulation.phantom import make_vessel_phantom

SIGNALS = {"dice": {"ap": 0.95, "lat": 0.93}, "runner_up": None, "border_shift_px": {"ap": 0.1, "lat": 0.0},
           "outside_fraction": {"ap": 0.0, "lat": 0.0}, "stopped_on_tolerance": True,
           "unmatched_fraction": {"ap": 0.01, "lat": 0.02}, "uncovered_fraction": {"ap": 0.0, "lat": 0.01}}


@pytest.fixture(scope="module")
def branch_case(phantom):
    """One injected branch (~48 % of the phantom's faces), 256 px, a random pose."""
    case = selective_injection(phantom, 0.5, np.random.default_rng(0), vessel_tree(phantom))
    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(case.model, rig, np.random.default_rng(5), 40.0)
    return case, rig, truth, render_masks(case.visible, rig, truth)


def test_one_injected_branch_registers_with_no_initial_pose(branch_case):
    # Before the coverage search and the trimmed loss this case ended 50-70 mm off (verdict failed).
    case, rig, truth, masks = branch_case
    assert 0.4 <= case.visible_fraction <= 0.6
    result = register(case.model, masks, rig, RegistrationOptions(ground_truth_mesh_to_world=truth.tolist()))
    assert result.metrics["initialization"]["method"].startswith("search+")  # a partial search led the starts
    assert result.metrics["ground_truth"]["add_mm"] < 1.0
    confidence = result.metrics["confidence"]
    assert confidence["verdict"] == "check", confidence["reasons"]
    assert confidence["reasons"][0].startswith("the model has vessels the images do not show")
    assert confidence["signals"]["partial_loss"] is True
    assert min(confidence["signals"]["unmatched_fraction"].values()) > 0.3  # half the model is not filled
    assert max(confidence["signals"]["uncovered_fraction"].values()) <= 0.05


def test_a_branch_the_whole_model_searches_miss_registers_with_no_initial_pose(phantom):
    # One injected branch (47 % of the faces) at a pose where the whole-model searches rank wrong poses
    # first: on the base commit (centroid + coverage search, whole-model fit) this case ended 61 mm off,
    # verdict failed. The branch search finds the filled part and fits it.
    case = selective_injection(phantom, 0.5, np.random.default_rng(2), vessel_tree(phantom))
    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(case.model, rig, np.random.default_rng(102), 40.0)
    result = register(case.model, render_masks(case.visible, rig, truth), rig,
                      RegistrationOptions(ground_truth_mesh_to_world=truth.tolist()))
    assert result.metrics["ground_truth"]["add_mm"] < 1.0
    confidence = result.metrics["confidence"]
    assert confidence["verdict"] == "check" and confidence["reasons"][0].startswith("the model has vessels the images do not show")
    assert result.metrics["initialization"]["method"] == "search+branch"
    assert abs(result.metrics["initialization"]["branch"]["faces_fraction"] - case.visible_fraction) < 0.1


def test_a_model_with_a_foreign_territory_registers_with_no_initial_pose(phantom):
    # The model holds the phantom and another vessel tree joined at its inflow; the run shows the phantom.
    # On the base commit (the parts ranked by the centroid search, whose placement a thick stub of the
    # other tree pulled 12 mm off) this case ended far off (bench partial: 0 of 5 within 1 mm, all
    # failed); the parts ranked by coverage find the phantom.
    case = foreign_territory(phantom, make_vessel_phantom(seed=3))
    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(case.model, rig, np.random.default_rng(11), 40.0)
    result = register(case.model, render_masks(case.visible, rig, truth), rig,
                      RegistrationOptions(ground_truth_mesh_to_world=truth.tolist()))
    assert result.metrics["initialization"]["method"] == "search+branch"
    assert abs(result.metrics["initialization"]["branch"]["faces_fraction"] - case.visible_fraction) < 0.1
    assert result.metrics["ground_truth"]["add_mm"] < 1.0
    confidence = result.metrics["confidence"]
    assert confidence["verdict"] == "check" and confidence["reasons"][0].startswith("the model has vessels the images do not show")


def test_the_faces_the_images_explain_and_the_refit_of_a_part_holding_more(phantom):
    # A model of two trees joined at the inflow, the images showing the phantom: at the true pose the phantom's
    # faces are explained and the other tree's are not (but where it crosses the phantom in both views).
    case = foreign_territory(phantom, make_vessel_phantom(seed=3))
    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(case.model, rig, np.random.default_rng(11), 40.0)
    explained = explained_faces(case.model, truth, render_masks(case.visible, rig, truth), rig)
    shown = np.arange(case.model.n_faces) < phantom.n_faces
    assert explained[shown].mean() > 0.97 and explained[~shown].mean() < 0.1
    # A part = the phantom and a stub of the other tree (3 % of its faces): refitted on what is explained.
    stub = shown | (np.arange(case.model.n_faces) < phantom.n_faces + int(0.03 * phantom.n_faces))
    assert np.array_equal(refit_faces(stub, explained), explained)
    assert refit_faces(shown & explained, explained) is None  # nothing off the vessels: no refit
    assert refit_faces(stub, explained & (np.arange(case.model.n_faces) < 40)) is None  # too little explained


def test_match_fractions_and_partial_rule_by_hand():
    mask = np.zeros((40, 40), bool)
    mask[10:30, 18:22] = True
    model = mask.copy()
    model[10:30, 30:34] = True  # a second branch with no vessel under it
    fractions = match_fractions(model, mask)
    assert fractions == {"unmatched": 0.5, "uncovered": 0.0}
    assert match_fractions(mask, model) == {"unmatched": 0.0, "uncovered": 0.5}
    assert looks_partial({"ap": fractions, "lat": fractions})
    assert not looks_partial({"ap": fractions, "lat": match_fractions(np.roll(mask, 8, axis=1), mask)})
    weight = trimmed_weight(mask.astype(np.float32))
    assert weight[20, 20] == 1.0 and weight[20, 23] == 1.0 and weight[20, 25] < 0.1  # 2 px band kept


def test_the_per_view_partial_rule_answers_as_the_fractions_do():
    from dsareg_engine.registration.partial import MATCH_TOLERANCE_PX, _near, view_looks_partial

    rng = np.random.default_rng(3)
    mask = np.zeros((40, 40), bool)
    mask[10:30, 18:22] = True
    for _ in range(200):
        model = np.roll(mask, int(rng.integers(-6, 7)), axis=1)
        model[10:30, 30:34] = rng.random() < 0.5
        model[rng.integers(0, 40, 30), rng.integers(0, 40, 30)] = True
        if rng.random() < 0.1:
            model[:] = False
        fractions = match_fractions(model, mask, mask_near=_near(mask, MATCH_TOLERANCE_PX))
        assert fractions == match_fractions(model, mask)
        assert view_looks_partial(model, mask) == view_looks_partial(model, mask, _near(mask, MATCH_TOLERANCE_PX)) == looks_partial({"ap": fractions})


def test_verdict_tells_partial_filling_from_a_wrong_pose_and_missing_vessels():
    ok = assess(SIGNALS)
    assert ok["verdict"] == "ok" and ok["reasons"] == []
    partial = assess({**SIGNALS, "dice": {"ap": 0.55, "lat": 0.6},
                      "unmatched_fraction": {"ap": 0.55, "lat": 0.48}, "uncovered_fraction": {"ap": 0.01, "lat": 0.02}})
    assert partial["verdict"] == "check" and len(partial["reasons"]) == 1
    assert "ap 55% / lat 48% of its silhouette outside the vessels, consistently across views" in partial["reasons"][0]
    one_view = assess({**SIGNALS, "dice": {"ap": 0.55, "lat": 0.93},
                       "unmatched_fraction": {"ap": 0.55, "lat": 0.02}, "uncovered_fraction": {"ap": 0.0, "lat": 0.0}})
    assert one_view["verdict"] == "check" and "this view only" in one_view["reasons"][0]
    wrong = assess({**SIGNALS, "dice": {"ap": 0.3, "lat": 0.35},
                    "unmatched_fraction": {"ap": 0.6, "lat": 0.6}, "uncovered_fraction": {"ap": 0.5, "lat": 0.45}})
    assert wrong["verdict"] == "failed" and all("a wrong pose" in reason for reason in wrong["reasons"])
    missing = assess({**SIGNALS, "dice": {"ap": 0.65, "lat": 0.68},
                      "unmatched_fraction": {"ap": 0.02, "lat": 0.01}, "uncovered_fraction": {"ap": 0.45, "lat": 0.4}})
    assert missing["verdict"] == "check"
    assert all("the images show vessels the model lacks" in reason for reason in missing["reasons"])


def test_verdict_says_when_the_images_hold_vessels_the_model_lacks_even_with_a_high_dice():
    # Another territory or background in both views: Dice 0.80 / 0.82 read ok before, with 31 % / 27 % unexplained.
    more = assess({**SIGNALS, "dice": {"ap": 0.80, "lat": 0.82},
                   "unmatched_fraction": {"ap": 0.02, "lat": 0.03}, "uncovered_fraction": {"ap": 0.31, "lat": 0.27}})
    assert more["verdict"] == "check" and len(more["reasons"]) == 1
    assert more["reasons"][0].startswith("the images show vessels the model lacks (ap 31% / lat 27% of the vessels")
    assert "do not show" not in more["reasons"][0]  # not read as partial filling (bench partial counts those)
    # a CTA model without its small branches (the whole-head CTA: 15 % / 17 % at ADD 0.095 mm), one view alone (a
    # catheter filling one view: the grey-level phantom's 16 % / 8 %): ok, as before
    assert assess({**SIGNALS, "uncovered_fraction": {"ap": 0.15, "lat": 0.17}})["verdict"] == "ok"
    assert assess({**SIGNALS, "uncovered_fraction": {"ap": 0.16, "lat": 0.08}})["verdict"] == "ok"
    assert assess({**SIGNALS, "uncovered_fraction": {"ap": 0.24, "lat": 0.3}})["verdict"] == "ok"
    one_view = {key: {"ap": value["ap"]} for key, value in SIGNALS.items() if key.endswith("_fraction")}
    assert assess({**SIGNALS, **one_view, "uncovered_fraction": {"ap": 0.3}})["verdict"] == "ok"  # two views needed


def test_images_holding_another_vessel_read_check_with_the_reason_though_the_overlap_is_high(phantom):
    # The images hold the model and, 25-30 mm away, branches of three other copies of it (other vessels in the field,
    # over a quarter of the vessel pixels in each view): from a pose a few degrees off the fit is right and the
    # overlap high (Dice > 0.7), which read ok before.
    from dsareg_engine.registration.parameterization import random_start_poses

    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(phantom, rig, np.random.default_rng(2), 30.0)
    branch = selective_injection(phantom, 0.2, np.random.default_rng(1), vessel_tree(phantom)).visible
    masks = render_masks(phantom, rig, truth)
    for shift in ([0.0, 30.0, 0.0], [25.0, 0.0, 25.0], [-25.0, -25.0, 0.0]):
        elsewhere = truth.copy()
        elsewhere[:3, 3] += shift
        masks = {name: mask | render_masks(branch, rig, elsewhere)[name] for name, mask in masks.items()}
    initial = random_start_poses(truth, phantom.centroid, 2, 3.0, 2.0, seed=0)[1]
    result = register(phantom, masks, rig, RegistrationOptions(initial_mesh_to_world=initial.tolist(),
                                                               ground_truth_mesh_to_world=truth.tolist()))
    assert result.metrics["ground_truth"]["add_mm"] < 0.5
    confidence = result.metrics["confidence"]
    assert min(confidence["signals"]["dice"].values()) > 0.7, confidence["signals"]  # no low-overlap rule fires
    assert confidence["verdict"] == "check", confidence["reasons"]
    assert confidence["reasons"][0].startswith("the images show vessels the model lacks (")

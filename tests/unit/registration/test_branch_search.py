"""The branch search: the model cut into its branches, each searched alone (partial visibility)."""

import numpy as np

from dsareg_engine.geometry.vessel_tree import vessel_tree
from dsareg_engine.registration.branch_search import BranchSettings, candidate_parts, search_parts
from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks
from dsareg_engine.simulation.partial_filling import extra_territory


def test_parts_are_distinct_branches_in_the_size_range(phantom):
    settings = BranchSettings(samples=200, max_parts=12)
    parts = candidate_parts(phantom, settings)
    assert 2 <= len(parts) <= 12 and parts.shape[1] == phantom.n_faces
    share = parts.mean(axis=1)
    assert np.all((share >= settings.min_fraction) & (share <= settings.max_fraction))
    for i in range(len(parts)):
        for j in range(i):
            assert (parts[i] & parts[j]).sum() <= settings.overlap * (parts[i] | parts[j]).sum()
    # a part is a branch (never holding the inflow's faces) or the model less a branch (holding them)
    tree = vessel_tree(phantom)
    inflow_faces = np.any(phantom.faces == tree.inflow, axis=1)
    holds_inflow = parts[:, inflow_faces].any(axis=1)
    assert holds_inflow.any() and not holds_inflow.all()


def test_the_filled_territory_is_found_among_the_parts(phantom):
    # The model holds the phantom and its mirror image; the images show the phantom alone. The part
    # that is the phantom must score best and place it near its true pose; other parts score worse.
    case = extra_territory(phantom)
    rig = clinical_biplane_rig(192)
    truth = random_visible_pose(case.model, rig, np.random.default_rng(3), 30.0)
    found = search_parts(case.model, render_masks(case.visible, rig, truth), rig, BranchSettings(samples=150, max_parts=6))
    assert abs(found.fractions[0] - 0.5) < 0.1  # the original half (and a few faces past the inflow)
    original = phantom.vertices
    moved = original @ found.poses[0][:3, :3].T + found.poses[0][:3, 3]
    assert np.linalg.norm(moved - (original @ truth[:3, :3].T + truth[:3, 3]), axis=1).mean() < 5.0
    assert found.scores[0] < 0.3 < found.scores[-1]

"""The coverage search: precision / recall of a placed model over pixel shifts, and its pose search."""

from dataclasses import replace

import numpy as np

from dsareg_engine.registration.search.coverage_search import coverage_scores, coverage_view, search_by_coverage
from dsareg_engine.registration.search.initialization import surface_points, triangulate_mask_centroids
from dsareg_engine.registration.search.rotation_grid import angles_between_deg
from dsareg_engine.registration.search.settings import COVERAGE
from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, render_masks


def _placed(phantom, rig, centroid_world):
    pose = np.eye(4)
    pose[:3, 3] = centroid_world - phantom.centroid
    return pose


def _scores_at(phantom, rig, pose, masks, past_edge_weight):
    settings = replace(COVERAGE, beta=1.0, past_edge_weight=past_edge_weight)
    centre = pose[:3, :3] @ phantom.centroid + pose[:3, 3]  # canvases centred on the truth: no shift to linearize
    radius = float(np.sqrt(((phantom.vertices - phantom.centroid) ** 2).sum(axis=1).mean()))
    canvases = [coverage_view(rig.views[name], mask, centre, radius, settings) for name, mask in masks.items()]
    points = np.ascontiguousarray(surface_points(phantom, 2500) - phantom.centroid)
    return coverage_scores(canvases, pose[None, :3, :3], centre, points, settings)


def test_model_pixels_past_the_detector_edge_count_as_weighed(phantom):
    # The phantom's centre placed on the AP detector's left edge: about half of it projects past the edge.
    # At its true pose every model pixel on the detector lies on the vessels, so AP precision is
    # on / (on + w past): 1 when the part past the edge is free (w = 0), the old score's on / all
    # (0.40 here, as low as a wrong pose's) when it counts in full (w = 1), between for the default.
    rig = clinical_biplane_rig(192)
    ap = rig.views["ap"]
    across = ap.world_to_view[0, :3]  # the view's x axis in the world: moving along it moves the projection in u
    edge = next(sign * mm * across for mm in np.linspace(0.0, 300.0, 601) for sign in (1.0, -1.0)
                if ap.project((sign * mm * across)[None])[0, 0] <= 0.0)
    pose = _placed(phantom, rig, edge)
    masks = render_masks(phantom, rig, pose)
    seen = ap.project(phantom.vertices @ pose[:3, :3].T + pose[:3, 3])[:, 0]
    assert 0.3 < (seen < 0).mean() < 0.7  # the case is what it claims: a large share past the edge
    precision = {w: _scores_at(phantom, rig, pose, masks, w)[2][0, :, 0] for w in (0.0, COVERAGE.past_edge_weight, 1.0)}
    free, default, full = precision.values()
    assert free.min() > 0.95 and full[0] < 0.7 and full[1] > 0.95  # LAT sees it all
    assert full[0] < default[0] < free[0]
    recall = _scores_at(phantom, rig, pose, masks, 0.5)[2][0, :, 1]
    assert recall.min() > 0.95


def test_the_search_finds_a_fully_visible_phantom(phantom):
    rig = clinical_biplane_rig(192)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° about z
    pose = np.eye(4)
    pose[:3, :3] = turn
    pose[:3, 3] = np.array([10.0, -5.0, 8.0]) - turn @ phantom.centroid
    masks = render_masks(phantom, rig, pose)
    centre = triangulate_mask_centroids(masks, rig)
    points = np.ascontiguousarray(surface_points(phantom, 2500) - phantom.centroid)
    found = search_by_coverage(phantom, masks, rig, centre, points, 2, 30.0, replace(COVERAGE, beta=1.0))
    assert found.poses.shape == (2, 4, 4) and found.scores[0] <= found.scores[1]
    assert angles_between_deg(found.poses[:1, :3, :3], pose[:3, :3])[0] < 15.0
    placed = phantom.vertices @ found.poses[0][:3, :3].T + found.poses[0][:3, 3]
    assert np.linalg.norm(placed - (phantom.vertices @ pose[:3, :3].T + pose[:3, 3]), axis=1).mean() < 10.0
    assert found.best_detail.shape == (2, 2)

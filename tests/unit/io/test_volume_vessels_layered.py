"""Heads from the second generator (skull with diploë, a cancellous skull base the trunk crosses, streak noise;
MRA with coil inhomogeneity and skull-base marrow fat) at common voxel sizes, anisotropic ones included.

On main before the medial measure, the CTA head was refused at 0.6, 0.8 and 1.0 mm: "the kept voxels are
plate-shaped (89 % / 99 %)" or "keeps 3.9 % of the volume" (the diploë, in the vessels' HU window, was kept).
"""

from functools import cache

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dsareg_engine.io.volume_io import read_volume
from dsareg_engine.io.volume_vessels import extract_vessels
from dsareg_engine.simulation.synthetic_heads_layered import CTA_LEVELS, make_layered_cta_head, make_layered_mra_head
from dsareg_engine.simulation.synthetic_volumes import vessel_tree

SMALL_HEAD_MM = (30.0, 30.0, 40.0)


@cache
def _tree():
    return vessel_tree(2, 3)


def _distances(mesh, tree):
    samples, _ = trimesh.sample.sample_surface(trimesh.Trimesh(tree.vertices, tree.faces, process=False), 20_000,
                                               seed=1)
    return cKDTree(samples).query(mesh.vertices)[0], cKDTree(mesh.vertices).query(samples)[0]


@pytest.mark.parametrize("kind, voxel_mm", [("cta", 0.8), ("cta", (0.5, 0.5, 1.0)), ("mra", 0.6)])
def test_a_layered_head_is_read_as_its_vessels(kind, voxel_mm):
    maker = make_layered_cta_head if kind == "cta" else make_layered_mra_head
    head = maker(voxel_mm=voxel_mm, tree=_tree(), min_head_mm=SMALL_HEAD_MM)
    volume = read_volume(head.parts)
    assert volume.spacing_mm == pytest.approx(np.broadcast_to(voxel_mm, (3,)), abs=1e-4)
    extraction = extract_vessels(volume)
    coarse = float(np.max(voxel_mm))
    model_to_truth, truth_to_model = _distances(extraction.mesh, head.tree)
    assert np.percentile(model_to_truth, 95) < 2.0 * coarse, np.percentile(model_to_truth, [50, 95, 100])
    # most of the tree is there (the trunk's segment through the cancellous skull base can be set aside with it)
    assert np.percentile(truth_to_model, 75) < 1.5 * coarse, np.percentile(truth_to_model, [50, 75, 90, 100])
    assert extraction.readout.plate_share < 0.35


def test_a_cancellous_skull_base_does_not_raise_the_vessel_window():
    """The skull base's cancellous core (550 HU, in the HU window) outweighed the vessels in the level estimate: on
    main the window started at 259 HU instead of ~160 and at 0.8 mm the thin distal tree fell below it (42 % of the
    tree's upper half kept; ADD 5.0 mm, ``check``, in the sweep). The level is estimated again without the plates."""
    tree = vessel_tree(3, 3)
    head = make_layered_cta_head(voxel_mm=0.8, tree=tree, min_head_mm=SMALL_HEAD_MM)
    extraction = extract_vessels(read_volume(head.parts))
    samples, _ = trimesh.sample.sample_surface(trimesh.Trimesh(tree.vertices, tree.faces, process=False), 20_000,
                                               seed=1)
    covered = cKDTree(extraction.mesh.vertices).query(samples)[0] < 1.0
    upper = samples[:, 2] > np.median(samples[:, 2])  # the distal half: thin branches
    assert covered[upper].mean() > 0.9, covered[upper].mean()
    assert extraction.readout.vessel_min < 0.5 * (CTA_LEVELS["brain"] + CTA_LEVELS["vessel"]) + 20.0

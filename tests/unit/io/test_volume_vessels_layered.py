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
from dsareg_engine.simulation.synthetic_heads_layered import (CTA_LEVELS, MRA_LEVELS, make_layered_cta_head,
                                                               make_layered_mra_head)
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


def _tube(start, end, radius_mm, end_radius_mm=None):
    from dsareg_engine.simulation.phantom import _tube as swept

    start, end = np.asarray(start, float), np.asarray(end, float)
    line = start + np.linspace(0.0, 1.0, 8)[:, None] * (end - start)
    return swept(line, np.linspace(radius_mm, end_radius_mm or radius_mm, 8), 12)


def _tree_with_a_folded_loop(rungs: int = 3, radius_mm: float = 1.8, apart_mm: float = 5.0):
    """A trunk (+z) into a loop folded flat (``rungs`` 16 mm rungs ``apart_mm`` apart in one plane, r ``radius_mm``:
    close-packed vessels that read plate-like on the medial measure at 1 mm, as the paper's carotid bulge does), then
    two branches with two children each."""
    from dsareg_engine.mesh import TriangleMesh

    parts = [_tube((0, 0, -40), (0, 0, 0), 2.4, 2.2)]
    top = apart_mm * (rungs - 1)
    for rung in range(rungs):
        z = apart_mm * rung
        x0, x1 = (0.0, 16.0) if rung % 2 == 0 else (16.0, 0.0)
        parts.append(_tube((x0, 0, z), (x1, 0, z), radius_mm))
        if z < top:
            parts.append(_tube((x1, 0, z), (x1, 0, z + apart_mm), radius_mm))
    end = np.array([16.0 if rungs % 2 else 0.0, 0.0, top])
    for dx, dy in ((-20.0, 12.0), (18.0, -14.0)):
        middle = end + (dx, dy, 22.0)
        parts.append(_tube(end, middle, 1.3, 1.1))
        parts += [_tube(middle, middle + (ex, 6.0, 16.0), 1.0, 0.8) for ex in (-8.0, 8.0)]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return TriangleMesh(np.ascontiguousarray(vertices - vertices.mean(0)), faces), vertices.mean(0)


def test_a_plate_like_stretch_of_the_tree_is_not_set_aside_as_bone():
    """Close-packed vessels (a loop folded flat) read plate-like, like the cancellous skull base and the diploë; on
    main every plate part of 200 mm³ was set aside, the tree split there and only its largest piece stayed (43 % of
    the tree within 1.5 mm; the paper's tree in this generator's CTA: ADD 34-41 mm, ``failed``). Bone plates lie
    between cortical bone; the loop lies in tissue and stays with its tree, while the skull base is set aside."""
    tree, centre = _tree_with_a_folded_loop()
    head = make_layered_cta_head(voxel_mm=1.0, tree=tree, min_head_mm=SMALL_HEAD_MM)
    volume = read_volume(head.parts)
    extraction = extract_vessels(volume)
    samples, _ = trimesh.sample.sample_surface(trimesh.Trimesh(tree.vertices, tree.faces, process=False), 20_000,
                                               seed=1)
    covered = cKDTree(extraction.mesh.vertices).query(samples)[0] < 1.5  # 1.5 voxels (the loop's 1.4 mm gaps)
    height = samples[:, 2] + centre[2]  # as built: the loop from z 0 to 10 mm
    assert covered.mean() > 0.75, covered.mean()
    assert covered[(height > -1.0) & (height < 12.0)].mean() > 0.9
    assert covered[height > 12.0].mean() > 0.9  # the branches beyond it
    assert extraction.readout.plate_share < 0.35
    # the skull base's cancellous core (in the window, 5 mm thick across the head) is still set aside: in its
    # slice range only the trunk crossing it may be kept
    kept_z = (np.argwhere(extraction.kept) @ volume.affine[:3, :3].T + volume.affine[:3, 3])[:, 2]
    core = (kept_z > tree.vertices[:, 2].min() + 6.0) & (kept_z < tree.vertices[:, 2].min() + 10.0)
    assert core.sum() < 4.0 * np.pi * 3.0**2, core.sum()  # the trunk's cross-section (r ≤ 3 mm) over 4 mm


def _covered_within_1_5_mm(tree, extraction, centre) -> tuple[np.ndarray, np.ndarray]:
    """20,000 points sampled on the tree's surface: whether the extracted surface lies within 1.5 mm of each, and
    each point's height as the tree was built (z + the centre it was moved by)."""
    samples, _ = trimesh.sample.sample_surface(trimesh.Trimesh(tree.vertices, tree.faces, process=False), 20_000,
                                               seed=1)
    return cKDTree(extraction.mesh.vertices).query(samples)[0] < 1.5, samples[:, 2] + centre[2]


def test_a_plate_like_stretch_of_the_tree_is_not_set_aside_as_marrow_in_a_tof_mra():
    """TOF-MRA: the plate pass went by size alone (bone is dark there, so no bone contact): a loop folded flat (five
    rungs, r 2 mm: 870 mm³ read plate-like, as the paper's bulge is a 1,264 mm³ plate part at 1 mm) was set aside
    once the pass ran (plate share 0.36), the tree split there: on main 34 % of the tree within 1.5 mm, 9 % of the
    loop. Marrow and fat lie inside dark bone or under the skin; the loop lies in brain and stays with its tree."""
    tree, centre = _tree_with_a_folded_loop(rungs=5, radius_mm=2.0)
    head = make_layered_mra_head(voxel_mm=1.0, tree=tree)  # the default head: the plate pass runs (share 0.36)
    volume = read_volume(head.parts)
    extraction = extract_vessels(volume)
    covered, height = _covered_within_1_5_mm(tree, extraction, centre)  # as built: the loop from z 0 to 20 mm
    assert covered.mean() > 0.9, covered.mean()
    assert covered[(height > -1.0) & (height < 22.0)].mean() > 0.9
    # the skull base's marrow (bright, between dark cortical plates) is not kept: in its slice range only the trunk
    kept_z = (np.argwhere(extraction.kept) @ volume.affine[:3, :3].T + volume.affine[:3, 3])[:, 2]
    base = (kept_z > tree.vertices[:, 2].min() + 4.0) & (kept_z < tree.vertices[:, 2].min() + 12.0)
    assert base.sum() < 8.0 * np.pi * 3.0**2, base.sum()  # the trunk's cross-section (r ≤ 3 mm) over 8 mm


def test_a_plate_like_stretch_of_the_tree_in_a_csf_cistern_is_not_set_aside_in_a_tof_mra():
    """CSF is dark in TOF-MRA (generator B: 100, brain 230), darker than the tissue by 3 of its spreads, as bone is:
    a loop folded flat (five rungs 4.3 mm apart, r 2 mm: a 631 mm³ plate part, plate share 0.39, so the pass runs)
    lying in a 3 mm sleeve of CSF had 0.95 of its surface against "dark" voxels and was set aside as marrow: on main
    35 % of the tree within 1.5 mm, 12 % of the loop. Bone and air give no signal (the noise floor, measured
    outside the head); CSF does (generator B: bone 50, air ~15 after Rician noise, CSF 100): a plate lies against
    bone only where voxels are near the noise floor."""
    from dsareg_engine.simulation.cisterns import Cisterns

    tree, centre = _tree_with_a_folded_loop(rungs=5, radius_mm=2.0, apart_mm=4.3)
    head = make_layered_mra_head(voxel_mm=1.0, tree=tree, min_head_mm=SMALL_HEAD_MM,
                                 cisterns=Cisterns(sleeve_mm=3.0, reach_mm=60.0))  # the trunk's top, loop, branches
    volume = read_volume(head.parts)
    loop = volume.data[tuple(np.round(np.linalg.solve(volume.affine, [*(np.array([8.0, 3.5, 8.6]) - centre), 1.0]
                                                      )[:3]).astype(int))]
    assert loop < 0.6 * MRA_LEVELS["brain"], loop  # beside the loop's middle rung (1.5 mm off its wall): CSF, not brain
    extraction = extract_vessels(volume)
    covered, height = _covered_within_1_5_mm(tree, extraction, centre)  # as built: the loop from z 0 to 17.2 mm
    assert covered.mean() > 0.9, covered.mean()
    assert covered[(height > -1.0) & (height < 19.0)].mean() > 0.9
    assert covered[height > 19.0].mean() > 0.9  # the branches beyond it


def _slab_inside_the_head(head, slab_mm: float, margin_mm: float = 3.0):
    """The voxels of ``head`` around its tree (no scalp, no air) over ``slab_mm`` along z: a TOF slab's crop."""
    from dsareg_engine.io.volume_io import Volume

    volume = read_volume(head.parts)
    inv = np.linalg.inv(volume.affine)
    ijk = head.tree.vertices @ inv[:3, :3].T + inv[:3, 3]
    spacing = np.asarray(volume.spacing_mm)
    low = np.maximum(np.floor(ijk.min(0) - margin_mm / spacing).astype(int), 0)
    high = np.minimum(np.ceil(ijk.max(0) + margin_mm / spacing).astype(int) + 1, volume.data.shape)
    axial = int(np.argmax(np.abs(volume.affine[2, :3])))
    middle, half = (low[axial] + high[axial]) // 2, round(slab_mm / spacing[axial] / 2)
    low[axial], high[axial] = middle - half, middle + half
    affine = volume.affine.copy()
    affine[:3, 3] = volume.affine[:3, :3] @ low + volume.affine[:3, 3]
    data = np.ascontiguousarray(volume.data[tuple(slice(a, b) for a, b in zip(low, high))])
    return Volume(data, affine, volume.kind, tags=volume.tags), data.shape[axial] * spacing[axial]


def test_a_tof_slab_cut_through_the_head_is_read_as_its_vessels():
    """A TOF slab (or a crop) cuts through the head: its faces are not the head's surface. On main the closing of the
    head mask eroded it from the volume's faces and the 7-mm scalp shell was taken from there: a 12-mm slab was
    refused ("no head interior deeper than 7 mm"), a 16-mm one kept 129 voxels of the tree."""
    head = make_layered_mra_head(voxel_mm=(0.5, 0.5, 0.8), tree=_tree(), min_head_mm=SMALL_HEAD_MM)
    volume, thickness_mm = _slab_inside_the_head(head, slab_mm=12.0)
    assert 11.0 < thickness_mm < 13.5
    extraction = extract_vessels(volume)
    corners = volume.affine @ np.array([[0.0, 0.0, 0.0, 1.0], [*(np.array(volume.data.shape) - 1.0), 1.0]]).T
    z = corners[2]
    inside = head.tree.vertices[(head.tree.vertices[:, 2] > min(z) + 1.0) & (head.tree.vertices[:, 2] < max(z) - 1.0)]
    assert len(inside) > 50
    model = cKDTree(extraction.mesh.vertices)
    assert np.percentile(model.query(inside)[0], 75) < 1.5, np.percentile(model.query(inside)[0], [50, 75, 90])
    truth = cKDTree(head.tree.vertices)
    assert np.percentile(truth.query(extraction.mesh.vertices)[0], 95) < 1.6


@pytest.mark.parametrize("section, voxel_mm", [("round", 0.8), ("round", (0.5, 0.5, 1.0)), ("triangle", 0.8)])
def test_a_late_cta_s_dural_sinuses_are_set_aside(section, voxel_mm):
    """A CTA taken late: the superior sagittal and transverse sinuses filled (300 HU; the arteries 380), one piece
    several times the tree's size against the skull's inner table. Kept, it would be the model (the registration
    fits it to an arterial run). Round in section it is a tube: set aside as venous sinuses, with no close call; a
    flat triangle is a plate against bone: set aside with the plates. Either way the model is the tree's."""
    head = make_layered_cta_head(voxel_mm=voxel_mm, tree=_tree(), min_head_mm=SMALL_HEAD_MM, sinuses=section)
    volume = read_volume(head.parts)
    venous = (volume.data > 250.0) & (volume.data < 350.0)
    extraction = extract_vessels(volume)
    sinuses = [d for d in extraction.readout.decisions if d.what == "venous sinuses"]
    if section == "round":
        assert sinuses[0].chosen == "1 set aside" and sinuses[0].measure > sinuses[0].threshold + sinuses[0].band
    coarse = float(np.max(voxel_mm))
    model_to_truth, truth_to_model = _distances(extraction.mesh, head.tree)
    assert np.percentile(model_to_truth, 99) < 2.0 * coarse, np.percentile(model_to_truth, [50, 99, 100])
    assert np.percentile(truth_to_model, 75) < 1.5 * coarse
    assert extraction.readout.components == 1 and venous.sum() > 5 * extraction.readout.voxels_kept


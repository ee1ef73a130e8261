"""Vessel models from CTA and TOF-MRA heads (skull, skull base, scalp fat) and their registration.

On the code before volume kinds, the CTA head's Otsu + marching cubes kept the head itself (41 % of the
volume; a 368,752-face surface at 0.5 mm in the issue), so the model was not the vessels and the
registration ended 160 mm off; the MRA the same (scalp fat, brain).
"""

import json
from functools import cache

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.case import CaseFiles, load_case
from dsareg_engine.io.volume_io import Volume, read_volume
from dsareg_engine.io.volume_kind import VolumeReading
from dsareg_engine.io.volume_vessels import extract_vessels
from dsareg_engine.pipeline import run_case
from dsareg_engine.simulation.synthetic_volumes import make_volume_case

VOXEL_MM = 1.0  # coarse, in a narrow head: ~2 MB series, about a CPU second to make and to read
SMALL_HEAD_MM = (30.0, 30.0, 40.0)


@cache
def _case(kind: str, variant: str):
    return make_volume_case(kind, variant, voxel_mm=VOXEL_MM, depth=2, image_px=160, pixel_spacing_mm=0.9,
                            min_head_mm=SMALL_HEAD_MM)


@cache
def _read(kind: str, variant: str):
    volume = read_volume(_case(kind, variant).volume.parts)
    return volume, extract_vessels(volume)


def _distances(mesh, tree):
    samples, _ = trimesh.sample.sample_surface(trimesh.Trimesh(tree.vertices, tree.faces, process=False), 20_000,
                                               seed=1)
    model_to_truth = cKDTree(samples).query(mesh.vertices)[0]
    truth_to_model = cKDTree(mesh.vertices).query(samples)[0]
    return model_to_truth, truth_to_model


@pytest.mark.parametrize("kind, variant", [("cta", "a"), ("cta", "b"), ("mra", "a"), ("mra", "b")])
def test_a_head_yields_a_vessel_only_model(kind, variant):
    case = _case(kind, variant)
    extraction = _read(kind, variant)[1]
    readout = extraction.readout
    assert readout.kind == kind, readout.kind_source
    model_to_truth, truth_to_model = _distances(extraction.mesh, case.volume.tree)
    # every part of the model is on the vessels (no skull, slab, scalp fat or brain), within ~2 voxels ...
    assert np.percentile(model_to_truth, 99) < 2.0 * VOXEL_MM, np.percentile(model_to_truth, [50, 99, 100])
    assert np.median(model_to_truth) < 0.7 * VOXEL_MM
    # ... and the whole tree is there (the trunk through the skull-base slab included)
    assert np.percentile(truth_to_model, 95) < 1.5 * VOXEL_MM, np.percentile(truth_to_model, [50, 95, 100])
    assert readout.components == 1 and readout.voxels_kept < 0.002 * readout.voxels_total
    assert 1000 < readout.faces < 10_000


def test_the_carotid_canal_is_kept_through_the_skull_base():
    case = _case("cta", "a")
    mesh = _read("cta", "a")[1].mesh
    tree = case.volume.tree.vertices
    low = tree[:, 2].min()
    slab = (mesh.vertices[:, 2] > low + 6.0) & (mesh.vertices[:, 2] < low + 12.0)  # inside the 900 HU slab
    assert slab.sum() > 20
    # the surface there is the lumen's wall: close to the tree, not the slab's faces (a plane 80 mm wide)
    assert np.ptp(mesh.vertices[slab, 0]) < 10.0 and np.ptp(mesh.vertices[slab, 1]) < 10.0


def _late_case():
    """A CTA taken late (the second generator's head, its dural sinuses filled, round in section) and its arterial
    XA pair. Before the sinuses were set aside its model was mostly venous: ADD 3.1 mm, and ~100 mm on whole heads."""
    from dsareg_engine.simulation.synthetic_heads_layered import make_layered_cta_head
    from dsareg_engine.simulation.synthetic_volumes import vessel_tree, volume_case_of

    head = make_layered_cta_head(voxel_mm=0.8, tree=vessel_tree(2, 3), min_head_mm=SMALL_HEAD_MM, sinuses="round")
    return volume_case_of(head, image_px=160, pixel_spacing_mm=0.9)


@pytest.mark.parametrize("kind, variant", [("cta", "a"), ("mra", "b"), ("cta", "late")])
def test_the_head_registers_through_the_whole_job(kind, variant, tmp_path):
    case = _late_case() if variant == "late" else _case(kind, variant)
    files = CaseFiles(ap=case.ap, ap_name="ap.dcm", lat=case.lat, lat_name="lat.dcm", volume=case.volume.parts,
                      volume_name="volume.dcm")
    options = {"initialization": "given", "initial_mesh_to_world": np.eye(4).tolist(), "starts": 1,
               "ground_truth_mesh_to_world": case.mesh_to_world.tolist()}
    data = run_case(files, options, tmp_path, dicom="off")
    assert data["metrics"]["ground_truth"]["add_mm"] < 0.5, data["metrics"]["ground_truth"]
    assert data["metrics"]["confidence"]["verdict"] == "ok", data["metrics"]["confidence"]
    written = json.loads((tmp_path / "result.json").read_text())["volume"]
    assert written["kind"] == kind and written["voxels_kept"] > 500 and written["faces"] > 1000
    assert written["vessel_min"] > written["tissue_level"]
    if variant == "late":  # the venous system set aside, no close call
        (sinuses,) = [d for d in data["input_decisions"] if d["what"] == "venous sinuses"]
        assert sinuses["chosen"] == "1 set aside" and not sinuses["close"]


def test_override_reads_the_same_series_as_another_kind():
    volume, extraction = _read("cta", "a")
    given = extract_vessels(volume, VolumeReading("cta", vessel_min=250.0, vessel_max=800.0)).readout
    assert given.kind_source.startswith("given") and given.vessel_min == 250.0 and given.vessel_max == 800.0
    auto = extraction.readout
    assert given.voxels_kept < auto.voxels_kept  # a higher floor keeps fewer voxels
    with pytest.raises(DsaregInputError) as info:  # today's reading (Otsu) keeps the head: refused
        extract_vessels(volume, VolumeReading("3d-dsa"))
    assert info.value.field == "volume" and "far more than vessels" in info.value.message


def test_a_cta_without_contrast_in_the_window_is_refused():
    volume = _read("cta", "a")[0]
    data = volume.data.copy()
    data[(data > 100) & (data < 700)] = 40.0  # the vessels (and every partial-volume voxel) become tissue
    with pytest.raises(DsaregInputError, match="no vessels") as info:
        extract_vessels(Volume(data, volume.affine, volume.kind, tags=volume.tags))
    assert info.value.field == "volume"
    with pytest.raises(DsaregInputError, match="no vessels"):
        load_case(volume=_case("cta", "a").volume.parts, ap=_case("cta", "a").ap, lat=_case("cta", "a").lat,
                  volume_reading=VolumeReading("cta", vessel_min=2000.0, vessel_max=3000.0))


def test_the_reading_is_recorded_as_decisions_with_their_margins():
    readout = _read("cta", "a")[1].readout
    decisions = {decision.what: decision for decision in readout.decisions}
    assert set(decisions) == {"volume kind", "vessel window", "bone threshold", "vessel shape"}
    assert decisions["volume kind"].chosen == "cta" and decisions["volume kind"].source == "measured"
    assert decisions["bone threshold"].threshold == 700.0 and decisions["bone threshold"].margin < -200.0
    assert decisions["vessel window"].measure > 200.0 and not any(d.close for d in readout.decisions)
    assert decisions["vessel shape"].measure == readout.plate_share < 0.3
    assert "decisions" not in readout.to_dict() and "plate_share" in readout.to_dict()


def test_vessels_close_to_the_bone_threshold_are_a_close_call():
    volume = _read("cta", "a")[0]
    data = volume.data.copy()
    data[(data > 150) & (data < 600)] += 330.0  # vessels at ~680 HU: just under the 700 HU bone threshold
    readout = extract_vessels(Volume(data, volume.affine, volume.kind, tags=volume.tags)).readout
    bone = next(decision for decision in readout.decisions if decision.what == "bone threshold")
    assert bone.close and "bone threshold" in bone.reason()
    given = extract_vessels(Volume(data, volume.affine, volume.kind, tags=volume.tags),
                            VolumeReading("cta", vessel_max=850.0)).readout
    assert not any(decision.close for decision in given.decisions if decision.what == "bone threshold")


def test_a_released_volume_reads_the_same_and_lets_its_grid_go():
    """Issue 41: a job does not hold the volume's float32 grid through the reading (``release=True``, as
    ``load_case`` reads): the same surface, readout and decisions, and ``volume.data`` is let go."""
    parts = _case("cta", "a").volume.parts
    kept, released = read_volume(parts), read_volume(parts)
    shape = kept.data.shape
    a = extract_vessels(kept)
    b = extract_vessels(released, release=True)
    assert released.data is None and kept.data is not None
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    assert a.readout.to_dict() == b.readout.to_dict() and a.readout.decisions == b.readout.decisions
    assert b.kept.shape == shape and np.array_equal(a.kept, b.kept)


def _ball_head(shape: tuple[int, int, int], centre_z: float) -> np.ndarray:
    """A 1-mm-voxel ball of radius 40 mm, centred in x, y and at ``centre_z`` along z (so the grid may cut it)."""
    z, y, x = np.indices(shape, dtype=np.float32)
    return (x - shape[2] / 2) ** 2 + (y - shape[1] / 2) ** 2 + (z - centre_z) ** 2 <= 40.0 ** 2


def test_an_mra_heads_interior_keeps_its_shell_from_a_face_that_cuts_it_at_the_neck():
    """A whole head cut by the grid's bottom face (its scalp's bottom lies in that face): the interior stays the shell's
    depth away from the cut as well as from the air (on 7a41475 it reached the face, with the scalp's fat in it)."""
    from dsareg_engine.io.volume_vessels import MRA_SHELL_MM, _mra_interior

    head = _ball_head((70, 90, 90), centre_z=32.0)  # the ball's bottom 8 mm are cut away by the face z = 0
    interior = _mra_interior(head, np.ones(3))
    assert head[0].any() and interior.any()
    assert not interior[: int(MRA_SHELL_MM)].any()


def test_an_mra_slab_measures_its_interior_from_the_air_alone():
    """A 12-mm TOF slab through the head: measured from its faces too, nothing would be left; from the air, the
    slab's middle is interior."""
    from dsareg_engine.io.volume_vessels import _mra_interior

    head = _ball_head((12, 90, 90), centre_z=6.0)
    interior = _mra_interior(head, np.ones(3))
    assert interior[0].sum() > 0.25 * head[0].sum()


def test_an_mra_head_no_face_cuts_has_the_interior_measured_from_the_air():
    """No face cuts the head: the faces add nothing, so the interior is the air-measured one (computed once)."""
    from dsareg_engine.io.volume_vessels import MRA_SHELL_MM, _mra_interior
    from dsareg_engine.io.voxel_band import within_mm

    head = _ball_head((90, 90, 90), centre_z=45.0)
    assert np.array_equal(_mra_interior(head, np.ones(3)), head & ~within_mm(~head, np.ones(3), MRA_SHELL_MM))


def test_the_band_of_the_faces_is_that_of_a_padded_grid():
    """The faces' band (:func:`_near_faces`) added to the air's is the band of the grid padded with one outside
    layer (the measure before): the same voxels, for anisotropic voxels and bands dilated or transformed."""
    from dsareg_engine.io.volume_vessels import _near_faces
    from dsareg_engine.io.voxel_band import within_mm

    rng = np.random.default_rng(7)
    for spacing, band in (((1.0, 1.0, 1.0), 7.0), ((0.5, 0.4, 0.4), 3.0), ((0.6, 0.3, 0.3), 2.1), ((0.3, 0.3, 0.3), 1.2),
                          ((0.5, 0.5, 0.5), 5.0)):  # the last: a band too wide to dilate (transformed by slabs)
        spacing = np.asarray(spacing)
        shape = tuple(int(n) for n in rng.integers(12, 30, 3))
        air = rng.random(shape) < 0.02
        padded = within_mm(np.pad(air, 1, constant_values=True), spacing, band)[1:-1, 1:-1, 1:-1]
        assert np.array_equal(padded, within_mm(air, spacing, band) | _near_faces(shape, spacing, band))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_voxels_are_filled_and_a_constant_volume_is_refused(bad):
    """NaN (the volume's lowest finite value) and ±inf (0) are filled before any reading, found from the extremes
    alone (one pass fewer over a whole head); a volume with one value left is refused by name."""
    from dsareg_engine.io.volume_vessels import _finite

    voxels = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6) + 10.0
    voxels[1, 2, 3] = bad
    filled = _finite(voxels, "volume")
    assert np.isfinite(filled).all() and filled[1, 2, 3] == (10.0 if np.isnan(bad) else 0.0)
    assert np.array_equal(np.delete(filled.ravel(), 1 * 30 + 2 * 6 + 3), np.delete(voxels.ravel(), 1 * 30 + 2 * 6 + 3))
    constant = np.full((4, 5, 6), 7.0, np.float32)
    constant[0, 0, 0] = bad
    if not np.isnan(bad):  # ±inf filled by 0: two values left
        assert _finite(constant, "volume")[0, 0, 0] == 0.0
    else:
        with pytest.raises(DsaregInputError, match="is constant"):
            _finite(constant, "volume")


def test_the_seeded_components_and_the_local_half_maximum_are_the_expressions_they_replace():
    """The MRA reading's memory steps (issue 41, a 300-slice TOF: 2.46 → 1.81 GB) give the same voxels and the same
    float32 bits as the whole-grid expressions: ``np.isin`` of the labels, and the field in one expression."""
    from scipy import ndimage

    from dsareg_engine.io import volume_vessels as vv

    rng = np.random.default_rng(11)
    for _ in range(8):
        smooth = ndimage.gaussian_filter(rng.random((24, 30, 28)), 1.0).astype(np.float32) * 600
        mask = smooth > np.percentile(smooth, 70)
        seeds = mask & (smooth > np.percentile(smooth, 97))
        seeds[0, 0, 0] = True  # a seed outside the mask: no component
        labels, _ = ndimage.label(mask)
        assert np.array_equal(vv._seeded(mask, seeds), np.isin(labels, np.unique(labels[seeds & (labels > 0)])))
        spacing, tissue, level = np.array([0.4, 0.4, 0.5]), float(np.median(smooth)), float(np.percentile(smooth, 80))
        box = tuple(slice(max(a - 4, 0), b + 5) for a, b in zip(np.argwhere(mask).min(0), np.argwhere(mask).max(0)))
        size = np.maximum(3, np.round(vv.LOCAL_PEAK_MM / spacing).astype(int) | 1)
        local = ndimage.maximum_filter(np.where(mask[box], smooth[box], tissue), size=tuple(size))
        local = ndimage.maximum_filter(local, size=3)
        expected = np.full(smooth.shape, tissue, np.float32)
        expected[box] = tissue + (smooth[box] - tissue) / np.maximum(local - tissue, 1e-3) * 2.0 * (level - tissue)
        got = vv._local_half_maximum(smooth, mask, tissue, spacing, level)
        assert got.dtype == np.float32 and np.array_equal(got, expected)


def test_a_process_without_numba_reads_without_it_and_one_with_it_reads_the_same(tmp_path):
    """The service's validator reads a CTA below ``KERNEL_VOXELS`` without numba (a small CTA's allowance does not
    count numba's runtime: 190 MB of address space); a worker, which has numba loaded for the renderer, smooths and
    measures with the volume kernels (:mod:`dsareg_engine.io.smoothing_kernels`,
    :mod:`dsareg_engine.io.medial_kernels`), and so does any process reading a grid of ``KERNEL_VOXELS`` or more (a
    whole head: its reading loads numba itself; the bound lowered here): the same model to the bit."""
    import pickle
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "parts.pickle").write_bytes(pickle.dumps(list(_case("cta", "b").volume.parts)))
    script = (
        "import hashlib, json, pickle, sys\n"
        "from dsareg_engine.io import volume_kernels\n"
        "from dsareg_engine.io.volume_io import read_volume\n"
        "from dsareg_engine.io.volume_vessels import extract_vessels\n"
        "parts = pickle.loads(open(sys.argv[1], 'rb').read())\n"
        "def model():\n"
        "    mesh = extract_vessels(read_volume(parts)).mesh\n"
        "    return hashlib.sha256(mesh.vertices.tobytes() + mesh.faces.tobytes()).hexdigest()\n"
        "without = model(); loaded = 'numba' in sys.modules\n"
        "kernels = 'dsareg_engine.io.medial_kernels' in sys.modules\n"
        "volume_kernels.KERNEL_VOXELS = 1000  # this grid now counts as a whole head's\n"
        "print(json.dumps([without, loaded, kernels, model(), 'numba' in sys.modules,\n"
        "                  'dsareg_engine.io.medial_kernels' in sys.modules]))\n"
    )
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path / "parts.pickle")], capture_output=True, check=False,
                          text=True, timeout=300, cwd=Path(__file__).resolve().parents[3])
    assert done.returncode == 0, done.stderr[-2000:]
    without, loaded, kernels_before, with_numba, loaded_after, kernels_after = json.loads(
        done.stdout.strip().splitlines()[-1])
    assert not loaded and not kernels_before and loaded_after and kernels_after
    assert with_numba == without


def test_a_block_of_cancellous_bone_apart_from_the_tree_is_set_aside():
    """A clivus-like block (cancellous bone in the vessels' window inside a cortical shell) is thick, not a plate:
    its core is read as vessel. As a separate piece whose surface lies against bone it is set aside and recorded as
    a decision; the volume is read again with the vessels' level estimated without the block's voxels, and the model
    is the tree's."""
    import dataclasses

    volume, plain = _read("cta", "a")
    data = np.array(volume.data, np.float32)
    corner = _apart_from_the_tree("cta", volume, data, 40.0, 150.0)
    block = tuple(slice(c - 6, c + 6) for c in corner)
    core = tuple(slice(c - 4, c + 4) for c in corner)
    data[block] = 1500.0  # the cortex ...
    data[core] = 400.0 + 60.0 * np.random.default_rng(1).standard_normal(data[core].shape)  # ... and cancellous core
    extraction = extract_vessels(dataclasses.replace(volume, data=data))
    assert abs(extraction.readout.voxels_kept - plain.readout.voxels_kept) < 0.03 * plain.readout.voxels_kept
    assert extraction.readout.components == 1 and not extraction.kept[core].any()
    model_to_truth, truth_to_model = _distances(extraction.mesh, _case("cta", "a").volume.tree)
    assert np.percentile(model_to_truth, 99) < 2.0 * VOXEL_MM and np.percentile(truth_to_model, 95) < 1.5 * VOXEL_MM
    assert extraction.excluded[core].any()  # shown as set aside in the picture
    (pieces,) = [d for d in extraction.readout.decisions if d.what == "pieces in bone"]
    assert pieces.chosen == "1 set aside" and not pieces.close  # thick and along bone: no close call of its surface
    assert not [d for d in plain.readout.decisions if d.what == "pieces in bone"]  # one piece: nothing decided


def _apart_from_the_tree(kind: str, volume, data: np.ndarray, tissue: float, spread: float) -> tuple[int, ...]:
    """A voxel whose 16³ neighbourhood is the brain's tissue (within ``spread`` of ``tissue``), 10 voxels or more
    from the tree."""
    tree = _case(kind, "a").volume.tree.vertices
    tree_index = (np.linalg.inv(volume.affine) @ np.c_[tree, np.ones(len(tree))].T)[:3].T

    def fits(corner):
        block = tuple(slice(c - 8, c + 8) for c in corner)
        return (min(corner) >= 8 and all(c + 8 <= n for c, n in zip(corner, data.shape))
                and np.all(np.abs(data[block] - tissue) < spread)
                and np.min(np.linalg.norm(tree_index - corner, axis=1)) > 10.0)

    return next(c for c in np.ndindex(*data.shape) if c[0] % 4 == c[1] % 4 == c[2] % 4 == 0 and fits(c))


def test_a_second_vessel_piece_in_an_mra_s_tissue_stays():
    """An MRA reading of two pieces (the tree and a short vessel apart from it, in tissue): the pieces' bone is the
    MRA's (its voids and scalp shell), and the piece in tissue is kept, recorded as a decision with its margin."""
    import dataclasses

    volume, plain = _read("mra", "a")
    data = np.array(volume.data, np.float32)
    tissue = float(np.median(data[data > np.percentile(data, 60)]))
    centre = _apart_from_the_tree("mra", volume, data, tissue, 0.5 * tissue)
    bright = float(np.percentile(data[plain.kept], 75))
    data[centre[0] - 6:centre[0] + 6, centre[1] - 1:centre[1] + 2, centre[2] - 1:centre[2] + 2] = bright
    extraction = extract_vessels(dataclasses.replace(volume, data=data))
    (pieces,) = [d for d in extraction.readout.decisions if d.what == "pieces in bone"]
    assert pieces.chosen == "none" and pieces.measure < pieces.threshold
    assert extraction.readout.components == 2 and extraction.readout.voxels_kept > plain.readout.voxels_kept


def _with_a_vault_sinus(volume, data: np.ndarray, hu: float, radius_mm: float = 3.0) -> np.ndarray:
    """``data`` with a dural sinus painted at ``hu``: a tube of ``radius_mm`` whose lumen lies against the skull's
    inner table over the vault, in the midline plane (a superior sagittal sinus), found by rays from the skull's
    centre to its bone."""
    spacing = np.asarray(volume.spacing_mm, float)
    bone = data > 1000.0
    centre = np.argwhere(bone).mean(0)
    up = np.linalg.inv(volume.affine[:3, :3]) @ np.array([0.0, 0.0, 1.0])  # the world's z in index steps
    side = np.linalg.inv(volume.affine[:3, :3]) @ np.array([1.0, 0.0, 0.0])
    up, side = up / np.linalg.norm(up * spacing), side / np.linalg.norm(side * spacing)  # 1 mm per step
    points = []
    for angle in np.radians(np.linspace(15.0, 165.0, 120)):
        direction = np.cos(angle) * side + np.sin(angle) * up
        steps = np.arange(0.0, 200.0, 0.25)
        along = np.round(centre + steps[:, None] * direction).astype(int)
        inside = np.all((along >= 0) & (along < data.shape), axis=1)
        hit = np.flatnonzero(bone[tuple(along[inside].T)])[0]
        points.append(centre + (steps[hit] - radius_mm - 0.5) * direction)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in data.shape], indexing="ij"), axis=-1).reshape(-1, 3)
    near = cKDTree(np.array(points) * spacing).query(grid * spacing)[0] <= radius_mm
    out = data.copy()
    lumen = near.reshape(data.shape) & ~bone
    out[lumen] = hu + 15.0 * np.random.default_rng(2).standard_normal(int(lumen.sum()))
    return out


def test_a_venous_sinus_along_the_vault_is_set_aside_and_the_level_read_without_it():
    """A CTA with venous filling: a sinus along the skull's inner table, apart from the tree and dimmer than it.
    As a separate piece whose lumen runs against bone it is set aside and recorded as a decision (no close call);
    the vessels' level is estimated again without it (else its voxels pull the window down), and the model is the
    tree's."""
    import dataclasses

    volume, plain = _read("cta", "a")
    data = _with_a_vault_sinus(volume, np.array(volume.data, np.float32), hu=230.0)
    extraction = extract_vessels(dataclasses.replace(volume, data=data))
    (sinuses,) = [d for d in extraction.readout.decisions if d.what == "venous sinuses"]
    assert sinuses.chosen == "1 set aside" and sinuses.measure > sinuses.threshold + sinuses.band
    assert extraction.readout.components == 1
    assert abs(extraction.readout.vessel_min - plain.readout.vessel_min) < 5.0  # read without the sinus
    model_to_truth, truth_to_model = _distances(extraction.mesh, _case("cta", "a").volume.tree)
    assert np.percentile(model_to_truth, 99) < 2.0 * VOXEL_MM and np.percentile(truth_to_model, 95) < 1.5 * VOXEL_MM
    assert extraction.excluded[data > 200.0].any()  # shown as set aside in the picture
    assert not [d for d in plain.readout.decisions if d.what == "venous sinuses"]  # one piece: nothing decided

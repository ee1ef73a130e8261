"""A second generator of CTA / TOF-MRA heads, built to differ from :mod:`.synthetic_volumes` where readers go wrong.

* **CTA** (:func:`make_layered_cta_head`): a skull of two cortical tables (1.5 mm, 1600 HU) around a diploë of
  cancellous bone (3 mm, 450 ± 80 HU: inside the vessels' HU window), a skull base of a cancellous core
  (550 HU, 8 mm) between cortical plates, which the trunk crosses; noise correlated along the slice axis
  (streaks), its σ rising toward the skull base.
* **TOF-MRA** (:func:`make_layered_mra_head`): a smooth multiplicative coil inhomogeneity (±25 %), a slab of
  bright marrow fat in the skull base deeper than the scalp (as the clivus is) between dark cortical plates (the
  CTA's skull base: marrow lies inside bone), Rician noise.
* **Cisterns** (``cisterns``, off by default; :mod:`.cisterns`): CSF around the proximal tree above the skull base,
  8 HU in the CTA, 100 in the TOF-MRA (0.43 of the brain's 230; bone 50, air 0: CSF has a signal, bone none).

Any tree can be placed (``tree``: the phantom's, or the paper's mesh turned trunk-up); voxels may be
anisotropic (``voxel_mm`` per axis). The series are written by :mod:`.synthetic_volume_dicom` (layout "a").
"""

from __future__ import annotations

import numpy as np

from ..mesh import TriangleMesh
from .cisterns import CSF_HU, Cisterns, cistern_mask
from .dural_sinuses import VENOUS_HU, dural_sinuses
from .synthetic_volumes import SyntheticVolume, _smooth_field, vessel_tree

CTA_LEVELS = {"air": -1000.0, "scalp": 30.0, "table": 1600.0, "diploe": 450.0, "brain": 38.0, "vessel": 380.0,
              "base_core": 550.0, "base_cortex": 1400.0, "csf": CSF_HU}
MRA_LEVELS = {"air": 0.0, "scalp": 200.0, "fat": 480.0, "bone": 50.0, "brain": 230.0, "vessel": 600.0,
              "vessel_distal": 470.0, "marrow": 520.0, "csf": 100.0}
TABLE_MM, DIPLOE_MM, SCALP_MM = 1.5, 3.0, 5.0
BASE_MM, BASE_CORTEX_MM = 8.0, 1.5
FINE_MM = 0.15  # the finest grid the tree is filled on


def _grid(tree: TriangleMesh, voxel_mm: np.ndarray, min_head_mm=(45.0, 55.0, 45.0), grid_vox=None,
          diploe_mm: float = DIPLOE_MM):
    """The head's grid around the tree: its LPS mm coordinates per axis (three arrays shaped to broadcast over the
    grid: (X, 1, 1), (1, Y, 1), (1, 1, Z); a full (X, Y, Z, 3) array is GBs at 0.3 mm), the depth under the
    skull's inner surface (mm, outward positive), the affine, and the tree's occupancy on the grid.
    ``grid_vox``: a scanner's grid (e.g. 512 × 512 × 440) instead of the head's box: the head centred in x and y,
    the grid's first slice ``8 mm`` below the tree (a head CTA starts at the skull base), air around."""
    low, high = tree.vertices.min(0), tree.vertices.max(0)
    centre, inner = _skull(tree, min_head_mm)
    outer = inner + 2 * TABLE_MM + diploe_mm + SCALP_MM + 6.0
    origin = np.array([centre[0] - outer[0], centre[1] - outer[1], low[2] - 8.0])
    shape = np.ceil((np.array([2 * outer[0], 2 * outer[1], centre[2] + outer[2] - origin[2]])) / voxel_mm).astype(int)
    if grid_vox is not None:
        shape = np.asarray(grid_vox, int)
        origin[:2] = centre[:2] - shape[:2] * voxel_mm[:2] / 2.0
    affine = np.diag([*voxel_mm, 1.0])
    affine[:3, 3] = origin
    axes = [origin[a] + np.arange(shape[a], dtype=np.float32) * np.float32(voxel_mm[a]) for a in range(3)]
    axes = [axis.reshape([-1 if b == a else 1 for b in range(3)]) for a, axis in enumerate(axes)]
    depth = (np.sqrt(sum(((axes[a] - centre[a]) / inner[a]) ** 2 for a in range(3))) - 1.0) * float(np.mean(inner))
    return axes, depth.astype(np.float32), affine, _occupancy(tree, affine, shape), (low, high)


def _skull(tree: TriangleMesh, min_head_mm) -> tuple[np.ndarray, np.ndarray]:
    """The skull's centre and inner half-extents (LPS mm) around ``tree``: 14 mm beside it, 10 mm above and below,
    at least ``min_head_mm``; the centre 8 mm above the tree's (the vault is higher than the skull base is low)."""
    low, high = tree.vertices.min(0), tree.vertices.max(0)
    inner = np.maximum((high - low) / 2.0 + np.array([14.0, 14.0, 10.0]), min_head_mm)
    return (low + high) / 2.0 + np.array([0.0, 0.0, 8.0]), inner


def _occupancy(tree: TriangleMesh, affine: np.ndarray, shape) -> np.ndarray:
    """Partial-volume occupancy [0, 1] of the tree on the grid (2–4 samples per axis per voxel, inside test; the
    fine grid no finer than ``FINE_MM``, which bounds its memory at small voxels and a large tree)."""
    import trimesh

    solid = trimesh.Trimesh(tree.vertices, tree.faces, process=False)
    spacing = np.diag(affine)[:3]
    fine = float(spacing.min()) / float(np.clip(np.floor(float(spacing.min()) / FINE_MM + 1e-6), 2, 4))
    voxels = solid.voxelized(fine).fill()
    grid = voxels.matrix.astype(np.float32)
    origin = voxels.transform[:3, 3]  # centre of fine voxel 0
    from scipy import ndimage

    # the fine occupancy sampled at each coarse voxel, averaged over the voxel (box filter, then trilinear)
    box = np.maximum(1, np.round(spacing / fine).astype(int))
    smooth = ndimage.uniform_filter(grid, size=tuple(box))
    # an even box's mean at index i is centred half a fine voxel before it (its window is i - box//2 … i + box//2 - 1):
    # sampled half a voxel later, every axis's box is centred on the coarse voxel's centre (0.1 mm at 0.4-mm voxels)
    centring = box // 2 - (box - 1) / 2.0
    first = np.maximum(np.floor((tree.vertices.min(0) - affine[:3, 3]) / spacing).astype(int) - 2, 0)
    last = np.minimum(np.ceil((tree.vertices.max(0) - affine[:3, 3]) / spacing).astype(int) + 3, shape)
    ijk = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(first, last)], indexing="ij"), -1)
    where = (ijk.reshape(-1, 3) * spacing + affine[:3, 3] - origin) / fine + centring
    out = np.zeros(tuple(shape), np.float32)
    box_values = ndimage.map_coordinates(smooth, where.T, order=1, mode="constant").reshape(ijk.shape[:3])
    out[first[0]:last[0], first[1]:last[1], first[2]:last[2]] = box_values
    return out


def _finish(volume, noise_sigma, rng, *, streak_axis: int | None, rician: bool, blur_vox: float = 0.6):
    from scipy import ndimage

    blurred = ndimage.gaussian_filter(volume, blur_vox)

    def noise():
        white = rng.standard_normal(volume.shape).astype(np.float32)
        if streak_axis is not None:  # correlated along one axis (streaks), then back to unit variance
            sigma = [0.3, 0.3, 0.3]
            sigma[streak_axis] = 1.5
            white = ndimage.gaussian_filter(white, sigma)
            white /= white.std() + 1e-12
        return white * noise_sigma

    if rician:
        return np.sqrt((blurred + noise()) ** 2 + noise() ** 2).astype(np.float32)
    return (blurred + noise()).astype(np.float32)


def _fill_cisterns(volume, brain, occupancy, spacing, z, floor_z_mm: float, cisterns: Cisterns | None, csf: float):
    """Set the cisterns' voxels (in the brain, above the skull base's top ``floor_z_mm``) to ``csf``, in place."""
    if cisterns is not None:
        volume[cistern_mask(occupancy, spacing, z, floor_z_mm, cisterns) & brain] = csf


def make_layered_cta_head(*, voxel_mm=0.6, tree: TriangleMesh | None = None, seed: int = 3,
                          min_head_mm=(45.0, 55.0, 45.0), cisterns: Cisterns | None = None,
                          grid_vox=None, diploe_mm: float = DIPLOE_MM, sinuses: str | None = None) -> SyntheticVolume:
    """A CTA series of ``tree`` (default: the phantom's) in a skull with diploë (``diploe_mm`` thick: 2–8 mm in
    adults, most of a whole head's voxels in the vessels' window) and a cancellous skull base; CSF cisterns around
    its proximal part when ``cisterns`` is given; filled dural venous sinuses (:mod:`.dural_sinuses`: a CTA taken
    late) when ``sinuses`` names their section (``"triangle"``, ``"round"``)."""
    from .synthetic_volume_dicom import cta_series

    rng = np.random.default_rng(seed + 303)
    tree = tree if tree is not None else vessel_tree(3, seed)
    spacing = np.broadcast_to(np.asarray(voxel_mm, float), (3,)).copy()
    axes, depth, affine, occupancy, (low, _) = _grid(tree, spacing, min_head_mm, grid_vox, diploe_mm)
    level = CTA_LEVELS
    volume = np.full(depth.shape, level["air"], np.float32)
    volume[depth < 2 * TABLE_MM + diploe_mm + SCALP_MM] = level["scalp"]
    volume[(depth >= 0) & (depth < 2 * TABLE_MM + diploe_mm)] = level["table"]
    diploe = (depth >= TABLE_MM) & (depth < TABLE_MM + diploe_mm)
    texture = _smooth_field(rng, depth.shape, 1.0 / float(spacing.mean()))
    volume[diploe] = level["diploe"] + 80.0 * texture[diploe]
    brain = depth < 0
    volume[brain] = level["brain"] + 6.0 * _smooth_field(rng, depth.shape, 3.0 / float(spacing.mean()))[brain]
    z = axes[2]
    base = brain & (z >= low[2] + 4.0) & (z < low[2] + 4.0 + BASE_MM)
    volume[base] = level["base_cortex"]
    core = brain & (z >= low[2] + 4.0 + BASE_CORTEX_MM) & (z < low[2] + 4.0 + BASE_MM - BASE_CORTEX_MM)
    volume[core] = level["base_core"] + 80.0 * texture[core]
    _fill_cisterns(volume, brain, occupancy, spacing, z, low[2] + 4.0 + BASE_MM, cisterns, level["csf"])
    if sinuses:
        veins = dural_sinuses(axes, depth, *_skull(tree, min_head_mm), section=sinuses)
        volume[veins] = VENOUS_HU + 20.0 * texture[veins]
        del veins
    volume = volume * (1.0 - occupancy) + level["vessel"] * occupancy
    sigma = 9.0 + 10.0 * np.clip(1.0 - (z - low[2]) / 40.0, 0.0, 1.0)  # noisier toward the skull base
    data = _finish(volume, sigma.astype(np.float32), rng, streak_axis=2, rician=False)
    parts, data, affine, study_uid = cta_series(data, affine, "a")
    return SyntheticVolume(parts, tree, data, affine, "cta", study_uid)


def make_layered_mra_head(*, voxel_mm=0.6, tree: TriangleMesh | None = None, seed: int = 3,
                          min_head_mm=(45.0, 55.0, 45.0), cisterns: Cisterns | None = None,
                          grid_vox=None) -> SyntheticVolume:
    """A TOF-MRA series of ``tree`` with a coil inhomogeneity and bright marrow fat in the skull base; CSF cisterns
    around its proximal part when ``cisterns`` is given."""
    from .synthetic_volume_dicom import mra_series

    rng = np.random.default_rng(seed + 404)
    tree = tree if tree is not None else vessel_tree(3, seed)
    spacing = np.broadcast_to(np.asarray(voxel_mm, float), (3,)).copy()
    axes, depth, affine, occupancy, (low, high) = _grid(tree, spacing, min_head_mm, grid_vox)
    level = MRA_LEVELS
    skull = 2 * TABLE_MM + DIPLOE_MM
    volume = np.full(depth.shape, level["air"], np.float32)
    volume[depth < skull + SCALP_MM] = level["scalp"]
    volume[(depth >= skull + 1.0) & (depth < skull + SCALP_MM - 1.5)] = level["fat"]
    volume[(depth >= 0) & (depth < skull)] = level["bone"]
    brain = depth < 0
    volume[brain] = level["brain"] + 20.0 * _smooth_field(rng, depth.shape, 3.0 / float(spacing.mean()))[brain]
    z = axes[2]
    base = (z >= low[2] + 4.0) & (z < low[2] + 4.0 + BASE_MM)
    volume[base & (depth < -10.0 + BASE_CORTEX_MM)] = level["bone"]  # cortical plates around the marrow
    core = (z >= low[2] + 4.0 + BASE_CORTEX_MM) & (z < low[2] + 4.0 + BASE_MM - BASE_CORTEX_MM)
    volume[core & (depth < -10.0)] = level["marrow"]
    _fill_cisterns(volume, brain, occupancy, spacing, z, low[2] + 4.0 + BASE_MM, cisterns, level["csf"])
    fraction = np.clip((z - low[2]) / max(high[2] - low[2], 1e-6), 0.0, 1.0)
    vessel = level["vessel"] + (level["vessel_distal"] - level["vessel"]) * fraction
    volume = volume * (1.0 - occupancy) + vessel * occupancy
    along = sum((axis - axis.mean()) * w for axis, w in zip(axes, (0.6, -0.3, 0.74)))  # from the grid's centre
    gain = 1.0 + 0.25 * np.tanh(along / 60.0)  # coil inhomogeneity
    data = _finish(volume * gain.astype(np.float32), 12.0, rng, streak_axis=None, rician=True)
    parts, data, affine, study_uid = mra_series(data, affine, "a")
    return SyntheticVolume(parts, tree, data, affine, "mra", study_uid)


__all__ = ["make_layered_cta_head", "make_layered_mra_head"]

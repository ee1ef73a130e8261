"""Synthetic head volumes around the built-in vessel tree: a CTA-like and a TOF-MRA-like DICOM series.

Both place the phantom tree (:func:`dsareg_engine.phantom.make_vessel_phantom`, its trunk turned to run
along +z, superior) inside an ellipsoidal head, in patient LPS mm, and return the series' files with the
tree's true surface in the same frame, so a case built from them has a known answer.

* **CTA** (:func:`make_cta_head`): air −1000 HU, scalp, a skull shell (bone HU), brain (~35 HU with a
  faint texture), a skull-base slab (bone) that the trunk crosses as through the carotid canal (the lumen
  replaces bone there), vessels at the contrast HU; partial volume (2× supersampled occupancy), a Gaussian
  point-spread blur, then noise.
* **TOF-MRA** (:func:`make_tof_mra_head`): Rician noise in air, bright scalp fat, dark skull, a CSF rim,
  textured brain, bright vessels (dimmer toward the distal tree, as in-flow saturation does).

``variant`` "a" and "b" differ in what a reader must not be tuned to: levels (HU / intensity), noise
model (white Gaussian vs correlated; Rician σ), blur, and the tag layout (slice order, orientation,
rescale, which of Modality / Image Type / Contrast-Bolus / angio tags are present).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mesh import TriangleMesh

TRUNK_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Phantom frame → LPS: the phantom's trunk direction (+y) becomes superior (+z)."""


@dataclass(frozen=True)
class HeadLevels:
    """Tissue levels of one synthetic head (HU for CTA, arbitrary units for MRA)."""

    air: float
    scalp: float
    bone: float
    brain: float
    vessel: float
    skull_base: float | None = None  # CTA only
    fat: float | None = None  # MRA only: scalp fat
    csf: float | None = None  # MRA only
    vessel_distal: float | None = None  # MRA only: the vessel level at the top of the tree


@dataclass(frozen=True)
class HeadVariant:
    levels: HeadLevels
    blur_vox: float  # Gaussian σ of the point-spread function, voxels
    noise: float  # σ (HU or intensity)
    noise_correlation_vox: float  # 0: white; else the noise is smoothed by this σ and rescaled
    texture: float  # amplitude of the brain's smooth texture


CTA_VARIANTS = {
    "a": HeadVariant(HeadLevels(air=-1000, scalp=40, bone=1200, brain=35, vessel=350, skull_base=900),
                     blur_vox=0.5, noise=8.0, noise_correlation_vox=0.0, texture=5.0),
    "b": HeadVariant(HeadLevels(air=-1010, scalp=-80, bone=1550, brain=42, vessel=430, skull_base=1050),
                     blur_vox=0.8, noise=14.0, noise_correlation_vox=0.8, texture=8.0),
}
MRA_VARIANTS = {
    "a": HeadVariant(HeadLevels(air=0, scalp=180, bone=40, brain=210, vessel=560, fat=430, csf=90,
                                vessel_distal=480),
                     blur_vox=0.5, noise=8.0, noise_correlation_vox=0.0, texture=25.0),
    "b": HeadVariant(HeadLevels(air=0, scalp=250, bone=60, brain=300, vessel=720, fat=640, csf=140,
                                vessel_distal=520),
                     blur_vox=0.8, noise=15.0, noise_correlation_vox=0.0, texture=40.0),
}


@dataclass
class SyntheticVolume:
    """A synthetic series and its truth.

    Attributes:
        parts: the DICOM files of the series.
        tree: the vessel tree's true surface, LPS mm (the frame of the volume).
        data, affine: the voxels written (float, ``[i, j, k]``) and voxel → LPS mm.
        kind: ``"cta"`` or ``"mra"``.
    """

    parts: list[bytes]
    tree: TriangleMesh
    data: np.ndarray
    affine: np.ndarray
    kind: str
    tags: dict = field(default_factory=dict)


def vessel_tree(depth: int = 3, seed: int = 3) -> TriangleMesh:
    """The phantom tree in LPS mm, trunk along +z, centred on its vertex mean."""
    from .phantom import make_vessel_phantom

    phantom = make_vessel_phantom(depth=depth, seed=seed)
    return TriangleMesh(np.ascontiguousarray(phantom.vertices @ TRUNK_UP.T), phantom.faces)


def _tree_occupancy(tree: TriangleMesh, voxel_mm: float, margin_mm: float):
    """Partial-volume occupancy [0, 1] of the tree on a grid ``voxel_mm`` wide around it plus ``margin_mm``."""
    from .phantom_study import voxelize_mesh

    margin = int(np.ceil(margin_mm / voxel_mm / 2.0))  # voxelize_mesh pads 2 × margin coarse voxels
    occupancy, affine = voxelize_mesh(tree, voxel_mm, margin=margin)
    return occupancy / 800.0, affine


def _smooth_field(rng, shape, sigma_vox: float) -> np.ndarray:
    """Unit-variance Gaussian-smoothed white noise (the brain's texture)."""
    from scipy import ndimage

    field = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma_vox)
    return field / (field.std() + 1e-12)


def _compose(tree: TriangleMesh, voxel_mm: float, levels: HeadLevels, kind: str, rng, texture: float):
    """Noise-free voxels before blur, the affine, and the head's inner semi-axes."""
    skull_mm, scalp_mm = 4.0, 5.0 if kind == "cta" else 6.0
    occupancy, affine = _tree_occupancy(tree, voxel_mm, margin_mm=0.0)
    low, high = tree.vertices.min(0), tree.vertices.max(0)
    inner = np.maximum((high - low) / 2.0 + np.array([14.0, 14.0, 10.0]), [45.0, 55.0, 45.0])
    centre = (low + high) / 2.0 + np.array([0.0, 0.0, 8.0])
    outer = inner + skull_mm + scalp_mm + 6.0  # air around the head
    bottom = low[2] - 8.0  # the volume's lowest slice: through the neck, below the trunk's start
    origin = np.array([centre[0] - outer[0], centre[1] - outer[1], bottom])
    shape = np.ceil((np.array([2 * outer[0], 2 * outer[1], centre[2] + outer[2] - bottom])) / voxel_mm).astype(int)
    head_affine = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    shift = np.round((origin - affine[:3, 3]) / voxel_mm).astype(int)  # align the grids
    head_affine[:3, 3] = affine[:3, 3] + shift * voxel_mm
    ijk = np.stack(np.meshgrid(*[np.arange(n, dtype=np.float32) for n in shape], indexing="ij"), -1)
    points = ijk * np.float32(voxel_mm) + head_affine[:3, 3].astype(np.float32)
    del ijk
    radius = np.sqrt((((points - centre) / inner) ** 2).sum(-1))
    mean_inner = float(np.mean(inner))
    depth_mm = (radius - 1.0) * mean_inner  # ~ mm outward from the skull's inner surface
    volume = np.full(shape, levels.air, np.float32)
    head = depth_mm < skull_mm + scalp_mm
    volume[head] = levels.scalp
    if kind == "mra":
        fat = (depth_mm >= skull_mm + 1.0) & (depth_mm < skull_mm + scalp_mm - 1.5)
        volume[fat] = levels.fat
    volume[(depth_mm >= 0) & (depth_mm < skull_mm)] = levels.bone
    brain = depth_mm < 0
    volume[brain] = levels.brain + texture * _smooth_field(rng, shape, 3.0 / voxel_mm)[brain]
    if kind == "mra":
        volume[(depth_mm < 0) & (depth_mm >= -2.0)] = levels.csf
    if kind == "cta":  # the skull base: a slab the trunk crosses (the carotid canal)
        z = points[..., 2]
        slab = brain & (z >= low[2] + 5.0) & (z < low[2] + 13.0)
        volume[slab] = levels.skull_base
    vessel = np.full(shape, levels.vessel, np.float32)
    if levels.vessel_distal is not None:  # in-flow saturation: dimmer toward the top of the tree
        fraction = np.clip((points[..., 2] - low[2]) / max(high[2] - low[2], 1e-6), 0.0, 1.0)
        vessel = levels.vessel + (levels.vessel_distal - levels.vessel) * fraction
    del points
    occ = np.zeros(shape, np.float32)
    start = -shift
    region = tuple(slice(max(0, s), min(n, s + m)) for s, n, m in zip(start, shape, occupancy.shape))
    source = tuple(slice(r.start - s, r.stop - s) for r, s in zip(region, start))
    occ[region] = occupancy[source]
    volume = volume * (1.0 - occ) + vessel * occ
    return volume.astype(np.float32), head_affine


def _finish(volume: np.ndarray, variant: HeadVariant, rng, rician: bool) -> np.ndarray:
    from scipy import ndimage

    blurred = ndimage.gaussian_filter(volume, variant.blur_vox) if variant.blur_vox > 0 else volume
    def noise():
        n = rng.standard_normal(volume.shape).astype(np.float32)
        if variant.noise_correlation_vox > 0:
            n = ndimage.gaussian_filter(n, variant.noise_correlation_vox)
            n /= n.std() + 1e-12
        return n * np.float32(variant.noise)
    if rician:  # magnitude of a complex signal with Gaussian noise in both channels
        return np.sqrt((blurred + noise()) ** 2 + noise() ** 2).astype(np.float32)
    return (blurred + noise()).astype(np.float32)


def make_cta_head(variant: str = "a", *, voxel_mm: float = 0.8, depth: int = 3, seed: int = 3) -> SyntheticVolume:
    """A CTA-like DICOM series (CT, HU) of the tree in a head with skull and skull base."""
    from .synthetic_volume_dicom import cta_series

    spec = CTA_VARIANTS[variant]
    rng = np.random.default_rng(seed + 101)
    tree = vessel_tree(depth, seed)
    volume, affine = _compose(tree, voxel_mm, spec.levels, "cta", rng, spec.texture)
    data = _finish(volume, spec, rng, rician=False)
    parts, data, affine = cta_series(data, affine, variant)
    return SyntheticVolume(parts, tree, data, affine, "cta")


def make_tof_mra_head(variant: str = "a", *, voxel_mm: float = 0.8, depth: int = 3, seed: int = 3) -> SyntheticVolume:
    """A TOF-MRA-like DICOM series (MR) of the tree in a head with bright scalp fat and dark bone."""
    from .synthetic_volume_dicom import mra_series

    spec = MRA_VARIANTS[variant]
    rng = np.random.default_rng(seed + 202)
    tree = vessel_tree(depth, seed)
    volume, affine = _compose(tree, voxel_mm, spec.levels, "mra", rng, spec.texture)
    data = _finish(volume, spec, rng, rician=True)
    parts, data, affine = mra_series(data, affine, variant)
    return SyntheticVolume(parts, tree, data, affine, "mra")


__all__ = ["CTA_VARIANTS", "MRA_VARIANTS", "SyntheticVolume", "make_cta_head", "make_tof_mra_head", "vessel_tree"]

"""Synthetic head volumes around the built-in vessel tree: a CTA-like and a TOF-MRA-like DICOM series.

Both place the phantom tree (:func:`dsareg_engine.simulation.phantom.make_vessel_phantom`, its trunk turned to run
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

from dataclasses import dataclass

import numpy as np

from ..mesh import TriangleMesh

MIN_HEAD_MM = (45.0, 55.0, 45.0)
"""Smallest semi-axes (x, y, z) of the skull's inner surface; the tree adds its own extent + a margin."""
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
    study_uid: str = ""


def vessel_tree(depth: int = 3, seed: int = 3) -> TriangleMesh:
    """The phantom tree in LPS mm, trunk along +z, centred on its vertex mean."""
    from .phantom import make_vessel_phantom

    phantom = make_vessel_phantom(depth=depth, seed=seed)
    return TriangleMesh(np.ascontiguousarray(phantom.vertices @ TRUNK_UP.T), phantom.faces)


def _tree_occupancy(tree: TriangleMesh, voxel_mm, margin_mm: float):
    """Partial-volume occupancy [0, 1] of the tree on a grid of ``voxel_mm`` (one or per axis) around it plus
    ``margin_mm``."""
    from .phantom_study import voxelize_mesh

    margin = int(np.ceil(margin_mm / float(np.min(voxel_mm)) / 2.0))  # voxelize_mesh pads 2 × margin fine voxels
    occupancy, affine = voxelize_mesh(tree, voxel_mm, margin=margin)
    return occupancy / 800.0, affine


def _smooth_field(rng, shape, sigma_vox: float) -> np.ndarray:
    """Unit-variance Gaussian-smoothed white noise (the brain's texture)."""
    from scipy import ndimage

    field = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), sigma_vox)
    return field / (field.std() + 1e-12)


def _compose(tree: TriangleMesh, voxel_mm, levels: HeadLevels, kind: str, rng, texture: float,
             min_head_mm=MIN_HEAD_MM):
    """Noise-free voxels before blur, and the affine (``voxel_mm``: one size or one per axis)."""
    skull_mm, scalp_mm = 4.0, 5.0 if kind == "cta" else 6.0
    spacing = np.broadcast_to(np.asarray(voxel_mm, float), (3,)).copy()
    occupancy, affine = _tree_occupancy(tree, spacing, margin_mm=0.0)
    low, high = tree.vertices.min(0), tree.vertices.max(0)
    inner = np.maximum((high - low) / 2.0 + np.array([14.0, 14.0, 10.0]), min_head_mm)
    centre = (low + high) / 2.0 + np.array([0.0, 0.0, 8.0])
    outer = inner + skull_mm + scalp_mm + 6.0  # air around the head
    bottom = low[2] - 8.0  # the volume's lowest slice: through the neck, below the trunk's start
    origin = np.array([centre[0] - outer[0], centre[1] - outer[1], bottom])
    shape = np.ceil((np.array([2 * outer[0], 2 * outer[1], centre[2] + outer[2] - bottom])) / spacing).astype(int)
    head_affine = np.diag([*spacing, 1.0])
    shift = np.round((origin - affine[:3, 3]) / spacing).astype(int)  # align the grids
    head_affine[:3, 3] = affine[:3, 3] + shift * spacing
    # per-axis coordinates broadcast over the grid (an (X, Y, Z, 3) array of points is GBs at 0.3 mm)
    axes = [(np.arange(n, dtype=np.float32) * np.float32(spacing[a]) + np.float32(head_affine[a, 3])).reshape(
        [-1 if b == a else 1 for b in range(3)]) for a, n in enumerate(shape)]
    radius = np.sqrt(sum(((axes[a] - centre[a]) / inner[a]) ** 2 for a in range(3)))
    depth_mm = (radius - 1.0) * float(np.mean(inner))  # ~ mm outward from the skull's inner surface
    del radius
    volume = np.full(shape, levels.air, np.float32)
    volume[depth_mm < skull_mm + scalp_mm] = levels.scalp
    if kind == "mra":
        volume[(depth_mm >= skull_mm + 1.0) & (depth_mm < skull_mm + scalp_mm - 1.5)] = levels.fat
    volume[(depth_mm >= 0) & (depth_mm < skull_mm)] = levels.bone
    brain = depth_mm < 0
    volume[brain] = levels.brain + texture * _smooth_field(rng, shape, tuple(3.0 / spacing))[brain]
    if kind == "mra":
        volume[(depth_mm < 0) & (depth_mm >= -2.0)] = levels.csf
    z = np.broadcast_to(axes[2], volume.shape)
    if kind == "cta":  # the skull base: a slab the trunk crosses (the carotid canal)
        volume[brain & (z >= low[2] + 5.0) & (z < low[2] + 13.0)] = levels.skull_base
    del brain, depth_mm
    vessel = np.float32(levels.vessel)
    if levels.vessel_distal is not None:  # in-flow saturation: dimmer toward the top of the tree
        fraction = np.clip((axes[2] - low[2]) / max(high[2] - low[2], 1e-6), 0.0, 1.0)
        vessel = levels.vessel + (levels.vessel_distal - levels.vessel) * fraction
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


def make_cta_head(variant: str = "a", *, voxel_mm=0.8, depth: int = 3, seed: int = 3,
                  min_head_mm=MIN_HEAD_MM, tree: TriangleMesh | None = None) -> SyntheticVolume:
    """A CTA-like DICOM series (CT, HU) of ``tree`` (default: the phantom's of ``depth``, ``seed``) in a head with
    skull and skull base; ``voxel_mm`` one size or one per axis (the slices along the third)."""
    from .synthetic_volume_dicom import cta_series

    spec = CTA_VARIANTS[variant]
    rng = np.random.default_rng(seed + 101)
    tree = tree if tree is not None else vessel_tree(depth, seed)
    volume, affine = _compose(tree, voxel_mm, spec.levels, "cta", rng, spec.texture, min_head_mm)
    data = _finish(volume, spec, rng, rician=False)
    parts, data, affine, study_uid = cta_series(data, affine, variant)
    return SyntheticVolume(parts, tree, data, affine, "cta", study_uid)


def make_tof_mra_head(variant: str = "a", *, voxel_mm=0.8, depth: int = 3, seed: int = 3,
                      min_head_mm=MIN_HEAD_MM, tree: TriangleMesh | None = None) -> SyntheticVolume:
    """A TOF-MRA-like DICOM series (MR) of ``tree`` (default: the phantom's) in a head with bright scalp fat and
    dark bone; ``voxel_mm`` one size or one per axis."""
    from .synthetic_volume_dicom import mra_series

    spec = MRA_VARIANTS[variant]
    rng = np.random.default_rng(seed + 202)
    tree = tree if tree is not None else vessel_tree(depth, seed)
    volume, affine = _compose(tree, voxel_mm, spec.levels, "mra", rng, spec.texture, min_head_mm)
    data = _finish(volume, spec, rng, rician=True)
    parts, data, affine, study_uid = mra_series(data, affine, variant)
    return SyntheticVolume(parts, tree, data, affine, "mra", study_uid)


@dataclass
class VolumeCase:
    """A head volume and the biplane XA pair (AP / LAT, geometry in their tags) of its true tree at ``mesh_to_world``."""

    volume: SyntheticVolume
    ap: bytes
    lat: bytes
    mesh_to_world: np.ndarray


def default_pose() -> np.ndarray:
    """6° about an oblique axis and (3, −2, 3.5) mm: the pose the DICOM phantom study uses."""
    from ..geometry.pose import make_transform

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(6.0)
    return make_transform(np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k, np.array([3.0, -2.0, 3.5]))


def make_volume_case(kind: str = "cta", variant: str = "a", *, voxel_mm=0.8, depth: int = 3, seed: int = 3,
                     image_px: int = 256, pixel_spacing_mm: float = 0.6, min_head_mm=MIN_HEAD_MM,
                     mesh_to_world: np.ndarray | None = None) -> VolumeCase:
    """A CTA (``kind="cta"``) or TOF-MRA (``"mra"``) head and the XA pair of its tree (the true surface, not
    what a reader extracts), seen by the DICOM phantom study's biplane (:mod:`dsareg_engine.simulation.phantom_study`)."""
    maker = {"cta": make_cta_head, "mra": make_tof_mra_head}[kind]
    volume = maker(variant, voxel_mm=voxel_mm, depth=depth, seed=seed, min_head_mm=min_head_mm)
    return volume_case_of(volume, image_px=image_px, pixel_spacing_mm=pixel_spacing_mm, mesh_to_world=mesh_to_world)


def volume_case_of(volume: SyntheticVolume, *, image_px: int = 256, pixel_spacing_mm: float = 0.6,
                   mesh_to_world: np.ndarray | None = None) -> VolumeCase:
    """The case of any synthetic head (either generator): the XA pair of its true tree at ``mesh_to_world``
    (default :func:`default_pose`), seen by the DICOM phantom study's biplane."""
    import torch

    from ..io.dicom_xa import view_from_angles
    from ..render import Camera, render_hard_silhouette
    from .phantom_study import AP_ANGLES, LAT_ANGLES, SID_MM, SOD_MM, _xa

    pose = default_pose() if mesh_to_world is None else np.asarray(mesh_to_world, float)
    vertices, faces = volume.tree.torch(torch.float64)
    images = {}
    for index, (name, angles, plane) in enumerate((("ap", AP_ANGLES, "A"), ("lat", LAT_ANGLES, "B"))):
        view = view_from_angles(angles[0], angles[1], SID_MM[index], SOD_MM[index],
                                (pixel_spacing_mm, pixel_spacing_mm), (image_px, image_px))
        mask = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                      Camera.from_view(view))[0].numpy().astype(bool)
        images[name] = _xa(mask, angles, SID_MM[index], SOD_MM[index], pixel_spacing_mm, volume.study_uid,
                           10 + index, plane)[0]
    return VolumeCase(volume, images["ap"], images["lat"], pose)


def fitting_pixel_spacing_mm(tree: TriangleMesh, image_px: int, least_mm: float = 0.6 * 256) -> float:
    """The detector pixel (mm) at which ``tree``, its vertex mean near the isocentre (within 5 mm), fills at most
    90 % of an image of ``image_px`` in any view of the phantom study's biplane; never below
    ``least_mm / image_px``."""
    from .phantom_study import SID_MM, SOD_MM

    reach_mm = float(np.abs(tree.vertices - tree.vertices.mean(0)).max()) + 5.0  # any axis may lie in the image
    magnification = max(sid / sod for sid, sod in zip(SID_MM, SOD_MM))
    return max(2.0 * reach_mm * magnification / 0.9, least_mm) / image_px


def tree_of_mesh(mesh: TriangleMesh) -> TriangleMesh:
    """A vessel mesh whose trunk runs along +y (the phantom's and the paper's convention) turned trunk-up in LPS
    (+y → superior, as :func:`vessel_tree`) and centred on its vertex mean."""
    vertices = mesh.vertices @ TRUNK_UP.T
    return TriangleMesh(np.ascontiguousarray(vertices - vertices.mean(0)), mesh.faces)


__all__ = ["CTA_VARIANTS", "MRA_VARIANTS", "SyntheticVolume", "VolumeCase", "default_pose", "fitting_pixel_spacing_mm", "make_cta_head", "make_tof_mra_head", "make_volume_case", "tree_of_mesh", "vessel_tree",
           "volume_case_of"]

"""Is a set of kept voxels shaped like vessels? Refuses a closed shell, a plate (skull, slab), far too many voxels.

Vessels are tubes: thin across in two directions, long in one. Bone and skin read by a wrong threshold
are plates (thin in one direction: the skull, a skull-base slab) or a closed shell around the head.
:func:`shape_measures` measures, on the kept voxels:

* ``enclosed_ratio``: volume with enclosed cavities filled ÷ kept volume (a shell encloses many times itself);
* ``plate_fraction``: the plate share of the kept voxels' medial axis, measured in mm on a working grid
  (:mod:`.medial_shape`: the same at every voxel size; refused above ``MAX_PLATE_FRACTION``, a close call
  within ``PLATE_BAND`` of it);
* ``solid_fraction``: of the ridge voxels (local maxima of the mask smoothed over ``HESSIAN_SIGMA_MM``, on
  a grid no finer than ``SHAPE_GRID_MM``), the share with no strong curvature at all (inside a mass far wider
  than the scale: a head's tissue read as "vessel");
* ``kept_fraction``: kept voxels ÷ all voxels.

:func:`check_vessel_shape` refuses the implausible with an error naming the volume and saying what was kept.
"""

from __future__ import annotations

import numpy as np

from ..errors import DsaregInputError
from .medial_shape import medial_shape
from .voxel_steps import bounding_box, filled_holes

SHAPE_GRID_MM = 1.0
HESSIAN_SIGMA_MM = 1.5
MAX_ENCLOSED_RATIO = 1.5
MAX_PLATE_FRACTION = 0.5
PLATE_BAND = 0.15
MAX_SOLID_FRACTION = 0.5
MAX_KEPT_FRACTION = {"cta": 0.12, "mra": 0.12, "3d-dsa": 0.2}  # CTA/MRA: a crop of the circle of Willis keeps ~6 %
RIDGE_TOLERANCE = 0.97
MIN_KEPT_VOXELS = 8
MAX_ARTERY_WIDTH_MM = 8.0  # wider than a head's largest artery (the ICA, ~5 mm; an aneurysm's neck region more)
TYPICAL_WIDTH_MM = 4.0  # the width a refused mass's thick parts are scaled to in the spacing hint


def _coarse(mask: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mask as a fraction on a grid no finer than SHAPE_GRID_MM (block means)."""
    factors = np.maximum(1, np.floor(SHAPE_GRID_MM / spacing).astype(int))
    if np.all(factors == 1):
        return mask.astype(np.float32), spacing
    shape = np.array(mask.shape) // factors * factors
    trimmed = mask[: shape[0], : shape[1], : shape[2]].astype(np.float32)
    blocks = trimmed.reshape(shape[0] // factors[0], factors[0], shape[1] // factors[1], factors[1],
                             shape[2] // factors[2], factors[2])
    return blocks.mean(axis=(1, 3, 5)), spacing * factors


def crop_to(mask: np.ndarray, margin: int = 1) -> np.ndarray:
    """``mask`` cut to its bounding box plus ``margin`` voxels (the same components, holes and ridges)."""
    box = bounding_box(mask, margin)
    return mask if box is None else mask[box]


def curvature_shares(mask: np.ndarray, spacing: np.ndarray) -> tuple[float, float]:
    """(plate share, solid share) of the structure's ridge voxels by their Hessian at ``HESSIAN_SIGMA_MM``; (0, 0)
    if empty. Only the solid share is used: the Hessian's plate share depends on the voxel size and on the
    vessels' calibre (the medial measure replaces it)."""
    from scipy import ndimage

    box = bounding_box(mask, 6)
    if box is None:
        return 0.0, 0.0
    cropped = mask[box]
    grid, grid_spacing = _coarse(cropped, np.asarray(spacing, float))
    sigma = HESSIAN_SIGMA_MM / grid_spacing
    smooth = ndimage.gaussian_filter(grid, sigma)
    ridge = (smooth >= RIDGE_TOLERANCE * ndimage.maximum_filter(smooth, 3)) & (smooth > 0.2)
    if not ridge.any():
        return 0.0, 0.0
    hessian = np.empty((np.count_nonzero(ridge), 3, 3), np.float32)
    for a in range(3):
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            value = ndimage.gaussian_filter(grid, sigma, order=order)[ridge] / (grid_spacing[a] * grid_spacing[b])
            hessian[:, a, b] = hessian[:, b, a] = value
    magnitudes = np.sort(np.abs(np.linalg.eigvalsh(hessian)), axis=1)  # ascending |λ|
    strong = magnitudes[:, 2] > 0.05 / HESSIAN_SIGMA_MM**2  # else: inside a mass wider than the scale
    plate = strong & (magnitudes[:, 1] < 0.3 * magnitudes[:, 2])
    return float(plate.mean()), float((~strong).mean())


def shape_measures(mask: np.ndarray, spacing, plate_share: float | None = None) -> dict[str, float]:
    """The measures above (``plate_share``: the medial plate share of this same mask, if already measured)."""
    kept = int(np.count_nonzero(mask))
    filled = int(np.count_nonzero(filled_holes(crop_to(mask)))) if kept else 0
    solid = curvature_shares(mask, np.asarray(spacing, float))[1]
    plate = medial_shape(mask, spacing).plate_share if plate_share is None else float(plate_share)
    return {"kept_fraction": kept / mask.size, "enclosed_ratio": filled / max(kept, 1), "plate_fraction": plate,
            "solid_fraction": solid}


def check_vessel_shape(mask: np.ndarray, spacing, readout, *, field_name: str = "volume",
                       plate_share: float | None = None, total_voxels: int | None = None) -> dict[str, float]:
    """Raise :class:`DsaregInputError` when the kept voxels cannot be vessels; else the measures
    (``plate_share``: :func:`shape_measures`'; ``total_voxels``: the volume's, when ``mask`` is a crop of it)."""
    what = readout.text() if readout is not None else "the kept voxels"
    kind = getattr(readout, "kind", "3d-dsa")
    accepted = ("a vessel model: set options.volume_kind (cta, mra, 3d-dsa) or the vessel window "
                "(options.volume_vessel_min / options.volume_vessel_max) to what the volume is")
    if kind == "labels":
        accepted = "a label map of vessels: choose its vessel labels with options.volume_labels"
    if np.count_nonzero(mask) < MIN_KEPT_VOXELS:
        raise DsaregInputError(f"no vessels in the window: {what}", field=field_name, accepted=accepted)
    limit = MAX_KEPT_FRACTION.get(kind, 0.5)
    kept_fraction = np.count_nonzero(mask) / (total_voxels or mask.size)
    if kept_fraction > limit:  # before the shape measures: on a third of a head they cost ~0.5 GB and seconds
        raise DsaregInputError(
            f"keeps {100 * kept_fraction:.1f}% of the volume, far more than vessels "
            f"(at most {100 * limit:.0f}% for {kind}): {what}", field=field_name, accepted=accepted)
    measures = shape_measures(mask, spacing, plate_share)
    measures["kept_fraction"] = kept_fraction
    if measures["enclosed_ratio"] > MAX_ENCLOSED_RATIO:
        raise DsaregInputError(
            f"the kept voxels form a closed shell (enclosing {measures['enclosed_ratio']:.1f}× their own volume: "
            f"bone or skin, not vessels): {what}", field=field_name, accepted=accepted)
    if measures["plate_fraction"] > MAX_PLATE_FRACTION:
        raise DsaregInputError(
            f"the kept voxels are plate-shaped ({100 * measures['plate_fraction']:.0f}% of them; vessels are "
            f"tubes: a skull or slab, not vessels): {what}", field=field_name, accepted=accepted)
    if measures["solid_fraction"] > MAX_SOLID_FRACTION:
        raise DsaregInputError(
            f"the kept voxels are mostly a solid mass far wider than a head's arteries "
            f"({100 * measures['solid_fraction']:.0f}% of their mid voxels){spacing_hint(mask, spacing)}: {what}",
            field=field_name, accepted=accepted + "; or the file's voxel spacing corrected")
    return measures


def spacing_hint(mask: np.ndarray, spacing) -> str:
    """``"; at the stated 1 × 1 × 1 mm voxels …"``: when the kept voxels' thick parts (90th percentile of their
    depth, twice: a width) are wider than any head artery (``MAX_ARTERY_WIDTH_MM``), the spacing that would make them
    an artery's width (a 3D rotational angiogram whose file states 1 mm where its voxels are ~0.4 mm); else ``""``.
    Measured on every second voxel (a few MB however large the mask)."""
    from scipy import ndimage

    spacing = np.asarray(spacing, float)
    coarse = crop_to(mask)[::2, ::2, ::2]
    if np.count_nonzero(coarse) < MIN_KEPT_VOXELS:
        return ""
    depth = ndimage.distance_transform_edt(np.pad(coarse, 1), sampling=2 * spacing)[1:-1, 1:-1, 1:-1][coarse]
    width_mm = 2.0 * float(np.percentile(depth, 90))
    if width_mm <= MAX_ARTERY_WIDTH_MM:
        return ""
    stated = " × ".join(f"{v:g}" for v in spacing)
    fitting = ", ".join(f"{v * TYPICAL_WIDTH_MM / width_mm:.2g}" for v in spacing)
    return (f"; at the stated {stated} mm voxels their thick parts are {width_mm:.0f} mm across, wider than any head "
            f"artery (≤ {MAX_ARTERY_WIDTH_MM:g} mm): if the file's spacing is wrong (a rotational angiogram's voxels are "
            f"often 0.1–0.5 mm), voxels of about {fitting} mm would make them {TYPICAL_WIDTH_MM:g} mm wide")


__all__ = ["check_vessel_shape", "curvature_shares", "shape_measures", "spacing_hint"]

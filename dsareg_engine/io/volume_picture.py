"""A picture of what was read from a volume: maximum-intensity projections with the kept vessel voxels.

Three panels — along the patient's z (axial), y (coronal) and x (sagittal) axes — each the MIP of
the volume (grey; without what the reader set aside — CTA bone, the MRA scalp — which would hide
everything else) with the projection of the kept voxels in red over it. Voxel axes are matched to the nearest patient axis (an oblique volume is shown along
its own axes), and pixels are scaled to the voxel spacing so shapes are not stretched.
"""

from __future__ import annotations

import cv2
import numpy as np

PANEL_PX = 360


def _patient_order(affine: np.ndarray) -> tuple[list[int], list[bool]]:
    """For patient axes x, y, z: the voxel axis closest to each, and whether it runs backwards."""
    directions = affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)
    order, flips = [], []
    for world_axis in range(3):
        voxel_axis = int(np.argmax(np.abs(directions[world_axis])))
        order.append(voxel_axis)
        flips.append(bool(directions[world_axis, voxel_axis] < 0))
    return order, flips


def _to_patient_axes(data: np.ndarray, affine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order, flips = _patient_order(affine)
    if sorted(order) != [0, 1, 2]:  # strongly oblique: show the voxel axes as they are
        return data, np.linalg.norm(affine[:3, :3], axis=0)
    out = np.transpose(data, order)
    for axis, flip in enumerate(flips):
        if flip:
            out = np.flip(out, axis)
    return out, np.linalg.norm(affine[:3, :3], axis=0)[order]


def _panel(grey: np.ndarray, kept: np.ndarray | None, spacing_xy: tuple[float, float], title: str) -> np.ndarray:
    """``grey`` (n_x, n_y) in [0, 1]: shown with x to the right, y downward."""
    height_mm, width_mm = grey.shape[1] * spacing_xy[1], grey.shape[0] * spacing_xy[0]
    scale = PANEL_PX / max(height_mm, width_mm)
    size = (max(1, round(width_mm * scale)), max(1, round(height_mm * scale)))
    image = cv2.resize((grey.T * 255).astype(np.uint8), size, interpolation=cv2.INTER_AREA)
    rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR).astype(np.float32)
    if kept is not None:
        mask = cv2.resize(kept.T.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
        rgb[mask] = 0.5 * rgb[mask] + 0.5 * np.array([40, 40, 255], np.float32)
    canvas = np.full((PANEL_PX + 24, PANEL_PX, 3), 30, np.uint8)
    canvas[24:24 + size[1], :size[0]] = rgb.astype(np.uint8)
    cv2.putText(canvas, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    return canvas


def mip_picture(data: np.ndarray, affine: np.ndarray, kept: np.ndarray | None = None, caption: str = "",
                excluded: np.ndarray | None = None) -> np.ndarray:
    """BGR uint8 picture (3 MIP panels and a caption line) of ``data[i, j, k]`` and the ``kept`` mask.

    ``excluded``: voxels left out of the MIP (what the reader set aside: CTA bone and its partial-volume
    band, the MRA scalp shell), so the picture shows what they would hide."""
    volume, spacing = _to_patient_axes(np.asarray(data, np.float32), affine)
    mask = None if kept is None else _to_patient_axes(np.asarray(kept, bool), affine)[0]
    if excluded is not None:
        hidden = _to_patient_axes(np.asarray(excluded, bool), affine)[0]
        volume = np.where(hidden, np.float32(volume[~hidden].min()) if (~hidden).any() else 0.0, volume)
    projections = [volume.max(axis=axis) for axis in (2, 1, 0)]
    values = np.concatenate([p.ravel() for p in projections])
    low, high = np.percentile(values, [50.0 if excluded is not None else 1.0, 99.9])
    panels = []
    for axis, title, (a, b) in ((2, "axial MIP (x right, y down)", (0, 1)),
                                (1, "coronal MIP (x right, z up)", (0, 2)),
                                (0, "sagittal MIP (y right, z up)", (1, 2))):
        projection = np.clip((projections[2 - axis] - low) / max(high - low, 1e-6), 0.0, 1.0)
        projected = None if mask is None else mask.any(axis=axis)
        if axis != 2:  # z up
            projection, projected = projection[:, ::-1], None if projected is None else projected[:, ::-1]
        panels.append(_panel(projection, projected, (spacing[a], spacing[b]), title))
    picture = np.concatenate(panels, axis=1)
    footer = np.full((26, picture.shape[1], 3), 30, np.uint8)
    cv2.putText(footer, caption[:160], (4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    return np.concatenate([picture, footer], axis=0)


__all__ = ["mip_picture"]

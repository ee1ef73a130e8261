"""Dural venous sinuses for a synthetic CTA head: a CTA taken late fills them (issue 41).

The sinuses lie in the dura, their lumen against the skull's inner table: the superior sagittal sinus over the vault
in the midline, from the forehead to the torcula at the back, and the two transverse sinuses from the torcula around
the occiput, level, to the sides. In section (``section``) a ``"triangle"`` (a base on the table, an apex toward
the brain: the superior sagittal sinus's, flat enough to read as a plate on the medial measure) or ``"round"`` (a
tube against the table: a transverse or sigmoid sinus's, a tube on that measure).
They are apart from the arteries (no contact at any voxel size): the venous system and the arterial tree meet only
through capillaries.

Coordinates are the layered generator's (:mod:`.synthetic_heads_layered`): LPS mm per axis (x left, y posterior,
z up), ``depth`` the mm under the skull's inner surface (negative inside).
"""

from __future__ import annotations

import numpy as np

SINUS_MM = 8.0  # the lumen's base on the table (superior sagittal: 6-10 mm; transverse: 7-10 mm)
HEIGHT_MM = 6.0  # from the table to the apex
VENOUS_HU = 300.0  # a late CTA's venous blood: below the arteries' 380, well in the vessels' window
FRONT_Y_SHARE = 0.5  # the superior sagittal sinus starts this share of the head's half depth ahead of the centre


def dural_sinuses(axes, depth: np.ndarray, centre: np.ndarray, inner: np.ndarray,
                  section: str = "triangle") -> np.ndarray:
    """bool, ``depth``'s shape: the lumen of the superior sagittal and transverse sinuses.

    Args:
        axes: the grid's LPS mm coordinates per axis, shaped to broadcast: (X, 1, 1), (1, Y, 1), (1, 1, Z).
        depth: float32 (X, Y, Z), mm under the skull's inner surface (outward positive).
        centre, inner: the skull's centre (mm) and inner half-extents (mm) per axis.
        section: ``"triangle"`` (``SINUS_MM`` wide on the table, ``HEIGHT_MM`` high) or ``"round"`` (a tube
            ``HEIGHT_MM`` across, its wall on the table).
    """
    under = -depth  # mm under the inner table (positive inside the skull)
    index = np.nonzero((under > 0) & (under <= HEIGHT_MM))  # the shell the sinuses lie in (not the whole grid)
    x, y, z = (np.broadcast_to(axis, depth.shape)[index] for axis in axes)
    if section == "round":  # the half width at that depth of a disc whose edge touches the table
        radius = HEIGHT_MM / 2.0
        half_width = np.sqrt(np.clip(radius ** 2 - (under[index] - radius) ** 2, 0.0, None))
    else:
        half_width = (1.0 - under[index] / HEIGHT_MM) * SINUS_MM / 2.0  # the triangle's
    sagittal = (np.abs(x - centre[0]) <= half_width) & (z >= centre[2]) & (
        y >= centre[1] - FRONT_Y_SHARE * inner[1])  # over the vault, from the forehead back to the torcula
    transverse = (np.abs(z - centre[2]) <= half_width) & (y >= centre[1])  # level, around the occiput
    out = np.zeros(depth.shape, bool)
    out[tuple(i[sagittal | transverse] for i in index)] = True
    return out


__all__ = ["HEIGHT_MM", "SINUS_MM", "VENOUS_HU", "dural_sinuses"]

"""CSF cisterns around the proximal vessel tree of a synthetic head (an option of the generators).

The circle of Willis and the first segments of its branches (proximal MCA, basilar) run through CSF-filled cisterns
(suprasellar, ambient, Sylvian, prepontine), not through brain: a sleeve of CSF a few mm wide around the vessels,
from the skull base's top up to ``reach_mm`` above it. CSF is water: 0–15 HU in a CT (:data:`CSF_HU`); in a
TOF-MRA its long T1 is saturated by the short TR, so it is dark, but it has protons: it keeps a signal well above
cortical bone and air (no signal, the noise floor), at about 0.4 of the brain's (:data:`MRA_CSF_OF_BRAIN`;
generator A's MRA variants have CSF 90 / brain 210 and 140 / 300).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CSF_HU = 8.0
MRA_CSF_OF_BRAIN = 0.43  # TOF-MRA: CSF's level as a share of the brain's


@dataclass(frozen=True)
class Cisterns:
    """Where the CSF lies: within ``sleeve_mm`` of the vessels' wall, at heights (z, mm) from the skull base's top
    to ``reach_mm`` above it (the proximal tree)."""

    sleeve_mm: float = 3.0
    reach_mm: float = 30.0


def cistern_mask(occupancy: np.ndarray, spacing_mm: np.ndarray, z_mm: np.ndarray, floor_z_mm: float,
                 cisterns: Cisterns) -> np.ndarray:
    """bool, ``occupancy``'s shape (X, Y, Z): the cisterns' voxels (the vessels' own voxels excluded).
    ``occupancy``: the tree's partial-volume occupancy [0, 1]; ``z_mm``: the z of each slice, shaped (1, 1, Z);
    ``floor_z_mm``: the skull base's top."""
    from ..io.voxel_band import within_mm

    levels = (z_mm >= floor_z_mm) & (z_mm < floor_z_mm + cisterns.reach_mm)  # (1, 1, Z)
    vessel = occupancy >= 0.5
    sleeve = within_mm(vessel & levels, spacing_mm, cisterns.sleeve_mm)
    return sleeve & levels & ~vessel


__all__ = ["CSF_HU", "Cisterns", "MRA_CSF_OF_BRAIN", "cistern_mask"]

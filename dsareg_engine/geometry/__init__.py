"""Geometry: the imaging conventions of one view and a biplane rig (``rig``), rigid transforms (``pose``),
geometry and pose files (``file``, ``pose_file``), the one parsed, canonical geometry value (``spec``) and the
vessel model read as a tree: inflow, geodesic distances, branches, regions to register with (``vessel_tree``).

``from dsareg_engine.geometry import Rig`` keeps working: the rig's names are re-exported here.
"""

from .rig import (
    VIEW_NAMES,
    Rig,
    ViewGeometry,
    biplane_rig,
    default_principal_point,
    rotated_view,
    view_from_detector_pose,
    view_from_projection_matrix,
)

__all__ = [
    "VIEW_NAMES",
    "Rig",
    "ViewGeometry",
    "biplane_rig",
    "default_principal_point",
    "rotated_view",
    "view_from_detector_pose",
    "view_from_projection_matrix",
]

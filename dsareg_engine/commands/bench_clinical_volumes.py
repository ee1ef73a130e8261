"""The volume rows of ``dsareg bench clinical``: vessel models read from CTA and TOF-MRA heads.

Each kind builds one synthetic case (:func:`dsareg_engine.simulation.synthetic_volumes.make_volume_case`):
the head's DICOM series as the model (``--volume``), the XA pair of the true tree with the geometry in their
tags; no geometry file, no initial pose. Generators A and B differ in levels, noise, blur and tag layout.
A reference row registers the true tree as a mesh (what a perfect reader would give).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..io.case import CaseFiles

VOXEL_MM = 0.6
TREE_DEPTH = 3
PIXEL_SPACING_MM = 0.6


def _volume_case(kind: str, variant: str, as_mesh: bool = False) -> Callable[[int, int], tuple[CaseFiles, np.ndarray]]:
    def build(seed: int, size_px: int) -> tuple[CaseFiles, np.ndarray]:
        from ..simulation.synthetic_volumes import make_volume_case

        case = make_volume_case(kind, variant, voxel_mm=VOXEL_MM, depth=TREE_DEPTH, seed=3 + seed, image_px=size_px,
                                pixel_spacing_mm=PIXEL_SPACING_MM * 256 / size_px)
        model = {"mesh": _mesh_bytes(case.volume.tree), "mesh_name": "tree.obj"} if as_mesh else {
            "volume": case.volume.parts, "volume_name": "series.dcm"}
        return CaseFiles(ap=case.ap, ap_name="ap.dcm", lat=case.lat, lat_name="lat.dcm", **model), case.mesh_to_world
    return build


def _mesh_bytes(mesh) -> bytes:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "tree.obj"
        mesh.save(path)
        return path.read_bytes()


VOLUME_CASE_KINDS: list[tuple[str, str, Callable[[int, int], tuple[CaseFiles, np.ndarray]]]] = [
    ("CTA, generator A", f"{VOXEL_MM} mm CT series: vessels 350 HU, brain 35, skull 1200 (4 mm), skull-base slab 900 "
     "crossed by the trunk, air; white noise 8 HU, blur 0.5 vox; unsigned + intercept, Contrast/Bolus Agent",
     _volume_case("cta", "a")),
    ("CTA, generator B", "vessels 430 HU, brain 42, scalp fat -80, skull 1550, slab 1050; correlated noise 14 HU, blur "
     "0.8 vox; signed, slices reversed, no contrast tag", _volume_case("cta", "b")),
    ("TOF-MRA, generator A", "MR series: vessels 560 → 480 distally, brain 210 textured, scalp fat 430, bone 40, CSF 90; "
     "Rician noise 8, blur 0.5 vox; axial, Angio Flag", _volume_case("mra", "a")),
    ("TOF-MRA, generator B", "vessels 720 → 520, brain 300 textured ±40, fat 640, bone 60; Rician 15, blur 0.8 vox; "
     "sagittal slices, rescale slope 0.5, no angio tags", _volume_case("mra", "b")),
    ("  true tree as a mesh", "the reference: the same XA pair (generator A's) with the true surface as the model",
     _volume_case("cta", "a", as_mesh=True)),
]

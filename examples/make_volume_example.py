"""Regenerate the volume example in examples/volume/ with the project's own generator (no patient data).

The vessel tree of the study's CT series as a vessels-only volume (0.5 mm isotropic, as NIfTI; no HU, no skull:
dsareg reads it by intensity, as an already subtracted 3D-DSA) and the AP and LAT native XA runs
of the same tree (multi-frame, 256 px, a skull, Poisson noise, mask frames before the contrast and the
subtraction recipe), geometry in their headers, and the true pose. They are one study of
``dsareg phantom-study`` (:func:`dsareg_engine.simulation.native_study.make_native_study`, seed 3); the
pixels are the same on every run, the DICOM UIDs are new ones. Run: python examples/make_volume_example.py
"""

from pathlib import Path

import nibabel as nib
import numpy as np

from dsareg_engine.geometry.pose_file import save_pose
from dsareg_engine.io.volume_io import RAS_TO_LPS, read_volume
from dsareg_engine.simulation.native_study import make_native_study

OUT = Path(__file__).parent / "volume"


def main() -> None:
    OUT.mkdir(exist_ok=True)
    study = make_native_study(seed=3, size_px=256)
    volume = read_volume(study.volume)  # voxels and voxel → LPS mm, as dsareg reads the series
    nifti = nib.Nifti1Image(np.round(volume.data).astype(np.int16), RAS_TO_LPS @ volume.affine)
    nifti.header.set_xyzt_units("mm")
    nib.save(nifti, str(OUT / "vessels_ct.nii.gz"))
    for name, data in study.runs.items():
        (OUT / f"{name}_run.dcm").write_bytes(data)
    save_pose(OUT / "ground_truth.json", study.mesh_to_world)
    print(f"wrote {sorted(p.name for p in OUT.iterdir())}")


if __name__ == "__main__":
    main()

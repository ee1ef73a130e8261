"""A synthetic biplane DICOM study made from the built-in phantom (no patient data).

``make_biplane_study`` returns one study: a 3D volume series (CT-like slices of the voxelized
phantom, with a Frame of Reference) and two XA instances (AP / LAT plane of a biplane C-arm with
real-like positioner angles, distances and imager pixel spacing) whose pixels are the
silhouettes of the *volume's own vessel mesh* (what dsareg extracts from the series) rendered
at a known ``mesh_to_world``. So a registration of this study should return exactly that pose.
Used by the DICOM / DICOMweb tests and by ``examples/pacs``.
"""

from __future__ import annotations

import datetime as _dt
import io
from dataclasses import dataclass, field

import numpy as np

from ..io.dicom_out import new_uid

XA_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.1"
CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"
PATIENT_NAME = "PHANTOM^DSAREG"
PATIENT_ID = "DSAREG-PHANTOM-1"

# A biplane: frontal plane slightly LAO/CRA, lateral plane near 90° LAO with a little caudal tilt.
AP_ANGLES = (4.0, 3.0)
LAT_ANGLES = (88.0, -2.0)
SID_MM = (1100.0, 1150.0)
SOD_MM = (760.0, 780.0)


@dataclass
class BiplaneStudy:
    ap: bytes
    lat: bytes
    volume: list[bytes]
    mesh_to_world: np.ndarray
    study_uid: str
    uids: dict[str, str] = field(default_factory=dict)  # ap/lat/volume series UIDs, volume frame UID

    def instances(self) -> list[bytes]:
        return [self.ap, self.lat, *self.volume]


def _to_bytes(ds) -> bytes:
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _dataset(sop_class: str, study_uid: str, series_uid: str, modality: str, series_number: int, number: int):
    from ..io.dicom_out import new_instance

    ds = new_instance(sop_class, new_uid(), charset="ISO_IR 100")
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = PATIENT_NAME, PATIENT_ID, "", "O"
    today = _dt.date.today().strftime("%Y%m%d")
    ds.StudyInstanceUID, ds.StudyDate, ds.StudyTime, ds.StudyID = study_uid, today, "120000", "DSAREG1"
    ds.AccessionNumber, ds.ReferringPhysicianName, ds.StudyDescription = "", "", "dsareg synthetic biplane phantom"
    ds.SeriesInstanceUID, ds.SeriesNumber, ds.Modality = series_uid, series_number, modality
    ds.InstanceNumber = number
    ds.Manufacturer = "dsareg phantom"
    return ds


def voxelize_mesh(mesh, pitch, margin: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Partial-volume voxels (0..800) of a closed (possibly self-overlapping) mesh, and the voxel→LPS affine.

    ``pitch``: mm, one value or one per axis (anisotropic voxels: each a whole multiple of half the smallest).
    The mesh is filled on a grid of half the smallest pitch and averaged over each voxel's block of it.
    """
    import trimesh

    pitch = np.broadcast_to(np.asarray(pitch, float), (3,))
    fine = float(pitch.min()) / 2.0
    block = np.round(pitch / fine).astype(int)
    if not np.allclose(block * fine, pitch, rtol=1e-6, atol=1e-9):
        raise ValueError(f"voxel sizes {pitch.tolist()} mm: each must be a whole multiple of {fine:g} mm")
    solid = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).voxelized(fine).fill()
    occupancy = np.pad(solid.matrix.astype(np.float32), [(b * margin, b * margin) for b in block])
    shape = (np.array(occupancy.shape) + block - 1) // block * block
    occupancy = np.pad(occupancy, [(0, s - o) for s, o in zip(shape, occupancy.shape)])
    coarse = occupancy.reshape(shape[0] // block[0], block[0], shape[1] // block[1], block[1],
                               shape[2] // block[2], block[2]).mean(axis=(1, 3, 5))
    origin_fine = solid.transform[:3, 3] - block * margin * fine  # centre of fine voxel 0
    affine = np.diag([*pitch, 1.0])
    affine[:3, 3] = origin_fine + (block - 1) * fine / 2.0  # centre of the first block
    return (800.0 * coarse).astype(np.float32), affine


def _ct_series(volume: np.ndarray, affine: np.ndarray, study_uid: str) -> tuple[list[bytes], str, str]:
    series_uid, frame_uid = new_uid(), new_uid()
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    row_dir, col_dir = affine[:3, 0] / spacing[0], affine[:3, 1] / spacing[1]
    parts = []
    for k in range(volume.shape[2]):
        ds = _dataset(CT_SOP_CLASS, study_uid, series_uid, "CT", 2, k + 1)
        ds.SeriesDescription = "3D angiography phantom"
        ds.FrameOfReferenceUID, ds.PositionReferenceIndicator = frame_uid, ""
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
        ds.Rows, ds.Columns = volume.shape[1], volume.shape[0]
        ds.ImagePositionPatient = [round(float(x), 6) for x in affine[:3, :3] @ [0, 0, k] + affine[:3, 3]]
        ds.ImageOrientationPatient = [float(x) for x in (*row_dir, *col_dir)]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]
        ds.SliceThickness = float(spacing[2])
        ds.KVP = ""
        ds.RescaleSlope, ds.RescaleIntercept, ds.RescaleType = 1, -1000, "HU"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.PixelData = np.round(volume[:, :, k].T + 1000.0).astype(np.uint16).tobytes()
        parts.append(_to_bytes(ds))
    return parts, series_uid, frame_uid


def _xa(mask: np.ndarray, angles, sid, sod, spacing, study_uid: str, series_number: int, plane: str) -> tuple[bytes, str]:
    series_uid = new_uid()
    ds = _dataset(XA_SOP_CLASS, study_uid, series_uid, "XA", series_number, 1)
    ds.SeriesDescription = f"DSA plane {plane}"
    ds.ImageType = ["DERIVED", "PRIMARY", "SINGLE PLANE", "SINGLE A" if plane == "A" else "SINGLE B"]
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = float(angles[0]), float(angles[1])
    ds.DistanceSourceToDetector, ds.DistanceSourceToPatient = float(sid), float(sod)
    ds.ImagerPixelSpacing = [float(spacing), float(spacing)]
    ds.Rows, ds.Columns = mask.shape
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.PixelIntensityRelationship = "LIN"
    ds.PixelData = np.where(mask, 900, 3100).astype(np.uint16).tobytes()  # vessels dark, as in DSA
    ds.KVP, ds.RadiationSetting, ds.ContentDate, ds.ContentTime = "", "GR", ds.StudyDate, "120000"
    ds.Laterality = ""
    return _to_bytes(ds), series_uid


def make_biplane_study(
    mesh_to_world: np.ndarray | None = None,
    *,
    image_px: int = 256,
    pixel_spacing_mm: float = 0.6,
    pitch_mm: float = 0.5,
    depth: int = 2,
    seed: int = 3,
    slice_px: int | None = None,
) -> BiplaneStudy:
    """The study; ``mesh_to_world`` (volume LPS mm → C-arm isocentre LPS mm) defaults to 6° / 5 mm off identity.

    ``slice_px``: pad the slices with background to this size (e.g. 512, as a real CTA / 3D-RA).
    """
    import torch

    from ..io.dicom_xa import view_from_angles
    from ..io.volume_io import read_volume, volume_to_mesh
    from .phantom import make_vessel_phantom
    from ..geometry.pose import make_transform
    from ..render import Camera, render_hard_silhouette

    if mesh_to_world is None:
        axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        angle = np.radians(6.0)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        mesh_to_world = make_transform(rotation, np.array([3.0, -2.0, 3.5]))
    mesh_to_world = np.asarray(mesh_to_world, dtype=np.float64)
    phantom = make_vessel_phantom(depth=depth, seed=seed)
    study_uid = new_uid()
    volume, affine = voxelize_mesh(phantom, pitch_mm)
    if slice_px is not None and slice_px > max(volume.shape[:2]):  # realistic slice size: pad with background
        before = [(slice_px - n) // 2 for n in volume.shape[:2]]
        volume = np.pad(volume, [(b, slice_px - n - b) for b, n in zip(before, volume.shape[:2])] + [(0, 0)])
        affine = affine.copy()
        affine[:3, 3] -= affine[:3, :2] @ np.array(before, dtype=np.float64)
    parts, volume_series, frame_uid = _ct_series(volume, affine, study_uid)
    mesh = volume_to_mesh(read_volume(parts))  # exactly the model dsareg builds from the series
    vertices, faces = mesh.torch(torch.float64)
    xa, uids = {}, {"volume_series": volume_series, "volume_frame": frame_uid}
    for index, (name, angles, plane) in enumerate((("ap", AP_ANGLES, "A"), ("lat", LAT_ANGLES, "B"))):
        view = view_from_angles(angles[0], angles[1], SID_MM[index], SOD_MM[index],
                                (pixel_spacing_mm, pixel_spacing_mm), (image_px, image_px))
        mask = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ mesh_to_world)[None],
                                      Camera.from_view(view))[0].numpy().astype(bool)
        if not mask.any():
            raise RuntimeError(f"the phantom does not project into the {name} view")
        xa[name], uids[f"{name}_series"] = _xa(mask, angles, SID_MM[index], SOD_MM[index], pixel_spacing_mm,
                                               study_uid, 10 + index, plane)
    return BiplaneStudy(ap=xa["ap"], lat=xa["lat"], volume=parts, mesh_to_world=mesh_to_world,
                        study_uid=study_uid, uids=uids)

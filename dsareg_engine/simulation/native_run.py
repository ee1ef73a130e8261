"""Native (unsubtracted) XA runs synthesized from a vessel model: what the two run generators share.

A run is a stack of log-domain attenuation images per view: the background anatomy (the
generator's own), moved by the patient motion in the contrast frames, plus the iodine of the
vessel tree, which fills from the tree's root outward over the frames (``fill`` per frame:
the contrast front's distance from the root as a fraction of the tree's extent) and may wash
out (``strength`` per frame). The frame with the whole tree filled at full strength is the
peak; the true pose is the pose the vessels are drawn at, the true geometry the one the XA
tags carry for that frame. The generators (:mod:`.native_run_skull`, :mod:`.native_run_texture`)
differ in background, noise, intensity encoding and DICOM layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.rig import Rig, ViewGeometry
from ..io.dicom_xa import view_from_angles
from ..mesh import TriangleMesh
from .synthetic_dsa import vessel_thickness_mm

IODINE_PER_MM = 0.12
REFERENCE_PX = 160
FRONT_RAMP = 0.15


@dataclass(frozen=True)
class Plane:
    """One C-arm plane: angles (deg), distances (mm), detector pixel spacing (mm) at ``REFERENCE_PX``
    pixels per side (the field of view stays the same at other sizes)."""

    primary_deg: float
    secondary_deg: float
    sid_mm: float
    sod_mm: float
    spacing_mm: float

    def spacing_at(self, size_px: int) -> float:
        return self.spacing_mm * REFERENCE_PX / size_px

    def view(self, size_px: int) -> ViewGeometry:
        spacing = self.spacing_at(size_px)
        return view_from_angles(self.primary_deg, self.secondary_deg, self.sid_mm, self.sod_mm,
                                (spacing, spacing), (size_px, size_px))


@dataclass
class NativeRunCase:
    """A synthetic native biplane run and what is true about it.

    Attributes:
        files: ``{"ap", "lat"}`` DICOM bytes of the native runs.
        subtracted: the same case pre-subtracted: single-frame XA DSA of the peak frame (log
            contrast minus the perfectly aligned, noise-free mask), geometry in the tags.
        mesh, mesh_to_world: the model and its true pose.
        rig: the true views (of the peak frame).
        motion_px: per view, the patient motion ``(down, right)`` px of the contrast frames relative
            to the mask frames (what a correct motion correction finds).
        peak_frame, mask_frames: 0-based.
        vessels: per view the true vessel path length ``(H, W)`` mm at the peak.
    """

    files: dict[str, bytes]
    subtracted: dict[str, bytes]
    mesh: TriangleMesh
    mesh_to_world: np.ndarray
    rig: Rig
    motion_px: dict[str, tuple[float, float]]
    peak_frame: int
    mask_frames: tuple[int, ...]
    vessels: dict[str, np.ndarray] = field(default_factory=dict)


def tree_root(mesh: TriangleMesh, n_sides: int = 12) -> np.ndarray:
    """The phantom's inlet: the centre of its first ring (:func:`~.phantom.make_vessel_phantom` builds the trunk first)."""
    return mesh.vertices[:n_sides].mean(axis=0)


def lowest_point(mesh: TriangleMesh, up_axis: int = 1) -> np.ndarray:
    """The inlet of a model whose ``up_axis`` points to the head: its lowest vertex (the carotid enters from below)."""
    return mesh.vertices[int(np.argmin(mesh.vertices[:, up_axis]))]


def arrival_map(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, thickness: np.ndarray,
                root: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` when contrast reaches each vessel pixel, 0 (the root) .. 1 (the farthest vertex):
    the nearest projected vertex's distance from the root (model mm; default :func:`tree_root`)."""
    distance = np.linalg.norm(mesh.vertices - (tree_root(mesh) if root is None else root), axis=1)
    distance = distance / distance.max()
    world = mesh.vertices @ mesh_to_world[:3, :3].T + mesh_to_world[:3, 3]
    tree = cKDTree(view.project(world))
    rows, cols = np.nonzero(thickness > 0)
    out = np.ones(thickness.shape)
    if len(rows):
        _, nearest = tree.query(np.stack([cols, rows], axis=1).astype(float))
        out[rows, cols] = distance[nearest]
    return out


def vessel_frames(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, fill: list[float],
                  strength: list[float], root: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``((N, H, W) iodine attenuation per frame, (H, W) path length at the peak, mm)``."""
    thickness = vessel_thickness_mm(mesh, view, mesh_to_world, supersample=3)
    arrival = arrival_map(mesh, view, mesh_to_world, thickness, root)
    frames = [IODINE_PER_MM * s * thickness * np.clip((f - arrival) / FRONT_RAMP, 0.0, 1.0)
              for f, s in zip(fill, strength)]
    return np.array(frames, np.float32), thickness


def peak_of(fill: list[float], strength: list[float]) -> int:
    """The first frame with the whole tree filled at the highest strength."""
    full = [s if f >= 1.0 + FRONT_RAMP else 0.0 for f, s in zip(fill, strength)]
    return int(np.argmax(full))


def pose_in_view(mesh: TriangleMesh, rig: Rig, seed: int) -> np.ndarray:
    """A random rotation, the model's centre within 15 mm of the isocentre, every vertex inside both views."""
    from .clinical_rig import random_visible_pose

    return random_visible_pose(mesh, rig, np.random.default_rng(seed), radius_mm=15.0)


def base_dataset(sop_class: str, rows: int, cols: int, n_frames: int, plane: str):
    """A synthetic XA instance's common tags (no patient data: a fixed phantom name)."""
    from ..io.dicom_out import new_instance, new_uid

    ds = new_instance(sop_class, new_uid(), charset="ISO_IR 100")
    ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "PHANTOM^RUN", "DSAREG-RUN-1", "", "O"
    ds.StudyInstanceUID, ds.SeriesInstanceUID = new_uid(), new_uid()
    ds.Modality, ds.SeriesNumber, ds.InstanceNumber = "XA", 1 if plane == "A" else 2, 1
    ds.Rows, ds.Columns, ds.NumberOfFrames = rows, cols, n_frames
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.SamplesPerPixel = 1
    return ds


def to_bytes(ds) -> bytes:
    import io

    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def subtracted_xa(dsa_log: np.ndarray, plane: Plane, name: str) -> bytes:
    """A single-frame subtracted XA (vessels dark; 12 bits) with the plane's geometry tags."""
    ds = base_dataset(XA_SOP, *dsa_log.shape, 1, "A" if name == "ap" else "B")
    del ds.NumberOfFrames
    ds.ImageType = ["DERIVED", "PRIMARY", "SINGLE PLANE", "SUBTRACTION"]
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LOG", 1
    classic_geometry(ds, plane, dsa_log.shape[0])
    stored = np.clip(np.round(3000.0 + 2500.0 * dsa_log), 0, 4095).astype(np.uint16)
    ds.PixelData = stored.tobytes()
    return to_bytes(ds)


XA_SOP = "1.2.840.10008.5.1.4.1.1.12.1"
ENHANCED_XA_SOP = "1.2.840.10008.5.1.4.1.1.12.1.1"


def classic_geometry(ds, plane: Plane, size_px: int) -> None:
    """The plane's geometry in the classic XA tags (positioner angles, distances, imager pixel spacing)."""
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = plane.primary_deg, plane.secondary_deg
    ds.DistanceSourceToDetector, ds.DistanceSourceToPatient = plane.sid_mm, plane.sod_mm
    spacing = round(plane.spacing_at(size_px), 6)
    ds.ImagerPixelSpacing = [spacing, spacing]

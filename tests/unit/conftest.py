"""Builders of small synthetic inputs for the reader tests (no patient data, no downloads)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from dsareg_engine.simulation.phantom import make_vessel_phantom

XA_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.1"
CT_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.2"


def _base_dataset(sop_class: str) -> Dataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.PatientName = "Anonymous^Phantom"
    ds.PatientID = "PHANTOM-0"
    return ds


def _to_bytes(ds: Dataset) -> bytes:
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def make_xa(
    pixels: np.ndarray | None = None,
    *,
    primary: float | None = 0.0,
    secondary: float | None = 0.0,
    sid: float | None = 1200.0,
    sod: float | None = 800.0,
    spacing: tuple[float, float] | None = (0.3, 0.3),
    rows: int = 64,
    cols: int = 80,
    monochrome1: bool = False,
) -> bytes:
    """A DICOM XA instance; ``pixels`` (H, W) or (N, H, W) uint16, or None for no pixel data."""
    ds = _base_dataset(XA_SOP_CLASS)
    ds.Modality = "XA"
    if pixels is not None:
        pixels = np.asarray(pixels, dtype=np.uint16)
        rows, cols = pixels.shape[-2:]
        if pixels.ndim == 3:
            ds.NumberOfFrames = pixels.shape[0]
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.SamplesPerPixel = 1
        ds.PixelData = pixels.tobytes()
    ds.PhotometricInterpretation = "MONOCHROME1" if monochrome1 else "MONOCHROME2"
    ds.Rows, ds.Columns = rows, cols
    if primary is not None:
        ds.PositionerPrimaryAngle = primary
    if secondary is not None:
        ds.PositionerSecondaryAngle = secondary
    if sid is not None:
        ds.DistanceSourceToDetector = sid
    if sod is not None:
        ds.DistanceSourceToPatient = sod
    if spacing is not None:
        ds.ImagerPixelSpacing = list(spacing)
    return _to_bytes(ds)


def make_ct_series(volume: np.ndarray, affine: np.ndarray) -> list[bytes]:
    """Axial-style DICOM slices of ``volume[i, j, k]`` with voxel→LPS ``affine`` (orthogonal axes)."""
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    row_dir, col_dir = affine[:3, 0] / spacing[0], affine[:3, 1] / spacing[1]
    low = float(volume.min())
    parts = []
    for k in range(volume.shape[2]):
        ds = _base_dataset(CT_SOP_CLASS)
        ds.Modality = "CT"
        ds.Rows, ds.Columns = volume.shape[1], volume.shape[0]
        ds.ImagePositionPatient = [float(x) for x in affine[:3, :3] @ [0, 0, k] + affine[:3, 3]]
        ds.ImageOrientationPatient = [float(x) for x in (*row_dir, *col_dir)]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]
        ds.SliceThickness = float(spacing[2])
        ds.RescaleSlope, ds.RescaleIntercept = 1, low
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.PixelData = np.round(volume[:, :, k].T - low).astype(np.uint16).tobytes()
        parts.append(_to_bytes(ds))
    return parts


def voxelize(mesh, pitch: float, margin: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Partial-volume voxelization of a (possibly self-overlapping) closed mesh.

    Signed distance per connected component (sign: vote of the 6 nearest surface
    samples' outward normals), union = minimum, intensity ramps over one voxel.
    Returns ``(volume[i, j, k] in [0, 800], voxel→world affine)``.
    """
    vertices, faces = mesh.vertices, mesh.faces
    lo = vertices.min(0) - margin * pitch
    shape = np.ceil((vertices.max(0) + margin * pitch - lo) / pitch).astype(int) + 1
    n = len(vertices)
    adjacency = sparse.coo_matrix(
        (np.ones(faces.size), (faces.ravel(), np.roll(faces, 1, axis=1).ravel())), shape=(n, n)
    )
    _, label = connected_components(adjacency, directed=False)
    sd = np.full(shape, np.inf)
    for component in np.unique(label[faces[:, 0]]):
        part = trimesh.Trimesh(vertices, faces[label[faces[:, 0]] == component], process=False)
        samples, face_index = trimesh.sample.sample_surface(part, max(2000, int(part.area * 40)), seed=int(component))
        normals = part.face_normals[face_index]
        a = np.maximum(np.floor((samples.min(0) - lo) / pitch).astype(int) - 2, 0)
        b = np.minimum(np.ceil((samples.max(0) - lo) / pitch).astype(int) + 3, shape)
        axes = [np.arange(a[k], b[k]) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) * pitch + lo
        distance, index = cKDTree(samples).query(grid, k=6)
        vote = np.sign(np.einsum("ikj,ikj->ik", grid[:, None] - samples[index], normals[index])).sum(1)
        local = np.where(vote > 0, distance[:, 0], -distance[:, 0]).reshape([len(x) for x in axes])
        region = tuple(slice(a[k], b[k]) for k in range(3))
        sd[region] = np.minimum(sd[region], local)
    affine = np.diag([pitch, pitch, pitch, 1.0])
    affine[:3, 3] = lo
    return (800.0 * np.clip(0.5 - sd / pitch, 0.0, 1.0)).astype(np.float32), affine


@pytest.fixture(scope="session")
def small_phantom():
    return make_vessel_phantom(depth=2)


@pytest.fixture(scope="session")
def phantom_volume(small_phantom):
    """(volume, affine LPS, pitch) of the small phantom, voxelized at 0.5 mm."""
    volume, affine = voxelize(small_phantom, 0.5)
    return volume, affine, 0.5


@pytest.fixture(scope="session")
def phantom_surface_tree(small_phantom):
    mesh = trimesh.Trimesh(small_phantom.vertices, small_phantom.faces, process=False)
    samples, _ = trimesh.sample.sample_surface(mesh, 200_000, seed=1)
    return cKDTree(samples)


def png_bytes(array: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def synthetic_dsa(height: int = 96, width: int = 128, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(uint8 DSA-like image with dark vessels on bright background, true vessel mask)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width]
    truth = np.zeros((height, width), bool)
    truth |= np.abs(rows - (0.3 * cols + 20)) < 3.5  # thick vessel
    truth |= np.abs(cols - (width * 0.6 + 0.1 * rows)) < 1.2  # thin vessel
    image = np.full((height, width), 200.0) + rng.normal(0, 4, (height, width))
    image[truth] -= 110
    return np.clip(image, 0, 255).astype(np.uint8), truth


@pytest.fixture(scope="session")
def build():
    """The builders above, for test modules (tests/io is not a package)."""
    from types import SimpleNamespace

    return SimpleNamespace(xa=make_xa, ct_series=make_ct_series, voxelize=voxelize, png=png_bytes, dsa=synthetic_dsa)

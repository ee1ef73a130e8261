"""Generator A of native runs: a skull, photon (Poisson) noise, LIN pixels, classic multi-frame XA.

Background: an ellipsoidal skull shell (bone) around an ellipsoidal brain (soft tissue), traced
per pixel ray (chord lengths through both ellipsoids), and a smooth ±8 % soft-tissue field; the
skull is placed off-centre so its rim crosses the field of view; optionally a contrast-filled
catheter (in every frame). Each pixel counts ``Poisson(N0 · exp(−attenuation))`` photons, blurred
0.5 px, stored by :func:`encode` (default 12-bit ``LIN``: values ∝ intensity, no attenuation at
~97 % of full scale; or ``LOG`` / ``DISP``, 8–16 bits, MONOCHROME1 or 2). Tags: classic
multi-frame XA (geometry only in the XA positioner / distance tags) and, with ``recipe``,
Recommended Viewing Mode ``SUB`` and a Mask Subtraction Sequence ``AVG_SUB`` (the mask frames,
applied to the frames after them). The patient moves between the mask and the contrast frames by
``rotation_deg`` about the image centre (counter-clockwise as displayed) then ``motion_px``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..geometry.rig import Rig, ViewGeometry
from ..mesh import TriangleMesh
from .native_run import (
    IODINE_PER_MM,
    REFERENCE_PX,
    XA_SOP,
    NativeRunCase,
    Plane,
    base_dataset,
    classic_geometry,
    pose_in_view,
    subtracted_xa,
    to_bytes,
)
from .native_run_bolus import Bolus, run_iodine, run_peak
from .phantom import make_vessel_phantom
from .synthetic_dsa import _smooth_field

PLANES = {"ap": Plane(4.0, 3.0, 1100.0, 760.0, 1.1), "lat": Plane(88.0, -2.0, 1150.0, 780.0, 1.1)}


@dataclass(frozen=True)
class SkullRunSettings:
    """Attributes:
        size_px: image side.
        fill, strength: per frame, the contrast front (fraction of the tree) and the iodine strength.
        mask_frames: 1-based frame numbers the recipe averages into the mask (the frames before contrast).
        motion_px: ``(down, right)`` patient motion of the contrast frames.
        photons: ``N0``, photons per pixel without attenuation at 160 px per side (scaled with the pixel area).
        skull_centre_mm, skull_radii_mm, bone_mm: the skull (world LPS, about the isocentre).
        bone_per_mm, tissue_per_mm: attenuation coefficients, 1/mm.
        recipe: write Recommended Viewing Mode SUB and the Mask Subtraction Sequence (else neither).
        rotation_deg: in-plane patient rotation of the contrast frames (counter-clockwise as displayed).
        catheter_mm: diameter of a contrast-filled catheter in every frame (0: none).
        bits, relationship, photometric: the pixel encoding (:func:`encode`).
        bolus: a bolus passing along the tree (:mod:`.native_run_bolus`) instead of ``fill`` / ``strength``;
            its frames before contrast are the mask frames.
    """

    size_px: int = 160
    fill: tuple[float, ...] = (0.0, 0.0, 0.1, 0.3, 0.55, 0.8, 1.0, 1.2, 1.3, 1.3)
    strength: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.85, 0.7)
    mask_frames: tuple[int, ...] = (1, 2)
    motion_px: tuple[float, float] = (0.45, -0.4)
    photons: float = 36000.0
    skull_centre_mm: tuple[float, float, float] = (22.0, 5.0, 30.0)
    skull_radii_mm: tuple[float, float, float] = (72.0, 90.0, 82.0)
    bone_mm: float = 7.0
    bone_per_mm: float = 0.04
    tissue_per_mm: float = 0.012
    recipe: bool = True
    rotation_deg: float = 0.0
    catheter_mm: float = 0.0
    bits: int = 12
    relationship: str = "LIN"
    photometric: str = "MONOCHROME2"
    bolus: Bolus | None = None


def pixel_rays(view: ViewGeometry) -> tuple[np.ndarray, np.ndarray]:
    """``(source (3,), unit directions (H, W, 3))`` in world mm of every pixel centre's ray."""
    fx, fy = view.focal_px
    u0, v0 = view.principal_point_px
    v, u = np.mgrid[0:view.height, 0:view.width].astype(np.float64)
    directions = np.stack([(u - u0) / fx, (v - v0) / fy, np.ones_like(u)], axis=-1)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    view_to_world = view.world_to_view[:3, :3].T  # the rotation part is orthogonal (det ±1)
    return view.source_position_world, directions @ view_to_world.T


def chord_mm(source: np.ndarray, directions: np.ndarray, centre, radii) -> np.ndarray:
    """Length of each ray inside the ellipsoid ``Σ ((x − c) / r)² ≤ 1`` (mm)."""
    radii = np.asarray(radii, float)
    p = (source - np.asarray(centre, float)) / radii
    d = directions / radii
    a = (d * d).sum(-1)
    b = 2.0 * (d * p).sum(-1)
    c = float(p @ p) - 1.0
    disc = np.maximum(b * b - 4.0 * a * c, 0.0)
    return np.sqrt(disc) / a  # (s2 − s1) with unit world directions


def skull_attenuation(view: ViewGeometry, settings: SkullRunSettings, rng: np.random.Generator) -> np.ndarray:
    """``(H, W)`` background attenuation (bone shell + brain + a smooth tissue field)."""
    source, directions = pixel_rays(view)
    radii = np.array(settings.skull_radii_mm)
    outer = chord_mm(source, directions, settings.skull_centre_mm, radii)
    inner = chord_mm(source, directions, settings.skull_centre_mm, radii - settings.bone_mm)
    tissue = settings.tissue_per_mm * (outer + 20.0) * (1.0 + 0.16 * _smooth_field(outer.shape, rng, 5))
    return (settings.bone_per_mm * (outer - inner) + tissue).astype(np.float32)


def _photons(settings: SkullRunSettings) -> float:
    """``N0`` per pixel at this size: the detector's dose spreads over the same field of view."""
    return settings.photons * (REFERENCE_PX / settings.size_px) ** 2


def _intensity(attenuation: np.ndarray, settings: SkullRunSettings, rng: np.random.Generator) -> np.ndarray:
    """Detected intensity (1 = no attenuation): Poisson photon counts, blurred 0.5 px."""
    counts = rng.poisson(_photons(settings) * np.exp(-attenuation)).astype(np.float32)
    return cv2.GaussianBlur(counts, (0, 0), 0.5) / _photons(settings)


def encode(intensity: np.ndarray, bits: int, relationship: str, photometric: str) -> np.ndarray:
    """Stored values of ``intensity`` (1 = no attenuation). ``LIN``: ∝ intensity (1 → 97 % of full
    scale); ``LOG``: ∝ log intensity, full scale spanning attenuation 6..0;
    ``DISP``: ``LOG`` through a gamma-0.7 display curve. MONOCHROME1 turns the values around
    (the Pixel Intensity Relationship Sign written is then −1)."""
    top = float(2 ** bits - 1)
    if relationship == "LIN":
        values = 0.97 * top * intensity
    else:
        level = np.clip(1.0 + np.log(np.maximum(intensity, 1e-6)) / 6.0, 0.0, 1.0)  # 1: no attenuation
        values = top * (level if relationship == "LOG" else level ** 0.7)
    if photometric == "MONOCHROME1":
        values = top - values
    return np.clip(np.round(values), 0, top).astype(np.uint16 if bits > 8 else np.uint8)


def _moved(image: np.ndarray, motion_px: tuple[float, float], rotation_deg: float = 0.0) -> np.ndarray:
    """``image`` turned by ``rotation_deg`` about its centre (counter-clockwise as displayed), then moved
    by ``(down, right)`` px (cv2's rotation matrix; independent of the reader's motion model)."""
    height, width = image.shape
    matrix = cv2.getRotationMatrix2D(((width - 1) / 2.0, (height - 1) / 2.0), rotation_deg, 1.0)
    matrix[:, 2] += (motion_px[1], motion_px[0])
    return cv2.warpAffine(image.astype(np.float32), matrix, (width, height), flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REPLICATE)


def _dataset(stack: np.ndarray, plane: Plane, name: str, settings: SkullRunSettings):
    ds = base_dataset(XA_SOP, stack.shape[1], stack.shape[2], len(stack), "A" if name == "ap" else "B")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "BIPLANE A" if name == "ap" else "BIPLANE B"]
    ds.PhotometricInterpretation = settings.photometric
    ds.PixelIntensityRelationship = settings.relationship
    ds.PixelIntensityRelationshipSign = -1 if settings.photometric == "MONOCHROME1" else 1
    if settings.bits <= 8:
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    else:
        ds.BitsStored, ds.HighBit = settings.bits, settings.bits - 1
    ds.FrameTime = 250.0
    classic_geometry(ds, plane, stack.shape[1])
    ds.PixelData = stack.tobytes()
    if not settings.recipe:
        return ds
    ds.RecommendedViewingMode = "SUB"
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    item = Dataset()
    item.MaskOperation = "AVG_SUB"
    item.MaskFrameNumbers = list(settings.mask_frames)
    item.ApplicableFrameRange = [max(settings.mask_frames) + 1, len(stack)]
    ds.MaskSubtractionSequence = Sequence([item])
    return ds


def make_skull_run(seed: int = 0, settings: SkullRunSettings = SkullRunSettings(), mesh: TriangleMesh | None = None,
                   root_mm: np.ndarray | None = None) -> NativeRunCase:
    """Generator A: a native biplane run pair (see the module docstring); ``mesh`` (default: the phantom of
    ``seed``) with its inlet ``root_mm`` (default: the phantom's)."""
    rng = np.random.default_rng(seed)
    mesh = make_vessel_phantom(seed=seed, depth=3) if mesh is None else mesh
    rig = Rig(views={name: plane.view(settings.size_px) for name, plane in PLANES.items()})
    pose = pose_in_view(mesh, rig, seed)
    if settings.bolus is not None:
        settings = replace(settings, mask_frames=tuple(range(1, settings.bolus.mask_frames + 1)))
    files, subtracted, vessels, peak = {}, {}, {}, None
    for name, view in rig.views.items():
        iodine, vessels[name] = run_iodine(mesh, view, pose, settings.fill, settings.strength, settings.bolus, root_mm)
        peak = run_peak(iodine, settings.fill, settings.strength, settings.bolus) if peak is None else peak
        still = skull_attenuation(view, settings, rng)
        if settings.catheter_mm > 0:
            from .synthetic_dsa import _catheter_mm

            still = still + IODINE_PER_MM * _catheter_mm(view, vessels[name], settings.catheter_mm, rng).astype(np.float32)
        moved = _moved(still, settings.motion_px, settings.rotation_deg)
        masks = {n - 1 for n in settings.mask_frames}
        intensity = [_intensity((still if k in masks or k < min(masks) else moved) + iodine[k], settings, rng)
                     for k in range(len(iodine))]
        stack = np.array([encode(frame, settings.bits, settings.relationship, settings.photometric)
                          for frame in intensity])
        files[name] = to_bytes(_dataset(stack, PLANES[name], name, settings))
        contrast = np.log(np.maximum(intensity[peak], 1.0 / _photons(settings)))
        clean = np.log(cv2.GaussianBlur(np.exp(-moved), (0, 0), 0.5))  # the noise-free mask, aligned
        subtracted[name] = subtracted_xa((contrast - clean).astype(np.float32), PLANES[name], name)
    return NativeRunCase(files=files, subtracted=subtracted, mesh=mesh, mesh_to_world=pose, rig=rig,
                         motion_px={name: settings.motion_px for name in rig.views}, peak_frame=peak,
                         mask_frames=tuple(n - 1 for n in settings.mask_frames), vessels=vessels)

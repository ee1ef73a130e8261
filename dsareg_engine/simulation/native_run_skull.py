"""Generator A of native runs: a skull, photon (Poisson) noise, LIN pixels, classic multi-frame XA.

Background: an ellipsoidal skull shell (bone) around an ellipsoidal brain (soft tissue), traced
per pixel ray (chord lengths through both ellipsoids), and a smooth ±8 % soft-tissue field; the
skull is placed off-centre so its rim crosses the field of view. Each pixel counts
``Poisson(N0 · exp(−attenuation))`` photons, blurred 0.5 px, stored 12-bit ``LIN`` (values ∝
intensity; no attenuation at ~4000). Tags: classic multi-frame XA (geometry only in the XA positioner / distance tags),
Recommended Viewing Mode ``SUB`` and a Mask Subtraction Sequence ``AVG_SUB`` (mask frames
1–2, applied to frames 3–N). The patient moves by ``motion_px`` between the mask and the
contrast frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.rig import Rig, ViewGeometry
from .phantom import make_vessel_phantom
from .synthetic_dsa import _smooth_field
from .native_run import (REFERENCE_PX, XA_SOP, NativeRunCase, Plane, base_dataset, classic_geometry, peak_of,
                         pose_in_view, subtracted_xa, to_bytes, vessel_frames)

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


def _counts(attenuation: np.ndarray, settings: SkullRunSettings, rng: np.random.Generator) -> np.ndarray:
    expected = _photons(settings) * np.exp(-attenuation)
    counts = rng.poisson(expected).astype(np.float32)
    counts = cv2.GaussianBlur(counts, (0, 0), 0.5)
    gain = 4000.0 / _photons(settings)  # no attenuation → ~4000 of 4095
    return np.clip(np.round(counts * gain), 0, 4095).astype(np.uint16)


def _moved(image: np.ndarray, motion_px: tuple[float, float]) -> np.ndarray:
    from ..vision.xa_motion import shift_image

    return shift_image(image, motion_px)


def _dataset(stack: np.ndarray, plane: Plane, name: str, settings: SkullRunSettings):
    ds = base_dataset(XA_SOP, stack.shape[1], stack.shape[2], len(stack), "A" if name == "ap" else "B")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "BIPLANE A" if name == "ap" else "BIPLANE B"]
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LIN", 1
    ds.RecommendedViewingMode = "SUB"
    ds.FrameTime = 250.0
    classic_geometry(ds, plane, stack.shape[1])
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    item = Dataset()
    item.MaskOperation = "AVG_SUB"
    item.MaskFrameNumbers = list(settings.mask_frames)
    item.ApplicableFrameRange = [max(settings.mask_frames) + 1, len(stack)]
    ds.MaskSubtractionSequence = Sequence([item])
    ds.PixelData = stack.tobytes()
    return ds


def make_skull_run(seed: int = 0, settings: SkullRunSettings = SkullRunSettings()) -> NativeRunCase:
    """Generator A: a native biplane run pair (see the module docstring)."""
    rng = np.random.default_rng(seed)
    mesh = make_vessel_phantom(seed=seed, depth=3)
    rig = Rig(views={name: plane.view(settings.size_px) for name, plane in PLANES.items()})
    pose = pose_in_view(mesh, rig, seed)
    files, subtracted, vessels = {}, {}, {}
    for name, view in rig.views.items():
        iodine, vessels[name] = vessel_frames(mesh, view, pose, list(settings.fill), list(settings.strength))
        still = skull_attenuation(view, settings, rng)
        moved = _moved(still, settings.motion_px)
        masks = {n - 1 for n in settings.mask_frames}
        stack = np.array([_counts((still if k in masks or k < min(masks) else moved) + iodine[k], settings, rng)
                          for k in range(len(iodine))])
        files[name] = to_bytes(_dataset(stack, PLANES[name], name, settings))
        peak = peak_of(list(settings.fill), list(settings.strength))
        contrast = np.log(np.maximum(stack[peak].astype(np.float64), 1.0))
        expected = cv2.GaussianBlur(4000.0 * np.exp(-moved), (0, 0), 0.5)
        clean = np.log(np.clip(expected, 1.0, 4095.0))  # the noise-free mask, aligned
        subtracted[name] = subtracted_xa((contrast - clean).astype(np.float32), PLANES[name], name)
    return NativeRunCase(files=files, subtracted=subtracted, mesh=mesh, mesh_to_world=pose, rig=rig,
                         motion_px={name: settings.motion_px for name in rig.views},
                         peak_frame=peak_of(list(settings.fill), list(settings.strength)),
                         mask_frames=tuple(n - 1 for n in settings.mask_frames), vessels=vessels)

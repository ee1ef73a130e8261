"""Generator B of native runs: a textured background, Gaussian noise, LOG pixels, enhanced XA.

Made to differ from generator A (:mod:`.native_run_skull`) in every part a reader depends on:

* background: a fractal (1/f^``beta``) texture, a few bone-like bands with soft edges at random
  angles and a linear heel-effect gradient (no ellipsoid, no rim);
* noise: additive Gaussian in the log domain (no photon statistics);
* pixels: ``LOG`` with Pixel Intensity Relationship Sign −1 (higher values = less intensity),
  ``MONOCHROME1``, 12 bits: ``value = offset + scale · attenuation``;
* tags: Enhanced XA with per-frame functional groups: positioner angles per frame (the C-arm
  still settling by ``settle_deg`` during the mask frames), distances and pixel spacing (and the
  intensity relationship) in the shared groups; **no** Mask Subtraction Sequence and no Recommended
  Viewing Mode, so the reader must tell the run is native and find its mask frames itself;
* timing: 14 frames, 3 mask frames, a venous-like wash-out after the peak; motion ``motion_px``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..geometry.rig import Rig
from ..mesh import TriangleMesh
from .native_run import ENHANCED_XA_SOP, NativeRunCase, Plane, base_dataset, pose_in_view, subtracted_xa, to_bytes
from .native_run_bolus import Bolus, run_iodine, run_peak
from .phantom import make_vessel_phantom

PLANES = {"ap": Plane(-6.0, 8.0, 1200.0, 800.0, 1.2), "lat": Plane(94.0, 1.0, 1180.0, 790.0, 1.2)}
LOG_OFFSET, LOG_SCALE = 300.0, 800.0


@dataclass(frozen=True)
class TextureRunSettings:
    """Attributes:
        size_px: image side.
        fill, strength: per frame, the contrast front (fraction of the tree) and iodine strength.
        n_mask_frames: frames before any contrast.
        motion_px: ``(down, right)`` patient motion of the contrast frames.
        noise_sigma: Gaussian noise of the log-domain attenuation.
        beta: spectral exponent of the texture; texture_amplitude its peak-to-peak attenuation.
        bands: bone-like bands; band_attenuation each one's attenuation.
        settle_deg: primary-angle offset recorded for the mask frames.
        bolus: a bolus passing along the tree (:mod:`.native_run_bolus`; this generator's default shape
            is the raised cosine) instead of ``fill`` / ``strength``; its frames before contrast are the masks.
        rotation_deg: in-plane patient rotation of the contrast frames (counter-clockwise as displayed).
    """

    size_px: int = 160
    fill: tuple[float, ...] = (0.0, 0.0, 0.0, 0.05, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.25, 1.3, 1.3, 1.3)
    strength: tuple[float, ...] = (1.0,) * 10 + (0.95, 0.8, 0.6, 0.45)
    n_mask_frames: int = 3
    motion_px: tuple[float, float] = (-0.3, 0.8)
    noise_sigma: float = 0.018
    beta: float = 2.6
    texture_amplitude: float = 0.6
    bands: int = 3
    band_attenuation: float = 0.7
    settle_deg: float = 0.6
    bolus: Bolus | None = None
    rotation_deg: float = 0.0


def fractal_texture(shape: tuple[int, int], beta: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise with a 1/f^beta power spectrum, scaled to [−0.5, 0.5]."""
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    radius = np.sqrt(fx * fx + fy * fy)
    radius[0, 0] = 1.0
    spectrum = (rng.normal(size=radius.shape) + 1j * rng.normal(size=radius.shape)) / radius ** (beta / 2.0)
    spectrum[0, 0] = 0.0
    field = np.fft.irfft2(spectrum, s=shape)
    return (field - field.min()) / max(float(np.ptp(field)), 1e-12) - 0.5


def bands(shape: tuple[int, int], count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` soft-edged straight bands (0..1) at random angles, widths 6–14 % of the image."""
    height, width = shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    out = np.zeros(shape)
    for _ in range(count):
        angle = rng.uniform(0, np.pi)
        centre = rng.uniform(0.2, 0.8, size=2) * (width, height)
        distance = np.abs((u - centre[0]) * np.sin(angle) - (v - centre[1]) * np.cos(angle))
        half = rng.uniform(0.03, 0.07) * width
        out += 1.0 / (1.0 + np.exp((distance - half) / 1.5))
    return out


def texture_attenuation(shape: tuple[int, int], settings: TextureRunSettings, rng: np.random.Generator) -> np.ndarray:
    texture = settings.texture_amplitude * fractal_texture(shape, settings.beta, rng)
    heel = np.linspace(-0.15, 0.15, shape[1])[None, :]
    return (1.6 + texture + settings.band_attenuation * bands(shape, settings.bands, rng) + heel).astype(np.float32)


def _frame_groups(plane: Plane, n_frames: int, n_masks: int, settle_deg: float, size_px: int):
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    frames = []
    for k in range(n_frames):
        item, content, positioner = Dataset(), Dataset(), Dataset()
        content.FrameAcquisitionNumber, content.TemporalPositionIndex = k + 1, k + 1
        item.FrameContentSequence = Sequence([content])
        positioner.PositionerPrimaryAngle = plane.primary_deg + (settle_deg if k < n_masks else 0.0)
        positioner.PositionerSecondaryAngle = plane.secondary_deg
        item.PositionerPositionSequence = Sequence([positioner])
        frames.append(item)
    shared, geometry, pixels = Dataset(), Dataset(), Dataset()
    geometry.DistanceSourceToIsocenter, geometry.DistanceSourceToDetector = plane.sod_mm, plane.sid_mm
    spacing = round(plane.spacing_at(size_px), 6)
    pixels.ImagerPixelSpacing = [spacing, spacing]
    pixels.PixelIntensityRelationship, pixels.PixelIntensityRelationshipSign = "LOG", -1
    shared.XRayGeometrySequence = Sequence([geometry])
    shared.FramePixelDataPropertiesSequence = Sequence([pixels])
    return Sequence(frames), Sequence([shared])


def _dataset(stack: np.ndarray, plane: Plane, name: str, settings: TextureRunSettings):
    ds = base_dataset(ENHANCED_XA_SOP, stack.shape[1], stack.shape[2], len(stack), "A" if name == "ap" else "B")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE", "NONE"]
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.PerFrameFunctionalGroupsSequence, ds.SharedFunctionalGroupsSequence = _frame_groups(
        plane, len(stack), settings.n_mask_frames, settings.settle_deg, stack.shape[1])
    ds.PixelData = stack.tobytes()
    return ds


def make_texture_run(seed: int = 0, settings: TextureRunSettings = TextureRunSettings(),
                     mesh: TriangleMesh | None = None, root_mm: np.ndarray | None = None) -> NativeRunCase:
    """Generator B: a native biplane run pair (see the module docstring); ``mesh`` (default: the phantom of
    ``seed + 7``) with its inlet ``root_mm`` (default: the phantom's)."""
    rng = np.random.default_rng(1000 + seed)
    mesh = make_vessel_phantom(seed=seed + 7, depth=3) if mesh is None else mesh
    rig = Rig(views={name: plane.view(settings.size_px) for name, plane in PLANES.items()})
    pose = pose_in_view(mesh, rig, seed + 7)
    if settings.bolus is not None:
        settings = replace(settings, n_mask_frames=settings.bolus.mask_frames)
    files, subtracted, vessels, peak = {}, {}, {}, None
    for name, view in rig.views.items():
        iodine, vessels[name] = run_iodine(mesh, view, pose, settings.fill, settings.strength, settings.bolus, root_mm)
        peak = run_peak(iodine, settings.fill, settings.strength, settings.bolus) if peak is None else peak
        still = texture_attenuation(view.image_size[::-1], settings, rng)
        centre = ((still.shape[1] - 1) / 2.0, (still.shape[0] - 1) / 2.0)
        matrix = cv2.getRotationMatrix2D(centre, settings.rotation_deg, 1.0)
        matrix[:, 2] += (settings.motion_px[1], settings.motion_px[0])
        moved = cv2.warpAffine(still, matrix, still.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        frames = []
        for k in range(len(iodine)):
            background = still if k < settings.n_mask_frames else moved
            attenuation = background + iodine[k] + rng.normal(0.0, settings.noise_sigma, still.shape)
            frames.append(np.clip(np.round(LOG_OFFSET + LOG_SCALE * attenuation), 0, 4095).astype(np.uint16))
        stack = np.array(frames)
        files[name] = to_bytes(_dataset(stack, PLANES[name], name, settings))
        contrast = -(stack[peak].astype(np.float64) - LOG_OFFSET) / LOG_SCALE
        subtracted[name] = subtracted_xa((contrast + moved).astype(np.float32), PLANES[name], name)
    return NativeRunCase(files=files, subtracted=subtracted, mesh=mesh, mesh_to_world=pose, rig=rig,
                         motion_px={name: settings.motion_px for name in rig.views}, peak_frame=peak,
                         mask_frames=tuple(range(settings.n_mask_frames)), vessels=vessels)

"""Grey-level subtracted DSA images synthesized from a vessel model (tests and benchmarks).

Per view: the X-ray path length through the model per pixel (``thickness``, mm; rendered at
``supersample``× and area-averaged, so border pixels carry partial thickness like a real
detector), Beer–Lambert attenuation ``exp(−μ t)`` of an uneven background (a smooth random
field), a catheter (a thin contrast-filled tube entering from an image edge, drawn in 2D),
a Gaussian detector blur, and Gaussian noise. Vessels come out dark on a bright background,
as DSA is displayed. The true vessel mask is the model's silhouette at the same pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from ..geometry.rig import Rig, ViewGeometry
from ..mesh import TriangleMesh


@dataclass(frozen=True)
class DsaSettings:
    """Image formation.

    Attributes:
        attenuation_per_mm: μ of contrast-filled vessel (iodine mixture), 1/mm.
        background: mean background level (full scale = 1).
        background_variation: peak-to-peak amplitude of the smooth background field.
        background_cells: the field is a bicubic interpolation of this many random values per side
            (4: it varies over about a third of the image; more: finer structure).
        noise_sigma: Gaussian noise, full-scale units.
        blur_px: detector / focal-spot blur (Gaussian σ, px).
        supersample: thickness rendered at this factor per side.
        catheter_mm: catheter diameter at the isocentre (0: none); drawn with the
            attenuation of that much contrast.
    """

    attenuation_per_mm: float = 0.12
    background: float = 0.8
    background_variation: float = 0.25
    background_cells: int = 4
    noise_sigma: float = 0.01
    blur_px: float = 0.5
    supersample: int = 3
    catheter_mm: float = 1.4


@njit(cache=True)
def _path_length(vertices_view, faces, fx, fy, u0, v0, height, width, out):
    """out[v, u] += Σ_faces sign · distance along the pixel's ray to the face (mm).

    vertices_view (V, 3) view-frame mm; a closed surface gives ± the path length inside it.
    """
    for f in range(faces.shape[0]):
        a = vertices_view[faces[f, 0]]
        b = vertices_view[faces[f, 1]]
        c = vertices_view[faces[f, 2]]
        if a[2] < 1.0 or b[2] < 1.0 or c[2] < 1.0:
            continue
        ua, va = u0 + fx * a[0] / a[2], v0 + fy * a[1] / a[2]
        ub, vb = u0 + fx * b[0] / b[2], v0 + fy * b[1] / b[2]
        uc, vc = u0 + fx * c[0] / c[2], v0 + fy * c[1] / c[2]
        area = (ub - ua) * (vc - va) - (vb - va) * (uc - ua)
        if area == 0.0:
            continue
        n0 = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
        n1 = (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2])
        n2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        plane = n0 * a[0] + n1 * a[1] + n2 * a[2]
        x0 = max(int(np.ceil(min(ua, ub, uc))), 0)
        x1 = min(int(np.floor(max(ua, ub, uc))), width - 1)
        y0 = max(int(np.ceil(min(va, vb, vc))), 0)
        y1 = min(int(np.floor(max(va, vb, vc))), height - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                w0 = (ub - x) * (vc - y) - (vb - y) * (uc - x)
                w1 = (uc - x) * (va - y) - (vc - y) * (ua - x)
                w2 = (ua - x) * (vb - y) - (va - y) * (ub - x)
                if (w0 >= 0 and w1 >= 0 and w2 >= 0) or (w0 <= 0 and w1 <= 0 and w2 <= 0):
                    dx, dy = (x - u0) / fx, (y - v0) / fy
                    dot = n0 * dx + n1 * dy + n2
                    if dot != 0.0:
                        depth = plane / dot  # z of the hit; the ray is depth · (dx, dy, 1)
                        out[y, x] += np.sign(dot) * depth * np.sqrt(dx * dx + dy * dy + 1.0)


def vessel_thickness_mm(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, supersample: int = 3) -> np.ndarray:
    """``(H, W)`` mean X-ray path length through the closed mesh per pixel (mm)."""
    fine = view.resized(view.width * supersample, view.height * supersample)
    mesh_to_view = fine.world_to_view @ mesh_to_world
    vertices = mesh.vertices @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    out = np.zeros((fine.height, fine.width))
    _path_length(vertices, mesh.faces, *fine.focal_px, *fine.principal_point_px, fine.height, fine.width, out)
    return cv2.resize(np.abs(out), view.image_size, interpolation=cv2.INTER_AREA)


def _smooth_field(shape: tuple[int, int], rng: np.random.Generator, cells: int = 4) -> np.ndarray:
    """A smooth random field in [−0.5, 0.5] varying over about ``1 / (cells − 1)`` of the image."""
    coarse = rng.normal(size=(cells, cells)).astype(np.float32)
    field = cv2.resize(coarse, shape[::-1], interpolation=cv2.INTER_CUBIC)
    return (field - field.min()) / max(float(np.ptp(field)), 1e-9) - 0.5


def _catheter_mm(view: ViewGeometry, thickness: np.ndarray, diameter_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Path length (mm) of a catheter entering from the bottom edge, its tip in the vessels' lowest
    point in the image (where a parent artery usually enters the field)."""
    height, width = thickness.shape
    rows, cols = np.nonzero(thickness > 0.5 * np.percentile(thickness[thickness > 0], 90)) if (thickness > 0).any() else ((), ())
    lowest = int(np.argmax(rows)) if len(rows) else None
    end = np.array([cols[lowest], rows[lowest]], float) if lowest is not None else np.array([width / 2, height / 2])
    start = np.array([rng.uniform(0.3, 0.7) * width, height + 5.0])
    bend = rng.uniform(-0.15, 0.15) * width
    s = np.linspace(0.0, 1.0, 60)[:, None]
    path = (1 - s) * start + s * end + np.sin(np.pi * s) * np.array([bend, 0.0])
    scale = 8  # sub-pixel line drawing
    canvas = np.zeros((height * scale, width * scale), np.float32)
    radius_px = 0.5 * diameter_mm * view.focal_px[0] / np.linalg.norm(view.source_position_world)  # at the isocentre
    points = np.round((path + 0.5) * scale - 0.5).astype(np.int32)
    cv2.polylines(canvas, [points], False, 1.0, thickness=max(1, int(round(2 * radius_px * scale))))
    return cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA) * diameter_mm * np.pi / 4


def synthesize_dsa(mesh: TriangleMesh, rig: Rig, mesh_to_world: np.ndarray, seed: int = 0,
                   settings: DsaSettings = DsaSettings()) -> dict[str, np.ndarray]:
    """``{view: (H, W) float32}`` DSA images in [0, 1], vessels dark."""
    rng = np.random.default_rng(seed)
    images = {}
    for name, view in rig.views.items():
        thickness = vessel_thickness_mm(mesh, view, mesh_to_world, settings.supersample)
        if settings.catheter_mm > 0:
            thickness = thickness + _catheter_mm(view, thickness, settings.catheter_mm, rng)
        background = settings.background * (1.0 + settings.background_variation * _smooth_field(thickness.shape, rng, settings.background_cells))
        image = background * np.exp(-settings.attenuation_per_mm * thickness)
        if settings.blur_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), settings.blur_px)
        image = image + rng.normal(0.0, settings.noise_sigma, image.shape)
        images[name] = np.clip(image, 0.0, 1.0).astype(np.float32)
    return images

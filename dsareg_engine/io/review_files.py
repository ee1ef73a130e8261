"""What a person reviews a registration with: the image registered, the outlines as layers, the model and the C-arm.

* ``image_<view>.png`` (:func:`registered_image`): the image the registration actually fitted (the frame or the
  frames combined, subtracted: ``Case.images``), 8-bit grey at its own pixel grid, contrast stretched between
  the 0.5 and 99.5 percentiles, polarity as given.
* ``layers_<view>.png`` (:func:`layer_image`): the same grid, RGB, one layer per channel so a page can toggle
  them: **R** 255 on the outline of the initial pose's silhouette, **G** 255 on the outline of the registered
  one, **B** bit 7 (128) the vessel mask (the segmentation fitted), bit 6 (64) model pixels with no vessel under
  them ("unfilled").
* ``model.json`` (:func:`model_document`): the model's vertices **as given** (OBJ ``v`` lines in order,
  duplicates kept; the order hemodynamics' per-vertex arrays follow, ``hemodynamics.model_points``) with its
  triangles, both poses (``mesh_to_world`` registered, ``initial_mesh_to_world``) and per view the C-arm as it
  stood (:func:`detector_geometry`).

**Detector geometry** (the convention of :mod:`dsareg_engine.geometry.rig`): the source is the view frame's
origin; the image plane is ``z = sid_mm``, where pixel ``(u, v)`` sits at ``x = (u − u0)·du``,
``y = (v − v0)·dv``. ``corners_mm`` are the world positions of the image's outer corners
``(u, v) = (−0.5, −0.5), (W − 0.5, −0.5), (W − 0.5, H − 0.5), (−0.5, H − 0.5)``: top-left, top-right,
bottom-right, bottom-left of the stored image. ``mm_per_px_at_model`` is a pixel's size at the depth of the
model's centre (registered pose): what keeps two views at one mm scale on a page.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import cv2
import numpy as np

from ..geometry.pose import invert_rigid
from ..geometry.rig import ViewGeometry

from ..artifacts import MODEL_JSON, image_png, layers_png  # noqa: F401 - the names, spelled once
from .mesh_limits import review_bytes

INITIAL, REGISTERED, MASK_BIT, UNFILLED_BIT = 255, 255, 128, 64
_OBJ_LINE = re.compile(rb"(?m)^[ \t]*(v|f)[ \t]+([^\r\n#]*)")


def registered_image(pixels: np.ndarray) -> np.ndarray:
    """``(H, W)`` float image → ``(H, W)`` uint8, stretched between its 0.5 and 99.5 percentiles."""
    image = np.nan_to_num(np.asarray(pixels, np.float32))
    low, high = np.percentile(image, (0.5, 99.5))
    if high <= low:
        low, high = float(image.min()), float(image.max())
    return np.round(np.clip((image - low) / max(high - low, 1e-6), 0.0, 1.0) * 255).astype(np.uint8)


def outline(mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels of ``mask`` with a 4-neighbour outside it (the silhouette's 1-pixel edge)."""
    inside = np.asarray(mask, bool)
    eroded = cv2.erode(inside.astype(np.uint8), np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return inside & ~eroded


def layer_image(initial: np.ndarray, registered: np.ndarray, mask: np.ndarray, unfilled: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 **RGB** layers (see the module docstring for the channels)."""
    layers = np.zeros((*np.asarray(mask).shape, 3), np.uint8)
    layers[..., 0] = np.where(outline(initial), INITIAL, 0)
    layers[..., 1] = np.where(outline(registered), REGISTERED, 0)
    layers[..., 2] = np.where(np.asarray(mask, bool), MASK_BIT, 0) | np.where(np.asarray(unfilled, bool), UNFILLED_BIT, 0)
    return layers


def detector_geometry(view: ViewGeometry, mm_per_px_at_model: float | None) -> dict:
    """The C-arm of one view in world mm: ``source_mm``, ``corners_mm`` (4, 3), ``image_size_px``, ``sid_mm``."""
    width, height = view.image_size
    du, dv = view.pixel_spacing_mm
    u0, v0 = view.principal_point_px
    corners_px = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    in_view = np.column_stack([(corners_px[:, 0] - u0) * du, (corners_px[:, 1] - v0) * dv,
                               np.full(4, view.sid_mm), np.ones(4)])
    world = (invert_rigid(view.world_to_view) @ in_view.T).T[:, :3]
    return {"source_mm": [round(float(x), 4) for x in view.source_position_world],
            "corners_mm": [[round(float(x), 4) for x in corner] for corner in world],
            "image_size_px": [int(width), int(height)], "sid_mm": float(view.sid_mm),
            "pixel_spacing_mm": [float(du), float(dv)],
            "mm_per_px_at_model": None if mm_per_px_at_model is None else round(float(mm_per_px_at_model), 6)}


def _obj_index(token: bytes, count: int) -> int:
    index = int(token.split(b"/")[0])
    return index - 1 if index > 0 else count + index  # negative: relative to the vertices read so far


def obj_as_given(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """An OBJ's ``v`` lines in order ``(V, 3)`` (duplicates kept) and its faces fan-triangulated ``(F, 3)``."""
    vertices: list[list[float]] = []
    faces: list[list[int]] = []
    for kind, rest in _OBJ_LINE.findall(data):
        fields = rest.split()
        if kind == b"v":
            vertices.append([float(x) for x in fields[:3]])
            continue
        corners = [_obj_index(token, len(vertices)) for token in fields]
        faces.extend([corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1))
    return np.array(vertices, np.float64).reshape(-1, 3), np.array(faces, np.int64).reshape(-1, 3)


def model_as_given(data: bytes | None, name: str | None, mesh) -> tuple[np.ndarray, np.ndarray, str]:
    """The model file's vertices and faces as given, and what they are (``"file"`` or, for a volume input or
    a format read otherwise, ``"working mesh"``: the surface the registration used)."""
    suffix = Path(name or "").suffix.lower().lstrip(".")
    if data is not None and suffix == "obj":
        return (*obj_as_given(bytes(data)), "file")
    if data is not None and suffix in ("ply", "off", "stl"):
        import trimesh

        loaded = trimesh.load(file_obj=io.BytesIO(bytes(data)), file_type=suffix, force="mesh", process=False)
        vertices, faces = np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64)
        if suffix == "stl":  # three vertices per triangle, as hemodynamics counts them
            return vertices[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3), "file"
        return vertices, faces, "file"
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), "working mesh"


def model_document(vertices: np.ndarray, faces: np.ndarray, vertex_order: str, data: dict) -> dict:
    """``model.json``: vertices ``(V, 3)`` mm, faces ``(F, 3)``, both poses and each view's detector."""
    return {"units": "mm", "vertex_order": vertex_order, "vertex_count": int(len(vertices)),
            "vertices": np.round(vertices, 4).ravel().tolist(), "faces": faces.ravel().tolist(),
            "poses": {"registered": data["mesh_to_world"], "initial": data["initial_mesh_to_world"]},
            "views": {name: view["detector"] for name, view in data.get("views", {}).items() if "detector" in view}}


def write_model_json(out_dir: Path, mesh_bytes: bytes | None, mesh_name: str | None, mesh, data: dict) -> None:
    vertices, faces, order = model_as_given(review_bytes(mesh_bytes), mesh_name, mesh)  # size bounded
    (Path(out_dir) / MODEL_JSON).write_text(json.dumps(model_document(vertices, faces, order, data),
                                                       separators=(",", ":")))


def write_view_files(out_dir: Path, result, masks: dict[str, np.ndarray], images: dict[str, np.ndarray] | None,
                     rig, scales: dict[str, float | None], data: dict) -> None:
    """Per view: ``image_<view>.png`` (when the image is known), ``layers_<view>.png`` and
    ``data["views"][view]["detector"]`` (before ``result.json`` is written); ``scales``: mm per pixel at the model."""
    from ..overlay import write_png
    from ..registration.partial import unmatched_pixels

    for name, view in result.views.items():
        data["views"][name]["detector"] = detector_geometry(rig.views[name], scales.get(name))
        image = (images or {}).get(name)
        if image is not None and image.shape == masks[name].shape:
            write_png(Path(out_dir) / image_png(name), registered_image(image))
        layers = layer_image(view.initial_silhouette, view.silhouette, masks[name],
                             unmatched_pixels(view.silhouette, masks[name]))
        write_png(Path(out_dir) / layers_png(name), layers[..., ::-1])  # cv2 writes BGR

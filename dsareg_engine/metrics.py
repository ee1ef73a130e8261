"""Error metrics: overlap of silhouettes, and pose errors against a known truth (mm, degrees)."""

from __future__ import annotations

import cv2
import numpy as np

from .geometry.rig import ViewGeometry
from .geometry.pose import invert_rigid, rotation_error_deg


def dice(mask_a: np.ndarray, mask_b: np.ndarray) -> float:
    """Dice coefficient of two boolean masks of the same shape (1.0 when both are empty)."""
    a, b = np.asarray(mask_a, bool), np.asarray(mask_b, bool)
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else float(2.0 * np.logical_and(a, b).sum() / total)


def within_px(mask: np.ndarray, tolerance_px: float) -> np.ndarray:
    """``(H, W)`` bool: the pixels whose centre lies within ``tolerance_px`` (Euclidean, inclusive) of a pixel of
    ``mask`` (``(H, W)`` bool), the mask's own pixels included; none when the mask is empty.

    A dilation by the disc of integer offsets ``dx² + dy² ≤ tolerance²``: the same pixels as thresholding the exact
    Euclidean distance transform of the background (``tests/unit/test_metrics.py`` checks it against one), at a
    small fraction of its cost for the few-pixel tolerances used here (~0.2 against ~14 CPU ms at 800 × 800)."""
    if tolerance_px < 0:
        return np.zeros(mask.shape, bool)
    radius = int(np.floor(tolerance_px))
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    disc = (dx * dx + dy * dy <= tolerance_px * tolerance_px).astype(np.uint8)
    return cv2.dilate(np.asarray(mask, bool).astype(np.uint8), disc, borderType=cv2.BORDER_CONSTANT,
                      borderValue=0).astype(bool)


def iou(mask_a: np.ndarray, mask_b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(mask_a, bool), np.asarray(mask_b, bool)
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def transform_points_np(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points through a 4x4 transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def mean_distance_mm(pose_a: np.ndarray, pose_b: np.ndarray, points: np.ndarray) -> float:
    """Mean distance between ``points`` (mesh frame) placed by two poses (ADD / mTRE), mm."""
    diff = transform_points_np(pose_a, points) - transform_points_np(pose_b, points)
    return float(np.linalg.norm(diff, axis=1).mean())


def source_position_error_mm(
    estimated_mesh_to_world: np.ndarray, true_mesh_to_world: np.ndarray, view: ViewGeometry
) -> float:
    """The paper's translation error: distance between the view's X-ray source positions
    expressed in the mesh frame under the estimated and the true pose, mm."""
    source_world = np.append(view.source_position_world, 1.0)
    estimated = invert_rigid(estimated_mesh_to_world) @ source_world
    true = invert_rigid(true_mesh_to_world) @ source_world
    return float(np.linalg.norm(estimated[:3] - true[:3]))


def mean_projection_distance_mm(
    estimated_mesh_to_world: np.ndarray, true_mesh_to_world: np.ndarray, view: ViewGeometry, points: np.ndarray
) -> float:
    """Mean distance between the projections of ``points`` under the two poses, mm at the detector."""
    est = view.project(transform_points_np(estimated_mesh_to_world, points))
    true = view.project(transform_points_np(true_mesh_to_world, points))
    spacing = np.asarray(view.pixel_spacing_mm)
    return float(np.linalg.norm((est - true) * spacing, axis=1).mean())


def ground_truth_errors(
    estimated_mesh_to_world: np.ndarray,
    true_mesh_to_world: np.ndarray,
    views: dict[str, ViewGeometry],
    vertices: np.ndarray,
    targets: np.ndarray | None = None,
    reference_view: str = "ap",
) -> dict:
    """All the synthetic-study errors of the registration issue, as a JSON-ready dict.

    Args:
        vertices: ``(V, 3)`` mesh-frame points for ADD.
        targets: ``(N, 3)`` mesh-frame target points for mTRE (default: the vertices).
        reference_view: whose source position defines the translation error (the paper: AP).
    """
    reference = views.get(reference_view) or next(iter(views.values()))
    return {
        "rotation_error_deg": rotation_error_deg(estimated_mesh_to_world[:3, :3], true_mesh_to_world[:3, :3]),
        "translation_error_mm": source_position_error_mm(estimated_mesh_to_world, true_mesh_to_world, reference),
        "add_mm": mean_distance_mm(estimated_mesh_to_world, true_mesh_to_world, vertices),
        "mtre_mm": mean_distance_mm(
            estimated_mesh_to_world, true_mesh_to_world, vertices if targets is None else targets
        ),
        "mpd_mm": {
            name: mean_projection_distance_mm(estimated_mesh_to_world, true_mesh_to_world, view, vertices)
            for name, view in views.items()
        },
    }

"""The registration result object and its JSON layout (``result.json``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ViewResult:
    """Per-view outcome.

    Attributes:
        world_to_view: 4x4 (the rig's, unchanged).
        mesh_to_view: 4x4 = ``world_to_view · mesh_to_world`` (the paper's P).
        projection_matrix: 3x4 mapping homogeneous mesh-frame mm to homogeneous pixels.
        dice, iou: final hard silhouette vs the target mask at full resolution.
        silhouette: ``(H, W)`` bool final hard silhouette (not serialized).
        initial_silhouette: ``(H, W)`` bool silhouette at the initial pose (not serialized).
    """

    world_to_view: np.ndarray
    mesh_to_view: np.ndarray
    projection_matrix: np.ndarray
    dice: float
    iou: float
    silhouette: np.ndarray = field(repr=False)
    initial_silhouette: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        return {
            "world_to_view": self.world_to_view.tolist(),
            "mesh_to_view": self.mesh_to_view.tolist(),
            "projection_matrix": self.projection_matrix.tolist(),
            "dice": self.dice,
            "iou": self.iou,
        }


@dataclass
class RegistrationResult:
    """What :func:`register` returns.

    Attributes:
        mesh_to_world: 4x4 estimated pose.
        initial_mesh_to_world: 4x4 pose the registration started from.
        views: per view results, keyed ``"ap"``/``"lat"``.
        metrics: loss, iterations/seconds per stage, device, converged flag and reason,
            starts agreeing, and ``ground_truth`` errors when a truth was given.
        loss_history: ``[(stage name, [loss per iteration])]`` of the kept start.
        pose_history: ``(N, 4, 4)`` poses of the kept start along the way (for animations).
        frames: ``[(stage name, iteration, 4x4 pose)]`` from the initial pose on, one per
            iteration of each stage's best start; recorded only with ``options.animation``.
    """

    mesh_to_world: np.ndarray
    initial_mesh_to_world: np.ndarray
    views: dict[str, ViewResult]
    metrics: dict
    loss_history: list[tuple[str, list[float]]] = field(default_factory=list, repr=False)
    pose_history: list[np.ndarray] = field(default_factory=list, repr=False)
    frames: list[tuple[str, int, np.ndarray]] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        """The JSON-ready result; ``verdict`` repeats ``metrics.confidence.verdict`` (ok / check / failed)."""
        verdict = (self.metrics.get("confidence") or {}).get("verdict")
        return {
            "mesh_to_world": self.mesh_to_world.tolist(),
            "initial_mesh_to_world": self.initial_mesh_to_world.tolist(),
            "views": {name: view.to_dict() for name, view in self.views.items()},
            "metrics": self.metrics,
            **({"verdict": verdict} if verdict else {}),
        }

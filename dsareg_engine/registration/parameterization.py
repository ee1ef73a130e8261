"""Pose increments about the current estimate, scaled so one step size suits all six DoF.

``mesh_to_world(δ) = Trans(c + τ) · Rot(ω / L) · Trans(−c) · base`` where ``c`` is the mesh
centre in world mm, ``δ = (ω, τ)``, τ in mm and ω in "mm at the mesh's radius" (the
rotation angle times ``L``, the RMS vertex distance from the centre). A unit change of
any component moves the mesh by about 1 mm.
"""

from __future__ import annotations

import numpy as np
import torch

from ..geometry.pose import so3_exp, so3_log


class PoseIncrement:
    """Maps increments ``δ`` ``(B, 6)`` to poses ``(B, 4, 4)`` around base poses.

    Args:
        base_mesh_to_world: ``(B, 4, 4)`` float64 numpy.
        mesh_centre: ``(3,)`` mesh-frame mm (rotation centre).
        radius_mm: rotation scale ``L``.
    """

    def __init__(self, base_mesh_to_world: np.ndarray, mesh_centre: np.ndarray, radius_mm: float):
        self.base = torch.as_tensor(np.asarray(base_mesh_to_world), dtype=torch.float64)
        centre_h = np.append(mesh_centre, 1.0)
        self.centre_world = self.base @ torch.as_tensor(centre_h, dtype=torch.float64)  # (B, 4)
        self.radius_mm = float(radius_mm)

    def __call__(self, delta: torch.Tensor) -> torch.Tensor:
        """``(B, 6)`` → ``(B, 4, 4)`` float64, differentiable in ``delta``."""
        delta = delta.to(torch.float64)
        rotation = so3_exp(delta[:, :3] / self.radius_mm)
        centre = self.centre_world[:, :3]
        translation = centre + delta[:, 3:] - (rotation @ centre[..., None])[..., 0]
        top = torch.cat([rotation, translation[..., None]], dim=-1)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(delta.shape[0], 1, 4)
        return torch.cat([top, bottom], dim=1) @ self.base

    def tangents(self) -> np.ndarray:
        """∂mesh_to_world/∂δ_k at δ = 0: ``(B, 6, 4, 4)`` (ω about the centre scaled by 1/L, then τ)."""
        generators = np.zeros((len(self.base), 6, 4, 4))
        centre = self.centre_world[:, :3].numpy()
        for k in range(3):
            axis = np.zeros(3)
            axis[k] = 1.0 / self.radius_mm
            hat = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
            generators[:, k, :3, :3] = hat
            generators[:, k, :3, 3] = -centre @ hat.T
            generators[:, k + 3, k, 3] = 1.0
        return generators @ self.base.numpy()[:, None]

    def delta_of(self, mesh_to_world: np.ndarray) -> np.ndarray:
        """The increments ``(B, 6)`` that give ``mesh_to_world`` ``(B, 4, 4)`` (inverse of ``poses``)."""
        relative = mesh_to_world @ np.linalg.inv(self.base.numpy())
        centre = self.centre_world[:, :3].numpy()
        omega = np.stack([so3_log(rotation) for rotation in relative[:, :3, :3]]) * self.radius_mm
        tau = relative[:, :3, 3] - centre + np.einsum("bij,bj->bi", relative[:, :3, :3], centre)
        return np.concatenate([omega, tau], axis=1)

    def poses(self, delta: torch.Tensor) -> np.ndarray:
        """Detached ``(B, 4, 4)`` numpy poses."""
        with torch.no_grad():
            return self(delta).numpy()


def mesh_radius_mm(vertices: np.ndarray) -> float:
    """RMS distance of the vertices from their centroid (mm)."""
    return float(np.sqrt(((vertices - vertices.mean(axis=0)) ** 2).sum(axis=1).mean()))


def random_start_poses(
    initial_mesh_to_world: np.ndarray,
    mesh_centre: np.ndarray,
    count: int,
    spread_deg: float,
    spread_mm: float,
    seed: int,
) -> np.ndarray:
    """``count`` poses: the initial one, then perturbations of it about the mesh centre.

    Each perturbation has a uniformly random axis and direction, rotation angle
    ``spread_deg`` and translation length ``spread_mm`` (fixed magnitudes, like a
    standardized offset study). Returns ``(count, 4, 4)``.
    """
    rng = np.random.default_rng(seed)
    poses = [np.asarray(initial_mesh_to_world, dtype=np.float64)]
    increment = PoseIncrement(poses[0][None], mesh_centre, 1.0)
    for _ in range(count - 1):
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        delta = np.concatenate(
            [np.radians(spread_deg) * axis / np.linalg.norm(axis), spread_mm * direction / np.linalg.norm(direction)]
        )
        poses.append(increment.poses(torch.as_tensor(delta[None]))[0])
    return np.stack(poses)

"""Rigid transforms: rotation exponentials, look-at, validation, error angles.

Conventions used throughout dsareg:

* A transform ``a_to_b`` is a 4x4 homogeneous matrix acting on **column** vectors:
  ``p_b = a_to_b @ p_a``. Composition reads right to left:
  ``mesh_to_view = world_to_view @ mesh_to_world``.
* Units are millimetres for translations and radians for rotation vectors unless a
  name says ``_deg``.
* Batched tensors carry the batch first: rotation vectors ``(B, 3)``, rotations
  ``(B, 3, 3)``, transforms ``(B, 4, 4)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import DsaregInputError

if TYPE_CHECKING:  # torch is imported where it is used, so numpy-only users (the API) stay light
    import torch

ORTHONORMAL_TOLERANCE = 1e-4
"""Largest entry of ``|R Rᵀ − I|`` accepted for a rotation (or mirrored rotation)."""


def so3_exp(rotation_vector: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, smooth at zero.

    Args:
        rotation_vector: ``(B, 3)`` axis × angle (radians).

    Returns:
        ``(B, 3, 3)`` rotation matrices.
    """
    import torch

    theta_sq = (rotation_vector * rotation_vector).sum(-1, keepdim=True)  # (B, 1)
    small = theta_sq < 1e-8
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = safe_sq.sqrt()
    # Taylor expansions below 1e-4 rad keep the gradient exact at the identity.
    a = torch.where(small, 1.0 - theta_sq / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta_sq / 24.0, (1.0 - torch.cos(theta)) / safe_sq)
    k = hat(rotation_vector)
    eye = torch.eye(3, dtype=rotation_vector.dtype, device=rotation_vector.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def hat(vector: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric cross-product matrices: ``(B, 3) -> (B, 3, 3)``."""
    import torch

    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )


def so3_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (radians) of a 3x3 rotation matrix (numpy, float64)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    cos_angle = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos_angle))
    axis_unnorm = np.array(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )
    if angle < 1e-7:
        return 0.5 * axis_unnorm
    if np.pi - angle < 1e-4:
        # Near 180 degrees the antisymmetric part vanishes; take the axis from R + I.
        sym = rotation + np.eye(3)
        column = sym[:, int(np.argmax(np.diag(sym)))]
        return angle * column / np.linalg.norm(column)
    return angle * axis_unnorm / (2.0 * np.sin(angle))


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """3x3 rotation by ``angle_rad`` about ``axis`` (right-hand rule), numpy float64."""
    axis = np.asarray(axis, dtype=np.float64)
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 linear part and a 3-vector."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = translation
    return transform


def invert_rigid(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (or mirrored-rigid) 4x4 transform, using ``R⁻¹ = Rᵀ``."""
    transform = np.asarray(transform, dtype=np.float64)
    rotation_t = transform[:3, :3].T
    return make_transform(rotation_t, -rotation_t @ transform[:3, 3])


def look_at_world_to_view(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """A dsareg view (+z toward ``target``, +y image rows *down*) placed at ``eye``.

    The image's row axis (+y) points opposite to ``up`` as projected on the image
    plane, so ``up`` appears at the top of the image (row 0), like a radiograph
    displayed upright. +x = y × z keeps the frame right-handed (det +1).

    Args:
        eye, target, up: 3-vectors in world millimetres.

    Returns:
        4x4 ``world_to_view``.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z_axis = target - eye
    if np.linalg.norm(z_axis) < 1e-9:
        raise DsaregInputError("eye and target coincide", field="look_at")
    z_axis /= np.linalg.norm(z_axis)
    y_axis = -(up - np.dot(up, z_axis) * z_axis)
    if np.linalg.norm(y_axis) < 1e-9:
        raise DsaregInputError("up is parallel to the viewing direction", field="look_at")
    y_axis /= np.linalg.norm(y_axis)
    x_axis = np.cross(y_axis, z_axis)
    rotation = np.stack([x_axis, y_axis, z_axis])  # rows: view axes in world coordinates
    return make_transform(rotation, -rotation @ eye)


def validate_rigid(
    matrix: np.ndarray | list, *, field: str, allow_mirror: bool, tolerance: float = ORTHONORMAL_TOLERANCE
) -> np.ndarray:
    """Check a 4x4 rigid transform and return it as float64.

    Args:
        matrix: Candidate 4x4 (nested lists or array).
        field: Name used in the error message.
        allow_mirror: Accept a 3x3 part with determinant -1 (mirrored detector frames).

    Raises:
        DsaregInputError: wrong shape, non-finite entries, last row not ``[0, 0, 0, 1]``,
            non-orthonormal 3x3 part, or a mirror where none is allowed.
    """
    try:
        array = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DsaregInputError("is not a numeric matrix", field=field, accepted="a 4x4 list of numbers") from exc
    if array.shape != (4, 4):
        raise DsaregInputError(f"has shape {list(array.shape)}", field=field, accepted="a 4x4 matrix")
    if not np.all(np.isfinite(array)):
        raise DsaregInputError("contains NaN or infinite values", field=field, accepted="finite numbers")
    if np.max(np.abs(array[3] - [0, 0, 0, 1])) > 1e-9:
        raise DsaregInputError("last row must be [0, 0, 0, 1]", field=field, accepted="a homogeneous rigid transform")
    rotation = array[:3, :3]
    deviation = float(np.max(np.abs(rotation @ rotation.T - np.eye(3))))
    if deviation > tolerance:
        raise DsaregInputError(
            f"3x3 part is not orthonormal (max |R Rᵀ − I| = {deviation:.3g}); scaling and shear are not rigid",
            field=field,
            accepted=f"an orthonormal 3x3 part (tolerance {tolerance:g})"
            + (", determinant +1 or -1" if allow_mirror else ", determinant +1"),
        )
    if not allow_mirror and np.linalg.det(rotation) < 0:
        raise DsaregInputError(
            "3x3 part is a reflection (determinant -1)", field=field, accepted="a proper rotation (determinant +1)"
        )
    return array


def rotation_error_deg(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Geodesic angle (degrees) of ``R_a R_bᵀ``."""
    relative = np.asarray(rotation_a) @ np.asarray(rotation_b).T
    cos_angle = np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos_angle)))

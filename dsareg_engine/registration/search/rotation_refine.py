"""Rotation candidates after a grid search: local hill-climb, distinct picks, poses.

Shared by the pose searches (:mod:`.initialization`, :mod:`.coverage_search`, :mod:`.branch_search`).
A score function takes rotations ``(B, 3, 3)`` and returns scores ``(B,)`` (0 best) and the
positions ``(B, 3)`` (world mm) it placed them at.
"""

from __future__ import annotations

import numpy as np

from .rotation_grid import angles_between_deg, axis_angle_matrices


def local_moves(step_deg: float) -> np.ndarray:
    """``(13, 3, 3)``: the identity and ±``step_deg`` about the axes and about 3 diagonals."""
    axes = np.concatenate([np.eye(3), np.array([[1, 1, 1], [1, -1, 1], [1, 1, -1]]) / np.sqrt(3.0)])
    vectors = np.radians(step_deg) * np.concatenate([axes, -axes])
    return np.concatenate([np.eye(3)[None], axis_angle_matrices(vectors)])


def hill_climb(score, rotations: np.ndarray, steps_deg) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Refine rotations ``(M, 3, 3)`` by rounds of local moves, one round per step of ``steps_deg``;
    returns rotations, scores, positions and the count scored."""
    scored = 0
    scores = centres = None
    for step in steps_deg:
        moves = local_moves(step)  # world-frame turns applied on the left
        trial = np.einsum("kij,mjl->mkil", moves, rotations).reshape(-1, 3, 3)
        trial_scores, trial_centres = score(trial)
        scored += len(trial)
        pick = np.arange(len(rotations)) * len(moves) + trial_scores.reshape(len(rotations), len(moves)).argmin(axis=1)
        rotations, scores, centres = trial[pick], trial_scores[pick], trial_centres[pick]
    return rotations, scores, centres, scored


def distinct(rotations: np.ndarray, scores: np.ndarray, count: int, min_deg: float) -> list[int]:
    """Indices of the best ``count`` candidates at least ``min_deg`` apart in rotation."""
    chosen: list[int] = []
    for index in np.argsort(scores, kind="stable"):
        if all(angles_between_deg(rotations[[index]], rotations[other])[0] >= min_deg for other in chosen):
            chosen.append(int(index))
            if len(chosen) == count:
                break
    return chosen


def poses_from(rotations: np.ndarray, centres: np.ndarray, mesh_centroid: np.ndarray) -> np.ndarray:
    """``(K, 4, 4)`` mesh_to_world placing the mesh centroid at ``centres`` ``(K, 3)`` turned by ``rotations``."""
    poses = np.tile(np.eye(4), (len(rotations), 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = centres - rotations @ mesh_centroid
    return poses

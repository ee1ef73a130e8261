"""Tracking (re-registration): follow a small motion from the previous pose with a short schedule.

During an intervention the patient moves by a few millimetres and degrees between biplane
pairs. Starting from the previous result there is no capture range to buy: one start, no
coarse pyramid, one short blurred stage at a moderate resolution (it absorbs a motion of up to
~15 px at full size, which sharp full-size silhouettes of thin vessels would not), then the
sharp fit at full size in float32 (table-interpolated transcendentals; the same ADD to 4
decimals as float64). Both stages are Levenberg–Marquardt on the six pose increments
(:mod:`.gauss_newton`, per-pixel Jacobians from the numba kernel): 4–7 iterations at ~200 px and
3 at 800 px on the paper's mesh, where Adam took 13–20 and L-BFGS 10–17 evaluations. Where that
kernel is missing (CUDA, no numba) the stages are blurred Adam and L-BFGS as before.
``options.mode = "track"`` selects it.
"""
from __future__ import annotations

import numpy as np

from ..geometry.pose import so3_log
from .schedule import ADAM_SIGMA_PX, FINAL_SIGMA_PX, Stage

TRACK_SIDE_PX = 200
"""Side of the blurred stage's image (the pyramid level nearest to it): ~4 px of motion per 15 px at 800."""
TRACK_PLATEAU_TOLERANCE = 1e-2
"""Without the Jacobian kernel the blurred stage is Adam, which only has to bring the pose into L-BFGS's
basin: it stops at a 1 % plateau."""
TRACK_COARSE_POSE_TOLERANCE = 0.03
"""Gauss–Newton stop (mm) of the ~200-px stage: it only hands a pose to the full-size fit, whose first steps
move it by ~0.05 mm anyway (the coarse optimum's offset); 0.03 instead of 0.01 saved 1–2 of its 5–8 iterations
and cost the full-size stage nothing (4–5 iterations either way)."""
TRACK_REFINE_EVALUATIONS = 40
TRACK_POSE_TOLERANCE = 1e-3
"""Stop of the full-size fit on pose change (mm) when tracking: 10× the full registration's. Measured on
the paper's mesh with L-BFGS: 10–17 instead of 13–29 evaluations, ADD unchanged (0.0016–0.0038 mm); the
full registration keeps 1e-4 (at 1e-3 its median rotation error rose from 0.0007° to 0.0008°)."""


def track_scale(image_side_px: int) -> float:
    """Power-of-two reduction bringing the image side nearest to TRACK_SIDE_PX (≤ 1)."""
    scale = 1.0
    while image_side_px * scale / 2 >= TRACK_SIDE_PX * 0.75:
        scale /= 2
    return scale


def build_track_schedule(views: tuple[str, ...], image_side_px: int, max_iterations: int, jacobian: bool = True) -> list[Stage]:
    """Stages of a re-registration from the previous pose: blurred at ~200 px (at full size on smaller
    images), then sharp at full size; Levenberg–Marquardt with the Jacobian kernel (``jacobian``), else
    Adam then L-BFGS (no blurred stage on small images: L-BFGS's line search covers the distance)."""
    label = "+".join(views)
    scale = track_scale(image_side_px)
    stages = []
    # Under the 1-px blur the edge softness hardly matters; the Jacobian kernel's cost grows with σ
    # (more face–pixel pairs), Adam's schedule was tuned at 0.5.
    coarse_sigma_px = ADAM_SIGMA_PX if jacobian else 0.5
    # Gauss–Newton steps on sharp silhouettes are about σ long: small images (no smaller level) get the
    # blurred stage at full size. L-BFGS's line search covers that distance by itself.
    if scale < 1.0 or jacobian:
        stages.append(Stage(
            name=f"track:{label}:1/{round(1 / scale)}", scale=scale, sigma_px=coarse_sigma_px, blur_px=1.0, views=views,
            optimizer="gauss_newton" if jacobian else "adam", max_iterations=min(max_iterations, 60), learning_rate=0.2,
            all_starts=True, plateau_tolerance=TRACK_PLATEAU_TOLERANCE, pose_tolerance=TRACK_COARSE_POSE_TOLERANCE,
            float64=False, level_of_detail=True,
        ))
    stages.append(Stage(
        name=f"track:{label}:1/1:refine", scale=1.0, sigma_px=FINAL_SIGMA_PX, blur_px=0.0, views=views,
        optimizer="gauss_newton" if jacobian else "lbfgs", max_iterations=min(max_iterations, TRACK_REFINE_EVALUATIONS),
        learning_rate=0.05, all_starts=True, float64=False, pose_tolerance=TRACK_POSE_TOLERANCE, level_of_detail=False,
    ))
    return stages


def motion_between(previous: np.ndarray, current: np.ndarray, points: np.ndarray) -> dict:
    """How far the model moved from ``previous`` to ``current`` (both mesh_to_world 4x4).

    Returns ``rotation_deg`` (angle of the relative rotation), ``rotation_vector_deg`` (its axis times that angle,
    world frame), ``translation_mm`` and ``translation_vector_mm`` (displacement of the points' centroid, world
    mm), ``mean_displacement_mm`` (mean point displacement) and ``world_motion`` (4x4 ``current · previous⁻¹``,
    world frame).
    """
    previous = np.asarray(previous, dtype=np.float64)
    current = np.asarray(current, dtype=np.float64)
    relative = current @ np.linalg.inv(previous)
    centre = points.mean(axis=0)
    before = previous[:3, :3] @ centre + previous[:3, 3]
    after = current[:3, :3] @ centre + current[:3, 3]
    moved = (points @ current[:3, :3].T + current[:3, 3]) - (points @ previous[:3, :3].T + previous[:3, 3])
    rotation = np.degrees(so3_log(relative[:3, :3]))
    return {
        "rotation_deg": float(np.linalg.norm(rotation)),
        "rotation_vector_deg": rotation.tolist(),
        "translation_mm": float(np.linalg.norm(after - before)),
        "translation_vector_mm": (after - before).tolist(),
        "mean_displacement_mm": float(np.linalg.norm(moved, axis=1).mean()),
        "world_motion": relative.tolist(),
    }


def held_depth(refined: np.ndarray, joint: np.ndarray, world_to_view: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``refined`` (mesh_to_world 4x4) slid along the source ray through the model's ``centre`` (mesh mm) until that
    centre lies at ``joint``'s depth in the view (``world_to_view``): its projection stays where it was."""
    def in_view(pose: np.ndarray) -> np.ndarray:
        transform = world_to_view @ pose
        return transform[:3, :3] @ centre + transform[:3, 3]

    seen, wanted = in_view(refined), in_view(joint)
    shift_view = seen * (wanted[2] / seen[2] - 1.0)
    out = np.array(refined, dtype=np.float64)
    out[:3, 3] += np.linalg.solve(world_to_view[:3, :3], shift_view)
    return out

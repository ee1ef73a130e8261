"""Runs not acquired together: a pose per run, the motion between them, and an honest verdict.

On a monoplane C-arm the AP and LAT runs are two injections minutes apart (:mod:`dsareg_engine.io.view_roles`
tells from their headers), and the head moves between them. The joint registration then fits one pose to two
different poses. After it, each run's pose is refined from the joint pose on its own view alone (the tracking
schedule, :mod:`.track`), regularised toward no motion where one view cannot see: one view does not measure the
model's depth along its beam, so the refined pose is slid back along the source ray through the model's centre
to the joint pose's depth (the projection of that centre is unchanged). What remains is the motion the images
show (rotation and displacement across each beam).

The motion along each view's beam between the runs is not measured by anything: the AP run's depth is seen only by
the LAT view, which is of the other run. A sequential pair's verdict is therefore never ``ok``: ``check``, with a
reason naming the runs' times, the motion measured and the motion that cannot be excluded.
"""

from __future__ import annotations

import time

import numpy as np

from ..geometry.rig import Rig
from ..mesh import TriangleMesh
from ..metrics import dice
from .options import RegistrationOptions
from .result import RegistrationResult
from .track import held_depth, motion_between


def run_poses(mesh: TriangleMesh, targets: dict[str, np.ndarray], rig: Rig, joint: np.ndarray,
              device: str = "auto") -> dict[str, np.ndarray]:
    """Per view, the pose of its run: refined from ``joint`` on that view alone, its depth held at ``joint``'s."""
    from .solver import register

    centre = np.asarray(mesh.vertices, dtype=np.float64).mean(axis=0)
    poses = {}
    for name in targets:
        options = RegistrationOptions(configuration=name, mode="track", initialization="given", starts=1,
                                      initial_mesh_to_world=np.asarray(joint).tolist(), mirror_check=False,
                                      device=device)
        refined = register(mesh, targets, rig, options).mesh_to_world
        poses[name] = held_depth(refined, joint, rig.views[name].world_to_view, centre)
    return poses


def _run_dice(mesh: TriangleMesh, targets: dict[str, np.ndarray], rig: Rig, poses: dict[str, np.ndarray]) -> dict:
    import torch

    from ..render import Camera, render_hard_silhouette

    vertices, faces = mesh.torch(torch.float64)
    out = {}
    for name, pose in poses.items():
        view = rig.views[name]
        silhouette = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                           Camera.from_view(view))[0].numpy().astype(bool)
        out[name] = round(dice(silhouette, np.asarray(targets[name]) >= 0.5), 4)
    return out


def sequential_runs(mesh: TriangleMesh, targets: dict[str, np.ndarray], rig: Rig, result: RegistrationResult,
                    acquisition: dict, device: str = "auto") -> dict:
    """The ``acquisition`` record (``{"sequential", "basis", "interval_s"}``) completed for sequential runs: each
    run's pose (``run_poses``), its Dice there (``run_dice``), the ``motion`` between them (LAT run from the AP run,
    :func:`.track.motion_between`) and ``seconds``; the result's verdict is lowered to ``check`` with the reason."""
    started = time.perf_counter()
    poses = run_poses(mesh, targets, rig, result.mesh_to_world, device)
    motion = motion_between(poses["ap"], poses["lat"], np.asarray(mesh.vertices, dtype=np.float64))
    record = {**acquisition, "run_poses": {name: pose.tolist() for name, pose in poses.items()},
              "run_dice": _run_dice(mesh, targets, rig, poses), "motion": motion,
              "seconds": round(time.perf_counter() - started, 3)}
    reason = (f"sequential runs: {acquisition['basis']}; the head may have moved between them. Fitted alone, the "
              f"runs differ by {motion['rotation_deg']:.1f}° and {motion['translation_mm']:.1f} mm across the beams "
              "(acquisition.run_poses), and motion along each view's beam cannot be measured from one view: "
              "the pose can be off by that motion for one of the runs")
    confidence = result.metrics.get("confidence")
    if isinstance(confidence, dict):
        confidence["reasons"] = list(confidence.get("reasons") or []) + [reason]
        if confidence.get("verdict") == "ok":
            confidence["verdict"] = "check"
    return record

"""``python -m benchmarks.engine track``: tracking over a procedure, a later run of either plane or of both.

Sequences of small motions (each ``--rotation`` degrees about a random axis through the mesh centre and
``--translation`` mm in a random direction), masks rendered at each moved pose; each frame re-registered with
``mode: "track"`` from the previous frame's estimate (the first from the true first pose, which is the reference:
``options.reference_mesh_to_world``), so errors accumulate if a frame goes wrong. ``--planes`` runs the same
sequences once per choice: ``both`` (a biplane run each frame), ``ap`` / ``lat`` (that plane alone every frame),
``alternate`` (AP, LAT, AP, ...: a monoplane C-arm turned between runs). Per frame: wall and CPU time, ADD of the
tracked pose, the error of the reported motion since the first pose (``metrics.tracking.since_reference``: its
translation vector against the true centroid displacement, its rotation against the true one) and, for one plane,
the centre's error across and along that plane's beam (one view sees the depth through perspective alone).
``--grey``: the images are synthetic grey-level DSA segmented as the service does (``dsa`` coverage) instead of true
masks; ``--model-scale S``: they show the model scaled by ``S`` about its centre (a 3D model of the wrong size), the
registration fits the model as given (ADD and motion errors against the true pose of the model as given).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from dsareg_engine.commands.render import load_mesh_argument
from dsareg_engine.geometry.pose import rotation_error_deg
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.track import motion_between
from dsareg_engine.render import Camera, render_hard_silhouette

from .phantom import _options, _perturbation

PLANES = {"both": lambda frame: "simultaneous", "ap": lambda frame: "ap", "lat": lambda frame: "lat",
          "alternate": lambda frame: ("ap", "lat")[frame % 2]}
"""``--planes`` choice → the configuration of frame ``frame`` (0-based)."""


def _masks(mesh, rig: Rig, pose: np.ndarray) -> dict[str, np.ndarray]:
    vertices, faces = mesh.torch(torch.float64)
    return {name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                         Camera.from_view(view))[0].numpy() for name, view in rig.views.items()}


def _images(mesh, args: argparse.Namespace):
    """``images(rig, pose)``: true masks or (``--grey``) segmented grey-level DSA of the model as seen (``--model-scale``)."""
    from dsareg_engine.mesh import TriangleMesh

    from .phantom import _grey_masks

    seen = TriangleMesh((mesh.vertices - mesh.centroid) * args.model_scale + mesh.centroid, mesh.faces)
    if args.grey:
        return lambda rig, pose: _grey_masks(seen, rig, "dsa", args.seed, truth=pose)
    return lambda rig, pose: _masks(seen, rig, pose)


def _motions(mesh, args: argparse.Namespace) -> list[list[np.ndarray]]:
    """Per sequence, the true pose of each frame (the reference, the identity, is the sequence's first pose)."""
    rng = np.random.default_rng(args.seed)
    sequences = []
    for _ in range(args.sequences):
        truth, poses = np.eye(4), []
        for _ in range(args.frames):
            truth = _perturbation(mesh, truth, np.radians(rng.uniform(*args.rotation)), rng.uniform(*args.translation), rng)
            poses.append(truth)
        sequences.append(poses)
    return sequences


def _frame(mesh, rig: Rig, masks, estimate: np.ndarray, truth: np.ndarray, configuration: str, extra: dict) -> dict:
    """One tracked frame: its times, its pose's errors and its motion's error since the first pose (the identity)."""
    options = RegistrationOptions(configuration=configuration, **extra, initial_mesh_to_world=estimate.tolist(),
                                  reference_mesh_to_world=np.eye(4).tolist(), ground_truth_mesh_to_world=truth.tolist())
    started, cpu = time.perf_counter(), time.process_time()
    result = register(mesh, masks, rig, options)
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    metrics = result.metrics
    tracking = metrics["tracking"]
    reported = tracking["since_reference"]
    true = motion_between(np.eye(4), truth, mesh.vertices)
    centre = mesh.vertices.mean(axis=0)
    error = result.mesh_to_world[:3, :3] @ centre + result.mesh_to_world[:3, 3] - (truth[:3, :3] @ centre + truth[:3, 3])
    row = {"pose": result.mesh_to_world, "wall": wall * 1e3, "cpu": cpu * 1e3, "add": metrics["ground_truth"]["add_mm"],
           "verdict": metrics["confidence"]["verdict"], "converged": metrics["converged"],
           "motion_mm_error": float(np.linalg.norm(np.subtract(reported["translation_vector_mm"],
                                                               true["translation_vector_mm"]))),
           "motion_deg_error": rotation_error_deg(result.mesh_to_world[:3, :3], truth[:3, :3]),
           "motion_mm": reported["translation_mm"], "motion_deg": reported["rotation_deg"]}
    if tracking["unmeasured_direction_world"] is not None:
        beam = np.asarray(tracking["unmeasured_direction_world"])
        row["along"] = abs(float(error @ beam))
        row["across"] = float(np.linalg.norm(error - (error @ beam) * beam))
    return row


def _stat(rows: list[dict], key: str, *qs: float) -> str:
    values = [row[key] for row in rows if key in row]
    if not values:
        return "-"
    return " / ".join(f"{np.percentile(values, q):.4f}" if q < 100 else f"{max(values):.4f}" for q in qs)


def _row(planes: str, rows: list[dict]) -> str:
    wall = [row["wall"] for row in rows]
    verdicts = ", ".join(f"{v} {sum(row['verdict'] == v for row in rows)}" for v in ("ok", "check", "failed")
                         if any(row["verdict"] == v for row in rows))
    return (f"| {planes} | {len(rows)} | {np.median(wall):.0f} / {np.percentile(wall, 90):.0f} | "
            f"{np.median([row['cpu'] for row in rows]):.0f} | {_stat(rows, 'add', 50, 90, 100)} | "
            f"{_stat(rows, 'motion_mm_error', 50, 90)} | {_stat(rows, 'motion_deg_error', 50, 90)} | "
            f"{_stat(rows, 'across', 50, 100)} | {_stat(rows, 'along', 50, 100)} | {verdicts} |")


def bench_track(args: argparse.Namespace) -> int:
    """Each ``--planes`` choice over the same sequences of small motions, each frame tracked from the previous one."""
    mesh = load_mesh_argument(args.mesh)
    paper = load_rig("paper")
    rig = Rig({name: view.resized(args.size, args.size) for name, view in paper.views.items()}, np.eye(4))
    extra = {"mode": "track", **_options(args)}
    sequences = _motions(mesh, args)
    images = _images(mesh, args)
    print(f"mesh {mesh.n_faces} faces, {args.size}x{args.size} px, {'grey-level DSA' if args.grey else 'true masks'} "
          f"of the model scaled by {args.model_scale:g}, {args.sequences} sequences x {args.frames} motions of "
          f"{args.rotation[0]:g}-{args.rotation[1]:g} deg and {args.translation[0]:g}-{args.translation[1]:g} mm, "
          f"each tracked from the previous estimate (the first from the true first pose, the reference), planes "
          f"{' '.join(args.planes)}, options {extra}", flush=True)
    masks = _masks(mesh, rig, np.eye(4))
    for configuration in ("simultaneous", "ap", "lat"):  # warm-up (kernels, level of detail): not counted
        register(mesh, masks, rig, RegistrationOptions(configuration=configuration, **extra,
                                                      initial_mesh_to_world=np.eye(4).tolist()))
    table = []
    for planes in args.planes:
        rows = []
        for sequence, poses in enumerate(sequences):
            estimate = np.eye(4)
            for frame, truth in enumerate(poses):
                rows.append(_frame(mesh, rig, images(rig, truth), estimate, truth, PLANES[planes](frame), extra))
                estimate = rows[-1]["pose"]
                print(f"{planes} sequence {sequence} frame {frame}: ADD {rows[-1]['add']:.4f} mm, motion since the "
                      f"first pose {rows[-1]['motion_deg']:.2f} deg / {rows[-1]['motion_mm']:.2f} mm (error "
                      f"{rows[-1]['motion_deg_error']:.3f} deg / {rows[-1]['motion_mm_error']:.3f} mm), "
                      f"{rows[-1]['wall']:.0f} ms (CPU {rows[-1]['cpu']:.0f}), {rows[-1]['verdict']}", flush=True)
        depth = f", depth {extra.get('single_plane_depth', 'fit')}" if planes != "both" else ""
        seen = (", grey DSA" if args.grey else "") + (f", model x{args.model_scale:g}" if args.model_scale != 1 else "")
        table.append(_row(f"{planes}{depth}{seen}", rows))
    print("\n| planes | frames | ms per frame median / p90 | CPU ms median | ADD mm median / p90 / max | motion since "
          "the first pose: translation error mm median / p90 | rotation error ° median / p90 | one plane: centre error "
          "across its beam mm median / max | along its beam mm median / max | verdicts |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(table))
    return 0

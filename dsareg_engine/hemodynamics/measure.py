"""Measure both runs on the registered model: vessel points → curves per view → parameters → combined values.

:func:`measure` is the whole measurement on loaded data (frame stacks with their times, the mesh, the pose, the
rig); :mod:`.run` reads the files and writes the outputs around it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry.rig import Rig, ViewGeometry
from ..mesh import TriangleMesh
from ..render.ray_layers import layer_counts
from .combine import ViewMeasure, combine
from .model_points import VesselPoints, vessel_points
from .overlap import overlapped
from .parameters import curve_parameters, footprint_noise
from .sampling import Projection, curves, footprints, mean_chord_mm, project_points
from .timing import RunTiming

VIEWS = ("ap", "lat")


@dataclass(frozen=True)
class RunFrames:
    """One view's run ready to measure: ``opacity`` ``(T, H, W)`` float32 (the subtracted frames, higher = more
    contrast, 0 = no change), its ``timing``, and ``notes`` on how the frames were made."""

    opacity: np.ndarray
    timing: RunTiming
    notes: tuple[str, ...] = ()


@dataclass
class Measurement:
    """Per working-mesh vertex arrays (:func:`.combine.combine`), the points, and per view notes / counts."""

    values: dict[str, np.ndarray]
    points: VesselPoints
    views: dict[str, dict] = field(default_factory=dict)


def model_layers(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(layers (H, W), covered (H, W) bool)``: the separate parts of the model each ray crosses, at the pose."""
    mesh_to_view = view.world_to_view @ np.asarray(mesh_to_world, float)
    vertices = mesh.vertices @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    return layer_counts(vertices, mesh.faces, view.focal_px, view.principal_point_px, view.image_size)


def on_model(projection: Projection, covered: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the point's centre projects onto the model's silhouette (a centre estimate that left its
    vessel, e.g. where the local diameter was not found, is not measured in this view)."""
    height, width = covered.shape
    column = np.clip(np.round(projection.uv_px[:, 0]).astype(int), 0, width - 1)
    row = np.clip(np.round(projection.uv_px[:, 1]).astype(int), 0, height - 1)
    return projection.inside & covered[row, column]


def measure_view(points: VesselPoints, view: ViewGeometry, mesh_to_world: np.ndarray, run: RunFrames,
                 layers: tuple[np.ndarray, np.ndarray], times_s: np.ndarray) -> tuple[ViewMeasure, dict]:
    """One view: ``(its measure, its counts)``; ``layers`` from :func:`model_layers`, ``times_s`` on the common
    clock."""
    crossings, covered = layers
    projection = project_points(points.centres_mm, points.radii_mm, view, mesh_to_world)
    prints = footprints(projection, covered)
    stack = run.opacity.astype(np.float32, copy=False)
    background = ~cv2.dilate(covered.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    ring_radius = np.sqrt(np.maximum(prints.ring_pixels, 1) / np.pi)
    own = footprint_noise(stack, background, np.stack([projection.footprint_px, ring_radius]).ravel())
    noise = np.hypot(own[: len(points)], np.where(prints.ring_pixels > 0, own[len(points):], 0.0))
    measurable = projection.inside & (prints.footprint_pixels > 0) & on_model(projection, covered)
    chord = mean_chord_mm(projection, points.radii_mm)
    parameters = curve_parameters(curves(stack, prints), times_s, noise, chord, measurable)
    flags = overlapped(prints, crossings) & measurable
    counts = {"points": len(points), "inside": int(measurable.sum()), "overlapped": int(flags.sum()),
              "filled": int((parameters.filled & measurable).sum()),
              "median_footprint_px": round(float(np.median(projection.footprint_px[measurable])), 3)
              if measurable.any() else None}
    return ViewMeasure(parameters, measurable, flags), counts


def measure(mesh: TriangleMesh, mesh_to_world: np.ndarray, rig: Rig, runs: dict[str, RunFrames],
            offset_s: float = 0.0, points: VesselPoints | None = None) -> Measurement:
    """Both views of ``runs`` measured on ``mesh`` at ``mesh_to_world``; the LAT run started ``offset_s`` after the
    AP run (its times are moved onto the AP clock)."""
    points = points if points is not None else vessel_points(mesh)
    measures, notes = {}, {}
    for name in VIEWS:
        view, run = rig.views[name], runs[name]
        if run.opacity.shape[1:] != (view.height, view.width):
            raise ValueError(f"{name}: frames {run.opacity.shape[1:]} do not match the view {view.image_size}")
        times = run.timing.times_s + (offset_s if name == "lat" else 0.0)
        measures[name], notes[name] = measure_view(points, view, mesh_to_world, run,
                                                   model_layers(mesh, view, mesh_to_world), times)
    return Measurement(combine(measures["ap"], measures["lat"]), points, notes)

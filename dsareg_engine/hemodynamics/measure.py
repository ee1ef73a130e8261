"""Measure both runs on the registered model: vessel points → curves per view → parameters → combined values.

:func:`measure` is the whole measurement on loaded data (frame stacks with their times, the mesh, the pose, the
rig); :mod:`.run` reads the files and writes the outputs around it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..geometry.rig import Rig, ViewGeometry
from ..mesh import TriangleMesh
from ..kernels.compile_lock import wait_for_group
from ..render.ray_layers import RayStretches, ray_stretches
from .combine import ViewMeasure, combine
from .model_points import VesselPoints, vessel_points
from .overlap import OVERLAP_SHARE, foreign_share, overlapped, own_path_mm
from .parameters import baseline_frames, curve_parameters, lift, mean_noise
from .sampling import Projection, curves, footprints, mean_chord_mm, project_points
from .timing import RunTiming
from .unmixing import (ViewMixing, empty_around, known_concentration, measured_within_run, not_filled, on_clock,
                        stretch_owners, unique_edges, unmix_view, view_scale)

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


def model_stretches(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray) -> RayStretches:
    """The separate parts of the model each ray of ``view`` crosses, at the pose."""
    wait_for_group("hemodynamics")  # a worker's background helper may be compiling the kernels
    mesh_to_view = view.world_to_view @ np.asarray(mesh_to_world, float)
    vertices = mesh.vertices @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    return ray_stretches(vertices, mesh.faces, view.focal_px, view.principal_point_px, view.image_size)


def on_model(projection: Projection, covered: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the point's centre projects onto the model's silhouette (a centre estimate that left its
    vessel, e.g. where the local diameter was not found, is not measured in this view)."""
    height, width = covered.shape
    column = np.clip(np.round(projection.uv_px[:, 0]).astype(int), 0, width - 1)
    row = np.clip(np.round(projection.uv_px[:, 1]).astype(int), 0, height - 1)
    return projection.inside & covered[row, column]


def measure_view(points: VesselPoints, view: ViewGeometry, mesh_to_world: np.ndarray, run: RunFrames,
                 stretches: RayStretches, centres: cKDTree, times_s: np.ndarray
                 ) -> tuple[ViewMeasure, dict, ViewMixing]:
    """One view: ``(its measure, its counts, its mixing)``; ``stretches`` from :func:`model_stretches`,
    ``centres`` a tree of the points' centres, ``times_s`` on the common clock."""
    covered = stretches.covered
    projection = project_points(points.centres_mm, points.radii_mm, view, mesh_to_world)
    prints = footprints(projection, covered)
    stack = run.opacity.astype(np.float32, copy=False)
    background = ~cv2.dilate(covered.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    own = mean_noise(stack, background, np.concatenate([prints.footprint_pixels, prints.ring_pixels]))
    noise = np.hypot(own[: len(points)], np.where(prints.ring_pixels > 0, own[len(points):], 0.0))
    measurable = projection.inside & (prints.footprint_pixels > 0) & on_model(projection, covered)
    chord = mean_chord_mm(projection, points.radii_mm)
    sampled = curves(stack, prints)
    parameters = curve_parameters(sampled, times_s, noise, chord, measurable, gamma_fit=True)
    mixing = (prints.footprint @ stretch_owners(stretches, view, mesh_to_world, centres, len(points))).tocsr()
    own_mm = own_path_mm(mixing, points.centres_mm, points.radii_mm)
    beside = foreign_share(mixing, own_mm) >= OVERLAP_SHARE
    flags = (overlapped(prints, stretches.layers) | beside) & measurable
    counts = {"points": len(points), "inside": int(measurable.sum()), "overlapped": int(flags.sum()),
              "filled": int((parameters.filled & measurable).sum()),
              "median_footprint_px": round(float(np.median(projection.footprint_px[measurable])), 3)
              if measurable.any() else None}
    return (ViewMeasure(parameters, measurable, flags), counts,
            ViewMixing(lift(sampled, measurable), noise, mixing, np.asarray(times_s, float), own_mm))


def measure(mesh: TriangleMesh, mesh_to_world: np.ndarray, rig: Rig, runs: dict[str, RunFrames],
            offset_s: float = 0.0, points: VesselPoints | None = None) -> Measurement:
    """Both views of ``runs`` measured on ``mesh`` at ``mesh_to_world``; the LAT run started ``offset_s`` after the
    AP run (its times are moved onto the AP clock). Points no view sees clean are unmixed (:mod:`.unmixing`)."""
    points = points if points is not None else vessel_points(mesh)
    centres = cKDTree(points.centres_mm)
    measures, notes, mixes = {}, {}, {}
    for name in VIEWS:
        view, run = rig.views[name], runs[name]
        if run.opacity.shape[1:] != (view.height, view.width):
            raise ValueError(f"{name}: frames {run.opacity.shape[1:]} do not match the view {view.image_size}")
        times = run.timing.times_s + (offset_s if name == "lat" else 0.0)
        measures[name], notes[name], mixes[name] = measure_view(
            points, view, mesh_to_world, run, model_stretches(mesh, view, mesh_to_world), centres, times)
    measures = unmix(measures, mixes, mesh.faces, notes)
    return Measurement(combine(measures["ap"], measures["lat"]), points, notes)


def plausible(measure_: ViewMeasure, mix: ViewMixing, scale: float) -> ViewMeasure:
    """``measure_`` with its measured curves that cannot be the point's own bolus not filled
    (:func:`.unmixing.measured_within_run`)."""
    run_arrival = mix.times_s[baseline_frames(mix.curves[measure_.measurable])] if measure_.measurable.any() else -np.inf
    found = measured_within_run(measure_.parameters, mix.times_s, run_arrival, mix.own_mm, scale)
    return replace(measure_, parameters=found)


def unmix(measures: dict[str, ViewMeasure], mixes: dict[str, ViewMixing], faces: np.ndarray, notes: dict
          ) -> dict[str, ViewMeasure]:
    """Each view's measure with the points no view sees clean unmixed (:mod:`.unmixing`); ``notes[view]["unmixed"]``
    counts them and ``notes[view]["unmixed_filled"]`` those that showed contrast."""
    clean = {name: m.clean for name, m in measures.items()}
    carried = clean["ap"] | clean["lat"]
    scales = {name: view_scale(m.parameters.peak_opacity, mixes[name].path_mm, m.clean & m.parameters.filled)
              for name, m in measures.items()}
    measures = {name: plausible(m, mixes[name], scales[name]) for name, m in measures.items()}
    own = {name: known_concentration(mixes[name], clean[name], scales[name]) for name in VIEWS}
    edges = unique_edges(faces)
    known_empty = (clean["ap"] & ~measures["ap"].parameters.filled) | (clean["lat"] & ~measures["lat"].parameters.filled)
    contradicted = empty_around(edges, known_empty, carried)
    out = {}
    for name, other in zip(VIEWS, VIEWS[::-1]):
        measure_, mix = measures[name], mixes[name]
        rows = np.flatnonzero(measure_.measurable & ~carried)
        if not len(rows) or scales[name] <= 0:
            out[name] = measure_
            notes[name].update(unmixed=0, unmixed_filled=0)
            continue
        moved = on_clock(own[other], mixes[other].times_s, mix.times_s)
        q_known = np.where(clean[name][:, None], own[name], moved)
        found = unmix_view(mix, rows, carried, q_known, scales[name], edges)
        found = not_filled(found, contradicted[rows])
        out[name] = measure_.with_unmixed(rows, found)
        notes[name].update(unmixed=len(rows), unmixed_filled=int(found.filled.sum()))
    return out

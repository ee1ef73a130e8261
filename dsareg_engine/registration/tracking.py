"""Tracking over a procedure: the motion since the procedure's first pose and since the previous run, and what one
plane alone cannot measure.

The procedure's first registration fixes the reference pose; each later run, of either plane alone or of both, is
re-registered from the previous pose (``options.mode = "track"``, the schedule of :mod:`.track`), the reference
carried along in ``options.reference_mesh_to_world`` (the service's ``POST …/track`` sets it from the job it tracks
from). ``metrics.tracking`` reports the motion since the reference and since the previous pose
(:func:`.track.motion_between`: the rotation and the displacement of the model's centroid, both in the world frame:
the geometry's, for DICOM XA patient LPS axes with the origin at the isocentre).

One plane sees the model's depth along its beam only through perspective: a displacement along the beam scales
the silhouette (by less than a percent per few millimetres) and shifts its near parts against its far ones. On
synthetic images of an exact model the fit finds it within 0.1 mm (800 px, the paper's rig), but a model 1 % too
large moved it by 1.4-1.6 mm (docs/benchmarks/tracking.md): depth and the model's scale are one ambiguity there.
So a single-plane result says the motion along the beam is not measured (``along_beam_measured: false``, the beam's
direction and the fit's own motion along it, ``along_beam_mm``) and its verdict is never ``ok``: ``check``, with
the reason. ``options.single_plane_depth = "previous"`` holds the depth instead, as for monoplane runs
(:mod:`.motion`): the pose slid back along the source ray through the model's centre to the previous pose's depth
(:func:`.track.held_depth`: the silhouette stays where it was), no motion along the beam assumed.
"""

from __future__ import annotations

import numpy as np

from ..geometry.pose import validate_rigid
from ..geometry.rig import Rig
from .track import held_depth, motion_between


def beam_direction(world_to_view: np.ndarray, pose: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit vector (world frame) from the view's X-ray source through the model's ``centre`` (mesh mm) at ``pose``."""
    source = np.linalg.inv(np.asarray(world_to_view, dtype=np.float64))[:3, 3]
    at = pose[:3, :3] @ centre + pose[:3, 3]
    direction = at - source
    return direction / np.linalg.norm(direction)


def hold_unmeasured_depth(estimate: np.ndarray, previous: np.ndarray, rig: Rig, used_views: tuple[str, ...],
                          centre: np.ndarray) -> tuple[np.ndarray, float | None]:
    """A single-view fit's pose at ``previous``'s depth along that view's beam, and how far it moved (mm); two views
    measure the depth: ``(estimate, None)``."""
    if len(used_views) != 1:
        return estimate, None
    held = held_depth(estimate, previous, rig.views[used_views[0]].world_to_view, centre)
    return held, float(np.linalg.norm(held[:3, 3] - np.asarray(estimate)[:3, 3]))


def tracking_record(previous: np.ndarray, estimate: np.ndarray, reference: np.ndarray | None, points: np.ndarray,
                    rig: Rig, used_views: tuple[str, ...], depth_held_mm: float | None) -> dict:
    """``metrics.tracking``: the planes fitted, the motion since the reference (``reference`` None: the previous pose
    is the reference, this is the procedure's first tracked run) and since the previous pose, and what was not
    measured (one plane: the motion along its beam, its direction in the world frame)."""
    reference_pose = np.asarray(previous if reference is None else reference, dtype=np.float64)
    single = len(used_views) == 1
    centre = np.asarray(points, dtype=np.float64).mean(axis=0)
    direction = beam_direction(rig.views[used_views[0]].world_to_view, estimate, centre) if single else None
    since_previous = motion_between(previous, estimate, points)
    return {
        "views": list(used_views),
        "frame": "world",
        "reference_mesh_to_world": reference_pose.tolist(),
        "reference_given": reference is not None,
        "since_reference": motion_between(reference_pose, estimate, points),
        "since_previous": since_previous,
        "along_beam_measured": not single,
        "unmeasured_view": used_views[0] if single else None,
        "unmeasured_direction_world": direction.tolist() if direction is not None else None,
        "along_beam_mm": None if direction is None else
        round(float(np.dot(since_previous["translation_vector_mm"], direction)), 4),
        "depth": None if not single else "fit" if depth_held_mm is None else "previous",
        "depth_held_mm": None if depth_held_mm is None else round(depth_held_mm, 4),
    }


def single_plane_reason(record: dict) -> str | None:
    """The verdict's reason for a single-plane track (None with both planes)."""
    if record["along_beam_measured"]:
        return None
    view = str(record["unmeasured_view"]).upper()
    direction = ", ".join(f"{value:.2f}" for value in record["unmeasured_direction_world"])
    if record["depth"] == "previous":
        how = ("the pose keeps the previous pose's depth along it (options.single_plane_depth previous), so it is off "
               "by whatever the head moved that way since the previous run")
    else:
        how = (f"the fit moved the model {record['along_beam_mm']:+.2f} mm along it from perspective alone, which an "
               "error in the model's scale shifts (1 % by about 1.5 mm)")
    return (f"single-plane track ({view} only): motion along the {view} beam (world direction [{direction}]) is not "
            f"measured by one view (metrics.tracking.along_beam_measured false): {how}. Track with both planes to "
            "measure it")


def lower_verdict(confidence: dict | None, reason: str | None) -> None:
    """``ok`` becomes ``check`` with ``reason`` (a component that matters was not measured); ``failed`` stays."""
    if reason is None or not isinstance(confidence, dict):
        return
    confidence["reasons"] = list(confidence.get("reasons") or []) + [reason]
    if confidence.get("verdict") == "ok":
        confidence["verdict"] = "check"


def track_metrics(previous: np.ndarray, estimate: np.ndarray, reference: list | None, points: np.ndarray, rig: Rig,
                  used_views: tuple[str, ...], depth_held_mm: float | None, confidence: dict | None) -> dict:
    """The metrics a tracking result adds (``mode``, ``motion`` since the previous pose, ``tracking``), the verdict
    lowered for one plane."""
    given = None if reference is None else validate_rigid(reference, field="options.reference_mesh_to_world",
                                                          allow_mirror=False)
    record = tracking_record(previous, estimate, given, points, rig, used_views, depth_held_mm)
    lower_verdict(confidence, single_plane_reason(record))
    return {"mode": "track", "motion": record["since_previous"], "tracking": record}

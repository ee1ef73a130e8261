"""``hemodynamics.json``: per vertex of the model file as given, arrays with ``null`` where not measurable.

Arrays (one value per vertex, in the order of the file's vertices, :mod:`.model_points`): ``arrival_s``,
``peak_s``, ``peak_opacity``, ``arrival_s_ap``, ``arrival_s_lat``, ``agreement_s``, ``mtt_s``, ``area`` (the
gamma-variate fit, :mod:`.gamma_fit`); ``overlap_ap`` /
``overlap_lat`` (bool: that view is not clean there); ``unmixed`` (bool: no view is clean there, the values
come from unmixing, :mod:`.unmixing`). Times are seconds on the AP run's clock (t = 0 at its
first frame); ``frame_times_s`` gives each run's frame times on that clock.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..artifacts import HEMODYNAMICS_JSON, HEMODYNAMICS_PLY, HEMODYNAMICS_VTK  # noqa: F401 - the names, re-exported

ARRAYS = ("arrival_s", "peak_s", "peak_opacity", "arrival_s_ap", "arrival_s_lat", "agreement_s", "mtt_s", "area")
DIGITS = 4


def nullable(values: np.ndarray) -> list[float | None]:
    """Floats rounded to ``DIGITS``, ``None`` for NaN."""
    return [None if not math.isfinite(v) else round(float(v), DIGITS) for v in np.asarray(values, float)]


def hemodynamics_document(per_vertex: dict[str, np.ndarray], frame_times_s: dict[str, np.ndarray],
                          summary: dict) -> dict:
    """The JSON document from per-file-vertex arrays (``ARRAYS``, ``clean_ap`` / ``clean_lat`` and ``unmixed_ap`` /
    ``unmixed_lat``)."""
    document = {"vertex_order": summary.get("vertex_order"), "vertices": int(len(per_vertex["arrival_s"])),
                "clock": "seconds from the first AP frame",
                "frame_times_s": {name: [round(float(t), DIGITS) for t in times] for name, times in frame_times_s.items()}}
    document.update({name: nullable(per_vertex[name]) for name in ARRAYS})
    for view in ("ap", "lat"):
        document[f"overlap_{view}"] = [bool(not v) for v in per_vertex[f"clean_{view}"]]
    unmixed = np.asarray(per_vertex["unmixed_ap"], bool) | np.asarray(per_vertex["unmixed_lat"], bool)
    document["unmixed"] = [bool(v) for v in unmixed]
    document["summary"] = summary
    return document


def write_json(path: Path, document: dict) -> None:
    Path(path).write_text(json.dumps(document, separators=(",", ":")))


MESH_ARRAYS = ("arrival_s", "peak_s", "peak_opacity", "arrival_s_ap", "arrival_s_lat", "agreement_s", "mtt_s", "area")


def write_ply(path: Path, vertices_mm: np.ndarray, faces: np.ndarray, rgb: np.ndarray, comments: list[str]) -> None:
    """An ASCII PLY of the model (mesh frame, mm) with per-vertex ``red green blue`` (uint8) and ``comments``."""
    lines = ["ply", "format ascii 1.0", *[f"comment {c}" for c in comments], f"element vertex {len(vertices_mm)}",
             "property float x", "property float y", "property float z", "property uchar red", "property uchar green",
             "property uchar blue", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    lines += [f"{x:.5f} {y:.5f} {z:.5f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(vertices_mm, rgb)]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    Path(path).write_text("\n".join(lines) + "\n")


def write_vtk(path: Path, vertices_mm: np.ndarray, faces: np.ndarray, arrays: dict[str, np.ndarray]) -> None:
    """A legacy VTK file (meshio) with the model and per-vertex point-data arrays (NaN where not measured)."""
    import meshio

    point_data = {name: np.asarray(values, np.float64) for name, values in arrays.items()}
    meshio.Mesh(np.asarray(vertices_mm, float), [("triangle", np.asarray(faces, np.int64))],
                point_data=point_data).write(str(path), file_format="vtk", binary=True)

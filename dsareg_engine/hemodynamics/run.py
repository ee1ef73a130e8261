"""The hemodynamics step of a job: the runs' files → measurement on the registered model → files and a summary.

:func:`hemodynamics_step` runs after registration (the pose is final and unchanged by it) when
``options.hemodynamics`` is on. It writes ``hemodynamics.json`` (per vertex of the model file as given, or for a
volume input per vertex of ``hemodynamics.ply``, the mesh dsareg made), ``hemodynamics.ply`` (the working
model coloured by arrival time), ``hemodynamics.vtk`` (point-data arrays) and ``parametric_{ap,lat}.png``, and
returns ``result.hemodynamics``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..artifacts import RESULT_JSON, parametric_png
from ..errors import DsaregInputError
from ..io.mesh_units import MM_PER_UNIT
from ..overlay import write_png
from .colours import TimeScale
from .frames import run_frames
from .measure import VIEWS, RunFrames, measure
from .model_points import transfer, vertices_as_given
from .outputs import (HEMODYNAMICS_JSON, HEMODYNAMICS_PLY, HEMODYNAMICS_VTK, MESH_ARRAYS, hemodynamics_document,
                      write_json, write_ply, write_vtk)
from .parametric import parametric_image, pixel_arrival
from .summary import summarize
from .timing import TIMING_ACCEPTED, run_offset_s


def load_runs(files, readings: dict[str, dict]) -> dict[str, RunFrames]:
    """Each view's run (DICOM multi-frame) as frames and times; anything else is refused naming the view."""
    runs = {}
    for name in VIEWS:
        data = getattr(files, name)
        if not isinstance(data, (bytes, bytearray)) or data[128:132] != b"DICM":
            raise DsaregInputError(f"hemodynamics needs a DICOM XA run, but the {name} view is not DICOM", field=name,
                                   accepted=TIMING_ACCEPTED)
        runs[name] = run_frames(bytes(data), name, readings.get(name))
    return runs


def file_vertices(files, case) -> tuple[np.ndarray, str]:
    """The vertices (mm) the per-vertex arrays follow, and how they are ordered: the model file's as given, in the
    unit the reader took (``Case.decisions``: the mesh's ``units``), or for a volume the working mesh's."""
    if files.mesh is not None and case.kinds.get("mesh"):
        fmt = case.kinds["mesh"]
        units = [d.chosen for d in case.decisions if d.input == "mesh" and d.what == "units"]
        scale = MM_PER_UNIT.get(units[-1], 1.0) if units else 1.0
        return (vertices_as_given(files.mesh, fmt) * scale,
                f"the model file as given ({fmt.upper()} vertex order, duplicates included)")
    return case.mesh.vertices, f"{HEMODYNAMICS_PLY} (the mesh dsareg made from the volume)"


def hemodynamics_step(files, case, data: dict, out_dir: Path) -> dict:
    """Measure, write the files, return ``result.hemodynamics`` (see the module docstring)."""
    started = time.process_time()
    runs = load_runs(files, case.readings)
    offset, basis = run_offset_s(runs["ap"].timing, runs["lat"].timing)
    pose = np.asarray(data["mesh_to_world"], float)
    found = measure(case.mesh, pose, case.rig, runs, offset)
    vertices, order = file_vertices(files, case)
    moved = transfer(vertices, case.mesh)
    per_vertex = {name: moved.apply(values) for name, values in found.values.items()}
    scale = TimeScale.of(found.values["arrival_s"])
    times = {"ap": runs["ap"].timing.times_s, "lat": runs["lat"].timing.times_s + offset}
    summary = summarize(per_vertex, found, runs, offset, basis, order, moved, scale)
    out_dir = Path(out_dir)
    write_json(out_dir / HEMODYNAMICS_JSON, hemodynamics_document(per_vertex, times, summary))
    write_ply(out_dir / HEMODYNAMICS_PLY, case.mesh.vertices, case.mesh.faces, scale.rgb(found.values["arrival_s"]),
              ["dsareg hemodynamics: vertex colour = contrast arrival time (half-peak rise)", scale.describe()])
    write_vtk(out_dir / HEMODYNAMICS_VTK, case.mesh.vertices, case.mesh.faces,
              {name: found.values[name] for name in MESH_ARRAYS})
    for name in VIEWS:
        arrival, peak = pixel_arrival(runs[name].opacity, times[name])
        write_png(out_dir / parametric_png(name), parametric_image(arrival, peak, scale, f"{name.upper()} arrival time"))
    summary["files"] = [HEMODYNAMICS_JSON, HEMODYNAMICS_PLY, HEMODYNAMICS_VTK, *(parametric_png(v) for v in VIEWS)]
    summary["cpu_s"] = round(time.process_time() - started, 3)
    return summary


def attach(files, case, data: dict, out_dir: Path) -> dict:
    """Run the step after a registration and add ``result.hemodynamics`` to ``data`` and to ``result.json``."""
    data["hemodynamics"] = hemodynamics_step(files, case, data, out_dir)
    (Path(out_dir) / RESULT_JSON).write_text(json.dumps(data, indent=2))
    return data

"""The step on DICOM runs as a job reads them: files written, one value per vertex of the OBJ as given, refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.hemodynamics.intake import check_timed_runs
from dsareg_engine.hemodynamics.run import hemodynamics_step
from dsareg_engine.io.case import CaseFiles, load_case_files
from dsareg_engine.simulation.bolus_dicom import bolus_xa
from dsareg_engine.simulation.bolus_run import BolusSettings, make_bolus_run
from dsareg_engine.simulation.native_run import Plane, tree_root
from dsareg_engine.simulation.phantom import make_vessel_phantom

PLANES = {"ap": Plane(-6.0, 8.0, 1200.0, 800.0, 1.2), "lat": Plane(94.0, 1.0, 1180.0, 790.0, 1.2)}


def _obj_with_a_duplicate(mesh) -> bytes:
    """The mesh as OBJ, its first vertex repeated at the end (unused by any face: it must still get a value)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines.append(lines[0])
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return ("\n".join(lines) + "\n").encode()


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    mesh = make_vessel_phantom(seed=1, depth=2)
    rig = Rig(views={name: plane.view(128) for name, plane in PLANES.items()})
    pose = np.eye(4)
    pose[:3, 3] = -mesh.centroid
    settings = BolusSettings(fps=4.0, n_frames=24, supersample=1, noise="gaussian", lat_delay_s=0.5)
    run = make_bolus_run(mesh, rig, pose, settings, seed=2, inflow_mm=tree_root(mesh))
    files = CaseFiles(ap=bolus_xa(run.frames["ap"], PLANES["ap"], "ap", "no-recipe", settings.fps),
                      lat=bolus_xa(run.frames["lat"], PLANES["lat"], "lat", "subtracted", settings.fps, lat_delay_s=0.5),
                      mesh=_obj_with_a_duplicate(mesh), mesh_name="model.obj")
    case = load_case_files(files)
    out = tmp_path_factory.mktemp("hemodynamics")
    summary = hemodynamics_step(files, case, {"mesh_to_world": pose.tolist()}, out)
    return mesh, run, case, summary, out


def test_every_file_is_written_and_the_json_follows_the_obj_vertex_lines(job):
    mesh, run, case, summary, out = job
    assert case.readings["ap"]["run"] == "native"  # no recipe: the reader found the masks
    for name in summary["files"]:
        assert (out / name).stat().st_size > 0
    document = json.loads((out / "hemodynamics.json").read_text())
    assert document["vertices"] == len(mesh.vertices) + 1
    assert all(len(document[key]) == len(mesh.vertices) + 1 for key in ("arrival_s", "peak_s", "agreement_s"))
    assert document["arrival_s"][-1] == document["arrival_s"][0]  # the repeated vertex
    arrival = np.array([np.nan if v is None else v for v in document["arrival_s"][:-1]])
    mapped = np.isfinite(arrival)
    assert mapped.mean() > 0.75
    assert np.median(np.abs(arrival[mapped] - run.truth.arrival_s[mapped])) < 0.125
    assert summary["offset_s"] == pytest.approx(0.5) and "start times" in summary["offset_basis"]
    assert document["frame_times_s"]["lat"][0] == pytest.approx(0.5)


def test_the_ply_and_vtk_carry_the_colours_and_arrays(job):
    import meshio

    mesh, run, case, summary, out = job
    header = (out / "hemodynamics.ply").read_text().split("end_header")[0]
    assert "comment arrival time colour scale: Turbo" in header and "property uchar red" in header
    vtk = meshio.read(out / "hemodynamics.vtk")
    assert len(vtk.points) == len(case.mesh.vertices)
    assert {"arrival_s", "peak_s", "agreement_s", "arrival_s_ap", "arrival_s_lat"} <= set(vtk.point_data)


def test_a_still_image_or_an_untimed_run_is_refused_naming_the_view(job, tmp_path):
    from pydicom import dcmread
    import io

    mesh, run, case, summary, out = job
    data = bolus_xa(run.frames["lat"], PLANES["lat"], "lat", "no-recipe", 4.0)
    untimed = dcmread(io.BytesIO(data))
    del untimed.FrameTimeVector
    buffer = io.BytesIO()
    untimed.save_as(buffer)
    with pytest.raises(DsaregInputError) as caught:
        check_timed_runs(CaseFiles(ap=data, lat=buffer.getvalue()))
    assert caught.value.field == "lat" and "without frame timing" in caught.value.message
    with pytest.raises(DsaregInputError, match="not DICOM") as caught:
        check_timed_runs(CaseFiles(ap=b"\x89PNG\r\n\x1a\n" + bytes(200), lat=data))
    assert caught.value.field == "ap"


def test_the_summary_and_the_document_hold_the_service_contract(job):
    from service.api.schemas.hemodynamics import HemodynamicsDocument, HemodynamicsSummary

    mesh, run, case, summary, out = job
    HemodynamicsSummary.model_validate(summary)
    HemodynamicsDocument.model_validate(json.loads((out / "hemodynamics.json").read_text()))

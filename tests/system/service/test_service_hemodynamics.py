"""Hemodynamics through the HTTP service: a job with options.hemodynamics on small timed runs, its files and links,
the same pose as without it, a generated client reading result.hemodynamics, and 422s at submission."""

from __future__ import annotations

import importlib
import io
import json
import shutil
import subprocess

import numpy as np
import pydicom
import pytest
from tests.support.service_testkit import forget_generated_client, generated_client, needs_engine, wait_for

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.simulation.bolus_dicom import bolus_xa
from dsareg_engine.simulation.bolus_run import BolusSettings, make_bolus_run
from dsareg_engine.simulation.native_run import Plane, pose_in_view, to_bytes, tree_root
from dsareg_engine.simulation.phantom import make_vessel_phantom

PLANES = {"ap": Plane(-6.0, 8.0, 1200.0, 800.0, 1.2), "lat": Plane(94.0, 1.0, 1180.0, 790.0, 1.2)}
OPTIONS = {"starts": 1, "max_iterations": 60}


@pytest.fixture(scope="module")
def runs():
    mesh = make_vessel_phantom(seed=4, depth=2)
    rig = Rig(views={name: plane.view(112) for name, plane in PLANES.items()})
    pose = pose_in_view(mesh, rig, 4)
    settings = BolusSettings(fps=4.0, n_frames=20, supersample=1, start_s=1.0, transit_s=1.5)
    run = make_bolus_run(mesh, rig, pose, settings, seed=4, inflow_mm=tree_root(mesh))
    files = {"ap": bolus_xa(run.frames["ap"], PLANES["ap"], "ap", "recipe", settings.fps),
             "lat": bolus_xa(run.frames["lat"], PLANES["lat"], "lat", "no-recipe", settings.fps)}
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices] + \
        [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return run, files, ("\n".join(lines) + "\n").encode()


def _post(client, runs, options: dict, **override):
    run, files, mesh = runs
    files = {**files, **override}
    parts = [("mesh", ("tree.obj", mesh, "application/octet-stream")),
             ("ap", ("ap.dcm", files["ap"], "application/dicom")),
             ("lat", ("lat.dcm", files["lat"], "application/dicom"))]
    return client.post("/v1/registrations", files=parts, data={"options": json.dumps(options)})


def _job(client, runs, options: dict) -> dict:
    response = _post(client, runs, options)
    assert response.status_code == 202, response.text
    final = wait_for(client, response.json()["id"], timeout=300)
    assert final["status"] == "succeeded", final
    return final


@needs_engine
def test_a_job_maps_arrival_onto_the_model_and_serves_every_file(server, runs, tmp_path):
    run, _, _ = runs
    with server.client() as client:
        final = _job(client, runs, {**OPTIONS, "hemodynamics": True})
        plain = _job(client, runs, OPTIONS)
        links = final["links"]
        document = client.get(links["hemodynamics"]).json()
        model = client.get(links["model"]).json()  # the review page's 3D scene colours these vertices by arrival
        for key, media in (("hemodynamics_ply", "application/octet-stream"), ("hemodynamics_vtk", "application/octet-stream"),
                           ("parametric_ap", "image/png"), ("parametric_lat", "image/png")):
            response = client.get(links[key])
            assert response.status_code == 200 and response.headers["content-type"].startswith(media), key
        dicom = client.get(links["dicom_parametric_lat"]).content
        openapi = client.get("/openapi.json").text
    assert final["result"]["mesh_to_world"] == plain["result"]["mesh_to_world"]  # the registration is unchanged
    assert "hemodynamics" not in plain["links"]
    summary = final["result"]["hemodynamics"]
    assert document["vertices"] == summary["vertices"] == len(run.mesh.vertices)  # the OBJ's v lines
    assert model["vertex_count"] == document["vertices"] and model["vertex_order"] == "file"
    assert np.allclose(np.reshape(model["vertices"], (-1, 3)), run.mesh.vertices, atol=1e-4)  # same order
    arrival = np.array([np.nan if v is None else v for v in document["arrival_s"]])
    mapped = np.isfinite(arrival)
    assert mapped.mean() > 0.6, summary
    assert np.median(np.abs(arrival[mapped] - run.truth.arrival_s[mapped])) < 0.25  # one frame interval
    _dciodvfy_clean(dicom, tmp_path)
    _generated_client_reads(openapi, final, tmp_path)


def _dciodvfy_clean(data: bytes, tmp_path) -> None:
    assert pydicom.dcmread(io.BytesIO(data)).Modality == "OT"
    if shutil.which("dciodvfy") is None:
        return
    path = tmp_path / "parametric_lat.dcm"
    path.write_bytes(data)
    done = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60, check=False)
    errors = [line for line in (done.stdout + done.stderr).splitlines() if line.startswith("Error")]
    assert not errors, errors


def _generated_client_reads(openapi: str, final: dict, tmp_path) -> None:
    (tmp_path / "client").mkdir()
    generated_client(openapi, tmp_path / "client")
    try:
        models = importlib.import_module("dsareg_client.models")
        job = models.JobStatus.from_dict(final)
        summary = job.result.hemodynamics
        assert isinstance(summary, models.HemodynamicsSummary)
        assert summary.mapped_fraction == final["result"]["hemodynamics"]["mapped_fraction"]
        assert isinstance(summary.views["ap"].timing, models.RunTimingRecord)
    finally:
        forget_generated_client(tmp_path / "client")


@needs_engine
def test_a_still_image_or_an_untimed_run_is_422_at_submission(server, runs):
    _, files, _ = runs
    untimed = pydicom.dcmread(io.BytesIO(files["lat"]))
    del untimed.FrameTimeVector
    still = pydicom.dcmread(io.BytesIO(files["ap"]))
    first = still.pixel_array[0]
    still.NumberOfFrames = 1
    still.PixelData = first.tobytes()
    del still.MaskSubtractionSequence
    with server.client() as client:
        for override, field, words in (({"lat": to_bytes(untimed)}, "lat", "without frame timing"),
                                       ({"ap": to_bytes(still)}, "ap", "single frame")):
            response = _post(client, runs, {**OPTIONS, "hemodynamics": True}, **override)
            assert response.status_code == 422, response.text
            body = response.json()
            assert body["field"] == field and words in body["detail"] and "Frame Time" in body["accepted"], body

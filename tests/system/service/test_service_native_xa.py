"""Native XA runs through the HTTP service: accepted by multipart with no geometry, per-view frames,
and refused at submission (422 naming the field) when they cannot be read."""

from __future__ import annotations

import io
import json

import numpy as np
import pydicom
import pytest
from tests.support.service_testkit import needs_engine, wait_for

from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.simulation.native_run import to_bytes
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    case = make_skull_run(0, SkullRunSettings(size_px=96))
    path = tmp_path_factory.mktemp("mesh") / "tree.obj"
    case.mesh.save(path)
    return case, path.read_bytes()


def _post(client, run, ap: bytes | None = None, lat: bytes | None = None, options: dict | None = None):
    case, mesh = run
    files = [("mesh", ("tree.obj", mesh, "application/octet-stream")),
             ("ap", ("ap.dcm", ap or case.files["ap"], "application/dicom")),
             ("lat", ("lat.dcm", lat or case.files["lat"], "application/dicom"))]
    return client.post("/v1/registrations", files=files, data={"options": json.dumps(options or {})})


def _edited(data: bytes, edit) -> bytes:
    dataset = pydicom.dcmread(io.BytesIO(data))
    edit(dataset)
    return to_bytes(dataset)


@needs_engine
def test_native_runs_register_with_per_view_frames(server, run):
    case, _ = run
    with server.client() as client:
        response = _post(client, run, options={"frames": {"ap": None, "lat": "minip"}})
        assert response.status_code == 202, response.text
        final = wait_for(client, response.json()["id"], timeout=240)
    assert final["status"] == "succeeded", final
    result = final["result"]
    reading = result["image_reading"]
    assert reading["ap"]["run"] == reading["lat"]["run"] == "native"
    assert reading["ap"]["combined"] == "arterial" and reading["lat"]["combined"] == "minip"  # the default: arterial phase
    assert len(reading["ap"]["frame_indices"]) > 1 and reading["ap"]["phase"].startswith("arterial phase")
    add = mean_distance_mm(np.asarray(result["mesh_to_world"]), case.mesh_to_world, case.mesh.vertices)
    assert add < 0.3, add


@needs_engine
def test_unreadable_runs_are_refused_at_submission(server, run):
    case, _ = run

    def no_contrast(dataset):
        frames = dataset.pixel_array.copy()
        frames[:] = frames[0]
        dataset.PixelData = frames.tobytes()

    def missing_mask_frame(dataset):
        dataset.MaskSubtractionSequence[0].MaskFrameNumbers = [1, 12]

    with server.client() as client:
        cases = [({"ap": _edited(case.files["ap"], no_contrast)}, {}, "ap", "contrast"),
                 ({"lat": _edited(case.files["lat"], missing_mask_frame)}, {},
                  "lat.MaskSubtractionSequence[0].MaskFrameNumbers", "does not exist"),
                 ({}, {"frames": {"ap": 0}}, "ap", "not a contrast frame"),
                 ({}, {"frames": {"lat": -1}}, "options.frames.lat", "")]
        for images, options, field, words in cases:
            response = _post(client, run, options=options, **images)
            assert response.status_code == 422, response.text
            body = response.json()
            assert body["field"] == field and words in body["detail"], body

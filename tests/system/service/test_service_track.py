"""POST /v1/registrations/{id}/track: a new AP/LAT pair re-registered from a finished job (real server)."""

from __future__ import annotations

import json

import numpy as np
from tests.support.service_testkit import FAST_OPTIONS, needs_engine, png_bytes, render_mask, small_views, submit, wait_for

from dsareg_engine.registration.parameterization import random_start_poses


@needs_engine
def test_track_reuses_the_model_and_reports_the_motion(server, example_case):
    views, _ = small_views()
    centre = example_case.vertices.mean(axis=0)
    moved = random_start_poses(np.eye(4), centre, 2, 2.0, 2.0, seed=3)[1]  # 2° about the centre, 2 mm
    new_masks = {name: render_mask(example_case.vertices, example_case.faces, view, moved) for name, view in views.items()}
    with server.client() as c:
        first = submit(c, example_case)
        assert first.status_code == 202, first.text
        previous = wait_for(c, first.json()["id"], timeout=180)
        assert previous["status"] == "succeeded", previous

        files = [("ap", ("ap2.png", png_bytes(new_masks["ap"]), "image/png")),
                 ("lat", ("lat2.png", png_bytes(new_masks["lat"]), "image/png"))]
        response = c.post(f"/v1/registrations/{previous['id']}/track", files=files,
                          data={"options": json.dumps({"max_iterations": 40})})
        assert response.status_code == 202, response.text
        job = response.json()
        assert job["id"] != previous["id"] and response.headers["location"] == f"/v1/registrations/{job['id']}"
        previous_link = f'</v1/registrations/{previous["id"]}>; rel="previous"'
        assert response.headers["link"] == previous_link
        final = wait_for(c, job["id"], timeout=180)
        assert final["status"] == "succeeded", final
        # the tracking job points back wherever it is read: its status, its result, its summary
        assert final["links"]["previous"] == f"/v1/registrations/{previous['id']}"
        assert c.get(f"/v1/registrations/{job['id']}").headers["link"] == previous_link
        assert c.get(f"/v1/registrations/{job['id']}/result").headers["link"] == previous_link
        listed = c.get("/v1/registrations", params={"limit": 100}).json()["items"]
        assert next(i for i in listed if i["id"] == job["id"])["links"]["previous"] == final["links"]["previous"]
        assert "link" not in c.get(f"/v1/registrations/{previous['id']}").headers
        result = final["result"]
        metrics = result["metrics"]
        assert metrics["mode"] == "track" and metrics["starts"] == 1
        assert np.allclose(result["initial_mesh_to_world"], previous["result"]["mesh_to_world"])
        motion = metrics["motion"]
        # The previous estimate is near the identity (the first masks' pose): the motion is about 2° and 2 mm.
        assert abs(motion["translation_mm"] - 2.0) < 0.5, motion
        assert abs(motion["rotation_deg"] - 2.0) < 1.0, motion
        for name, view in views.items():
            registered = render_mask(example_case.vertices, example_case.faces, view, np.asarray(result["mesh_to_world"]))
            overlap = (registered & new_masks[name]).sum() * 2 / (registered.sum() + new_masks[name].sum())
            assert overlap > 0.9, (name, overlap)


@needs_engine
def test_track_errors(server, example_case):
    files = [("ap", ("ap.png", example_case.ap_png, "image/png")), ("lat", ("lat.png", example_case.lat_png, "image/png"))]
    with server.client() as c:
        missing = c.post("/v1/registrations/nope/track", files=files)
        assert missing.status_code == 404 and missing.headers["content-type"].startswith("application/problem+json")
        first = submit(c, example_case, options=FAST_OPTIONS)
        job_id = first.json()["id"]
        wait_for(c, job_id, timeout=180)
        extra = c.post(f"/v1/registrations/{job_id}/track",
                       files=[*files, ("mesh", ("m.obj", example_case.mesh_obj, "application/octet-stream"))])
        assert extra.status_code == 422 and extra.json()["field"] == "mesh"
        bad = c.post(f"/v1/registrations/{job_id}/track", files=files, data={"options": "[1]"})
        assert bad.status_code == 422 and bad.json()["field"] == "options"
        assert c.post(f"/v1/registrations/{job_id}/track", data={"x": "1"}).status_code == 415

"""POST /v1/registrations/{id}/track: a new AP/LAT pair re-registered from a finished job (real server)."""

from __future__ import annotations

import io
import json

import numpy as np
import pydicom
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


@needs_engine
def test_track_one_plane_then_both_reports_the_motion_since_the_first_pose(server, example_case):
    """A later AP run alone: only AP is fitted, the motion along its beam is said to be unmeasured, never `ok`; a
    later run of both planes from that job carries the first job's pose as the reference."""
    views, _ = small_views()
    centre = example_case.vertices.mean(axis=0)
    moved = random_start_poses(np.eye(4), centre, 2, 1.5, 1.5, seed=3)[1]
    later = random_start_poses(moved, centre, 2, 1.5, 1.5, seed=5)[1]
    masks = {name: render_mask(example_case.vertices, example_case.faces, view, later) for name, view in views.items()}
    ap_mask = render_mask(example_case.vertices, example_case.faces, views["ap"], moved)
    with server.client() as c:
        first = wait_for(c, submit(c, example_case).json()["id"], timeout=180)
        assert first["status"] == "succeeded", first
        refused = c.post(f"/v1/registrations/{first['id']}/track", files=[("ap", ("ap2.png", png_bytes(ap_mask), "image/png"))],
                         data={"options": json.dumps({"configuration": "lat"})})
        assert refused.status_code == 422 and refused.json()["field"] == "options.configuration", refused.text
        nothing = c.post(f"/v1/registrations/{first['id']}/track", files={"options": (None, "{}")})
        assert nothing.status_code == 422 and nothing.json()["field"] == "ap", nothing.text

        one = c.post(f"/v1/registrations/{first['id']}/track", files=[("ap", ("ap2.png", png_bytes(ap_mask), "image/png"))])
        assert one.status_code == 202, one.text
        one = wait_for(c, one.json()["id"], timeout=180)
        assert one["status"] == "succeeded", one
        tracking = one["result"]["metrics"]["tracking"]
        assert tracking["views"] == ["ap"] and not tracking["along_beam_measured"] and tracking["unmeasured_view"] == "ap"
        assert one["result"]["verdict"] == "check" and "AP beam" in one["result"]["metrics"]["confidence"]["reasons"][-1]
        assert np.allclose(tracking["reference_mesh_to_world"], first["result"]["mesh_to_world"])

        both = c.post(f"/v1/registrations/{one['id']}/track", files=[
            ("ap", ("ap3.png", png_bytes(masks["ap"]), "image/png")), ("lat", ("lat3.png", png_bytes(masks["lat"]), "image/png"))])
        assert both.status_code == 202, both.text
        both = wait_for(c, both.json()["id"], timeout=180)
        assert both["status"] == "succeeded", both
        tracking = both["result"]["metrics"]["tracking"]
        assert tracking["views"] == ["ap", "lat"] and tracking["along_beam_measured"] and tracking["reference_given"]
        assert np.allclose(tracking["reference_mesh_to_world"], first["result"]["mesh_to_world"])  # carried along
        assert np.allclose(both["result"]["initial_mesh_to_world"], one["result"]["mesh_to_world"])
        true = np.asarray(later)[:3, :3] @ centre + later[:3, 3] - (np.asarray(first["result"]["mesh_to_world"])[:3, :3]
                                                                  @ centre + np.asarray(first["result"]["mesh_to_world"])[:3, 3])
        assert np.linalg.norm(np.subtract(tracking["since_reference"]["translation_vector_mm"], true)) < 0.5, tracking


CAPTIONS = ("return Object.fromEntries([...document.querySelectorAll('#views figcaption')]"
            ".map((c) => [c.dataset.view, c.innerText]))")


@needs_engine
def test_a_one_plane_track_says_which_image_is_from_an_earlier_run(server, example_case, tmp_path):
    """Issue 42: a LAT-less track shows the earlier LAT image; the job's case, its result's views and the review
    page name that image as carried from the job it was sent with (followed back through a second one-plane track),
    the AP image as this run's."""
    from tests.support.webdriver import Browser, browser_binaries

    views, _ = small_views()
    centre = example_case.vertices.mean(axis=0)
    moved = random_start_poses(np.eye(4), centre, 2, 1.5, 1.5, seed=7)[1]
    ap_mask = png_bytes(render_mask(example_case.vertices, example_case.faces, views["ap"], moved))
    with server.client() as c:
        first = wait_for(c, submit(c, example_case, options=FAST_OPTIONS).json()["id"], timeout=180)
        jobs = [first]
        for name in ("ap2.png", "ap3.png"):  # AP alone, twice: the LAT image stays the first job's
            sent = c.post(f"/v1/registrations/{jobs[-1]['id']}/track", files=[("ap", (name, ap_mask, "image/png"))],
                          data={"options": json.dumps({"max_iterations": 30})})
            assert sent.status_code == 202, sent.text
            jobs.append(wait_for(c, sent.json()["id"], timeout=180))
            assert jobs[-1]["status"] == "succeeded", jobs[-1]
        derivations = {view: pydicom.dcmread(io.BytesIO(c.get(jobs[-1]["links"][f"dicom_overlay_{view}"]).content))
                       .DerivationDescription for view in ("ap", "lat")}
        assert "not fitted" in derivations["lat"] and "not fitted" not in derivations["ap"], derivations
    assert all(view.get("image_from_job") is None for view in first["result"]["views"].values())
    for job in jobs[1:]:
        carried = {row["role"]: row.get("carried_from") for row in job["case"]["inputs"]}
        assert carried["lat"] == first["id"] and carried["ap"] is None and carried["mesh"] is None, carried
        assert job["result"]["views"]["lat"]["image_from_job"] == first["id"]
        assert job["result"]["views"]["ap"].get("image_from_job") is None
    browser_binaries()
    browser = Browser(tmp_path / "profile", width=1280, height=1000)
    try:
        browser.open(server.url + f"/ui/#/job/{jobs[2]['id']}")
        browser.wait("const s = document.getElementById('views'); return s && s.dataset.ready === '1'", what="views")
        captions = browser.run(CAPTIONS)
        lat_caption = captions["lat"]
        assert "earlier run" in lat_caption and first["id"][:12] in lat_caption and "not fitted" in lat_caption
        assert "acquired for this job" in captions["ap"] and "earlier" not in captions["ap"], captions
        note = browser.run("return document.getElementById('carried-note').innerText")
        assert note.startswith("Only AP was acquired for this job") and first["id"][:12] in note, note
        assert browser.run("return document.querySelector('#carried-note a').getAttribute('href')") == \
            f"#/job/{first['id']}"
        inputs = browser.run("return document.querySelector('#case li[data-role=\"lat\"]').innerText")
        assert "carried from an earlier run" in inputs and first["id"][:12] in inputs, inputs
        browser.resize(1280, 1500)  # the case, the note and both views with their captions in one picture
        browser.screenshot(tmp_path / "tracked-one-plane.png")
        browser.open(server.url + f"/ui/#/job/{first['id']}")  # a job of both planes says nothing of the kind
        browser.wait("const s = document.getElementById('views'); return s && s.dataset.ready === '1'", what="views")
        assert browser.run("return document.getElementById('carried-note')") is None
        assert browser.run(CAPTIONS) == {"ap": "AP: the image registered", "lat": "LAT: the image registered"}
    finally:
        browser.close()

"""The HTTP API against a real server (subprocess, real SQLite, real HTTP)."""

from __future__ import annotations

import io
import json
import sqlite3

import httpx
import numpy as np
import pytest
from tests.support.service_testkit import CASE_SIZE, FAST_OPTIONS, dice, needs_engine, render_mask, small_views, submit, wait_for
from tests.system.service.conftest import UPLOAD_LIMIT_BYTES

PROBLEM = "application/problem+json"


def _assert_problem(response: httpx.Response, status: int, field: str | None = None) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith(PROBLEM)
    body = response.json()
    assert body["status"] == status and body["title"] and body["type"].startswith("https://")
    assert body["detail"] and "Traceback" not in response.text
    if field is not None:
        assert body.get("field") == field, body
    return body


def test_health_ready_docs_and_loopback_only(server):
    with server.client() as c:
        assert c.get("/healthz").json()["status"] == "ok"
        ready = c.get("/readyz")
        assert ready.status_code == 200 and ready.json()["checks"]["workers_alive"] >= 1
        schema = c.get("/openapi.json").json()
        # authentication is off: no scheme, no lock in /docs (test_service_contract checks a server with keys)
        assert "securitySchemes" not in schema["components"]
        assert not [op for ops in schema["paths"].values() for op in ops.values() if "security" in op]
        post = schema["paths"]["/v1/registrations"]["post"]
        assert {"202", "400", "409", "413", "415", "422", "429", "503"} <= set(post["responses"])
        assert c.get("/docs").status_code == 200
    logs = server.logs()  # asked for 0.0.0.0 without keys: one warning says where it listens (was two lines)
    assert logs.count("no API keys configured") == 1 and "listens on 127.0.0.1 only (not 0.0.0.0" in logs, logs[:3000]


@needs_engine
def test_end_to_end_phantom(server, example_case):
    with server.client() as c:
        # client file names may carry patient identifiers: only their suffix may be kept
        names = ("DOE_JANE_19700101.obj", "DOE_JANE_19700101_ap.png", "DOE_JANE_19700101_lat.png")
        response = submit(c, example_case, names=names)
        assert response.status_code == 202, response.text
        job = response.json()
        assert response.headers["location"] == f"/v1/registrations/{job['id']}"
        assert int(response.headers["retry-after"]) >= 1
        assert job["status"] == "queued" and job["links"]["self"] == response.headers["location"]
        final = wait_for(c, job["id"], timeout=180)
        assert final["status"] == "succeeded", final
        assert final["attempts"] == 1 and final["started_at"] and final["finished_at"]
        result = final["result"]
        assert {"mesh_to_world", "views", "metrics"} <= set(result)
        pose = np.asarray(result["mesh_to_world"], dtype=float)
        assert pose.shape == (4, 4)
        assert c.get(final["links"]["result"]).json() == result

        from PIL import Image

        views, _ = small_views()
        for view in ("ap", "lat"):
            for kind in ("overlays", "masks"):
                r = c.get(f"/v1/registrations/{job['id']}/{kind}/{view}.png")
                assert r.status_code == 200 and r.headers["content-type"] == "image/png"
                image = Image.open(io.BytesIO(r.content))
                image.verify()
                size = Image.open(io.BytesIO(r.content)).size
                if kind == "masks":  # the mask registered, pixel for pixel
                    assert size == (CASE_SIZE, CASE_SIZE)
                else:  # the vessels' region enlarged to a readable size, with a caption band
                    assert min(size) >= 256, size
            registered = render_mask(example_case.vertices, example_case.faces, views[view], pose)
            score = dice(registered, example_case.masks[view])
            print(f"Dice {view}: {score:.3f}")
            assert score > 0.8, f"{view}: Dice {score:.3f}"
        _assert_problem(c.get(f"/v1/registrations/{job['id']}/animation.gif"), 404)
        metrics = c.get("/metrics").text
        assert 'dsareg_jobs{state="succeeded"}' in metrics and "dsareg_queue_depth" in metrics
        assert "dsareg_job_duration_seconds_bucket" in metrics
        assert 'route="/v1/registrations/{job_id}"' in metrics
    # client file names may carry patient identifiers: they are kept only in the job's case identity (shown to the
    # job's owner, like a DICOM input's patient), never in logs, paths or any other column
    case = final.get("case") or {}
    assert "DOE_JANE_19700101_ap.png" in json.dumps(case), case
    assert "DOE_JANE" not in server.logs()
    for path in server.data_dir.rglob("*"):
        assert "DOE_JANE" not in path.name
    database = server.data_dir / "jobs.sqlite3"
    with sqlite3.connect(database) as db:
        for (table,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'").fetchall():
            columns = [row[1] for row in db.execute(f"PRAGMA table_info({table})")]
            for row in db.execute(f"SELECT * FROM {table}"):
                for column, value in zip(columns, row):
                    if (table, column) not in {("jobs", "case_identity"), ("jobs", "case_search")}:
                        assert "doe_jane" not in str(value).lower(), (table, column)


@needs_engine
def test_cancel_queued_and_running(server, example_case):
    long_options = {"starts": 8, "max_iterations": 2000, "seed": 11}  # runs for seconds
    with server.client() as c:
        running = submit(c, example_case, options=long_options).json()
        queued = submit(c, example_case, options={**long_options, "seed": 12}).json()
        wait_for(c, running["id"], statuses=("running",), timeout=60,
                 predicate=lambda b: (b.get("progress") or {}).get("iteration", 0) > 0)
        r = c.post(f"/v1/registrations/{queued['id']}/cancel")
        assert r.status_code == 200 and r.json()["status"] == "canceled"
        r = c.post(f"/v1/registrations/{running['id']}/cancel")
        assert r.status_code == 202 and r.json()["cancel_requested"] is True
        assert wait_for(c, running["id"], timeout=60)["status"] == "canceled"
        _assert_problem(c.get(f"/v1/registrations/{running['id']}/result"), 404)
        assert c.get(f"/v1/registrations/{queued['id']}").json()["status"] == "canceled"


@needs_engine
def test_idempotency_delete_and_listing(server, example_case):
    with server.client() as c:
        first = submit(c, example_case, headers={"Idempotency-Key": "idem-1"})
        assert first.status_code == 202
        replay = submit(c, example_case, headers={"Idempotency-Key": "idem-1"})
        assert replay.status_code == 200 and replay.json()["id"] == first.json()["id"]
        body = _assert_problem(submit(c, example_case, options={"starts": 1, "max_iterations": 31},
                                      headers={"Idempotency-Key": "idem-1"}), 409)
        assert body["job_id"] == first.json()["id"]
        other = submit(c, example_case)
        assert other.status_code == 202 and other.json()["id"] != first.json()["id"]

        job_id = first.json()["id"]
        wait_for(c, job_id, timeout=180)
        page1 = c.get("/v1/registrations", params={"limit": 1}).json()
        assert len(page1["items"]) == 1 and page1["next_cursor"]
        page2 = c.get("/v1/registrations", params={"limit": 1, "cursor": page1["next_cursor"]}).json()
        assert page2["items"][0]["id"] != page1["items"][0]["id"]
        finished = c.get("/v1/registrations", params={"status": "succeeded", "limit": 100}).json()["items"]
        assert job_id in [j["id"] for j in finished]

        blobs_before = {p.name for p in (server.data_dir / "blobs").glob("??/*")}
        assert c.delete(f"/v1/registrations/{job_id}").status_code == 204
        _assert_problem(c.get(f"/v1/registrations/{job_id}"), 404)
        _assert_problem(c.get(f"/v1/registrations/{job_id}/overlays/ap.png"), 404)
        _assert_problem(c.delete(f"/v1/registrations/{job_id}"), 404)
        # shared input blobs stay (the other job uses them); nothing new appeared
        assert {p.name for p in (server.data_dir / "blobs").glob("??/*")} <= blobs_before
        # deleting a job that is queued or running works as well (the worker drops it)
        assert c.delete(f"/v1/registrations/{other.json()['id']}").status_code == 204
        _assert_problem(c.get(f"/v1/registrations/{other.json()['id']}"), 404)


def test_oversized_upload_rejected_while_streaming(server):
    limit = UPLOAD_LIMIT_BYTES

    def body():
        boundary = b"--xyz\r\nContent-Disposition: form-data; name=\"mesh\"; filename=\"m.obj\"\r\n\r\n"
        yield boundary
        for _ in range(limit // 65536 + 64):  # well past the limit, in chunks, no Content-Length
            yield b"v 0 0 0\n" * 8192

    with server.client() as c:
        response = c.post("/v1/registrations", content=body(),
                          headers={"content-type": "multipart/form-data; boundary=xyz"})
        assert "content-length" not in {k.lower() for k in response.request.headers}
        _assert_problem(response, 413)
    # a declared Content-Length over the limit is refused before any body byte is read
    import socket

    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(b"POST /v1/registrations HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=x\r\n"
                     + f"Content-Length: {limit + 1}\r\n\r\n".encode())
        reply = sock.recv(4096).decode(errors="replace")
    assert reply.startswith("HTTP/1.1 413") and PROBLEM in reply
    with server.client() as c:
        assert c.get("/healthz").status_code == 200


def test_bad_requests_get_problem_details(server, example_case):
    with server.client() as c:
        _assert_problem(c.post("/v1/registrations", json={"mesh": "x"}), 422, field="source")  # issue 21: not 415
        files = {"mesh": ("m.obj", example_case.mesh_obj), "lat": ("l.png", example_case.lat_png)}
        _assert_problem(c.post("/v1/registrations", files=files), 422, field="ap")
        files["ap"] = ("a.png", example_case.ap_png)
        _assert_problem(c.post("/v1/registrations", files=files, data={"options": '{"starts": 0}'}), 422,
                        field="options.starts")
        _assert_problem(c.post("/v1/registrations", files=files, data={"options": "{not json"}), 422)
        _assert_problem(c.post("/v1/registrations", files=files, data={"geometry": "{broken"}), 422, field="geometry")
        _assert_problem(c.post("/v1/registrations", files=files, data={"geometry": "/etc/passwd"}), 422,
                        field="geometry")
        _assert_problem(c.post("/v1/registrations", files=files, data={"surprise": "1"}), 422)
        _assert_problem(c.get("/v1/registrations/" + "0" * 32), 404)
        _assert_problem(c.get("/v1/registrations", params={"status": "sleeping"}), 422, field="status")
        _assert_problem(c.get("/v1/registrations", params={"limit": 1000}), 422, field="limit")
        _assert_problem(c.get("/v1/registrations", params={"cursor": "%%%"}), 400, field="cursor")
        _assert_problem(c.get("/nowhere"), 404)
        _assert_problem(c.put("/v1/registrations"), 405)
        assert c.get("/healthz").status_code == 200


@needs_engine
def test_unreadable_files_are_422_with_field(server, example_case):
    with server.client() as c:
        base = {"mesh": ("m.obj", example_case.mesh_obj), "ap": ("a.png", example_case.ap_png),
                "lat": ("l.png", example_case.lat_png)}
        data = {"geometry": json.dumps(example_case.geometry), "options": json.dumps(FAST_OPTIONS)}
        for field, junk in (("ap", ("a.png", b"\x89PNG\r\n\x1a\nnot really")), ("mesh", ("m.stl", b"solid x\nnonsense")),
                            ("lat", ("l.png", b"\x00" * 300))):
            r = c.post("/v1/registrations", files={**base, field: junk}, data=data)
            body = _assert_problem(r, 422)
            assert body.get("field", "").startswith(field), body
        # the phantom (about 100 mm) said to be in metres: 100 m across, refused at submission naming the unit
        r = c.post("/v1/registrations", files=base, data={**data, "options": json.dumps({**FAST_OPTIONS,
                                                                                          "mesh_units": "m"})})
        body = _assert_problem(r, 422, field="mesh")
        assert "mm across read in m" in body["detail"] and "options.mesh_units" in body["accepted"], body
        assert c.get("/readyz").status_code == 200


def test_schemathesis_contract(server):
    """Property-based, against the live OpenAPI document: every operation, generated valid and
    invalid inputs, all of schemathesis' checks (no 5xx, status codes, headers, content types and
    bodies conform to the schema, invalid data rejected). Only "schema-valid data is accepted" is
    left out: a schema cannot say which bytes are a readable mesh or image, so those get a 422."""
    schemathesis = pytest.importorskip("schemathesis")
    from hypothesis import HealthCheck, Phase, given, settings
    from schemathesis.checks import positive_data_acceptance

    schema = schemathesis.openapi.from_url(server.url + "/openapi.json")
    failures: list[str] = []

    def run(operation) -> None:
        @given(case=operation.as_strategy())
        @settings(max_examples=8, deadline=None, phases=[Phase.explicit, Phase.generate],
                  suppress_health_check=list(HealthCheck), derandomize=True, database=None)
        def check(case):
            case.call_and_validate(base_url=server.url, timeout=60, excluded_checks=[positive_data_acceptance])

        try:
            check()
        except Exception as exc:  # noqa: BLE001 - collect all operations' failures
            failures.append(f"{operation.label}: {' '.join(str(exc).split())[:800]}")

    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 10
    for operation in operations:
        run(operation)
    assert not failures, "\n".join(failures)
    with server.client() as c:
        assert c.get("/healthz").status_code == 200


@needs_engine
def test_python_client_and_submit_command(server, example_case, tmp_path):
    import subprocess
    import sys

    from service.cli.client import RegistrationClient, ServiceError

    (tmp_path / "m.obj").write_bytes(example_case.mesh_obj)
    (tmp_path / "ap.png").write_bytes(example_case.ap_png)
    (tmp_path / "lat.png").write_bytes(example_case.lat_png)
    (tmp_path / "geometry.json").write_text(json.dumps(example_case.geometry))
    (tmp_path / "truth.json").write_text(json.dumps({"mesh_to_world": np.eye(4).tolist()}))

    with RegistrationClient(server.url) as client:
        job = client.submit(mesh=tmp_path / "m.obj", ap=tmp_path / "ap.png", lat=tmp_path / "lat.png",
                            geometry=tmp_path / "geometry.json", options={**FAST_OPTIONS, "seed": 5})
        seen: list[str] = []
        final = client.wait(job["id"], progress=lambda s: seen.append(s["status"]), timeout=180, interval=0.2)
        assert final["status"] == "succeeded" and seen[-1] == "succeeded"
        written = client.download_all(job["id"], tmp_path / "out")
        assert {p.name for p in written} >= {"overlay_ap.png", "overlay_lat.png", "mask_ap.png", "result.json"}
        client.delete(job["id"])
        with pytest.raises(ServiceError) as err:
            client.get(job["id"])
        assert err.value.status == 404

    out = tmp_path / "cli"
    proc = subprocess.run(
        [sys.executable, "-m", "service", "submit", "--server", server.url, "--mesh", str(tmp_path / "m.obj"),
         "--ap", str(tmp_path / "ap.png"), "--lat", str(tmp_path / "lat.png"),
         "--geometry", str(tmp_path / "geometry.json"), "--options", json.dumps({**FAST_OPTIONS, "seed": 6}),
         "--ground-truth", str(tmp_path / "truth.json"), "--out", str(out)],  # --out implies --wait
        capture_output=True, text=True, timeout=240, check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "%" in proc.stderr  # the progress bar was drawn
    assert (out / "overlay_ap.png").is_file() and (out / "overlay_lat.png").is_file()
    summary = proc.stdout.strip().splitlines()
    assert len(summary) == 1 and "dice" in summary[0] and "ADD" in summary[0], proc.stdout  # one line, like register
    assert "ground_truth" in json.loads((out / "result.json").read_text())["metrics"]

    bad = subprocess.run(
        [sys.executable, "-m", "service", "submit", "--server", server.url, "--mesh", str(tmp_path / "m.obj"),
         "--ap", str(tmp_path / "ap.png"), "--lat", str(tmp_path / "lat.png"), "--options", '{"starts": -1}'],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert bad.returncode == 2 and "options.starts" in bad.stderr and "Traceback" not in bad.stderr

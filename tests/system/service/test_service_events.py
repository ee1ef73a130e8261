"""Server-Sent Events of a job (``GET /v1/registrations/{id}/events``), read with httpx from uvicorn on loopback."""

from __future__ import annotations

import re
import time

import httpx
from tests.support.service_testkit import Server, needs_engine, submit

from service.cli.client import RegistrationClient, ServiceError, parse_event_stream
from tests.support.time_bounds import allowed


def _frames(client: httpx.Client, job_id: str, timeout: float = 120.0) -> tuple[list[dict], float]:
    """Every frame of the stream, read to its end, and the seconds the stream stayed open."""
    started = time.monotonic()
    with client.stream("GET", f"/v1/registrations/{job_id}/events", timeout=timeout) as response:
        assert response.status_code == 200, response.read()
        assert response.headers["content-type"].startswith("text/event-stream")
        frames = list(parse_event_stream(response.iter_lines()))
    return frames, time.monotonic() - started


def _open_streams(client: httpx.Client) -> float:
    match = re.search(r"^dsareg_event_streams_open (\S+)$", client.get("/metrics").text, re.MULTILINE)
    assert match, "dsareg_event_streams_open missing from /metrics"
    return float(match.group(1))


def _wait_open_streams(client: httpx.Client, expected: float, timeout: float = 5.0) -> float:
    deadline = time.monotonic() + timeout
    while (value := _open_streams(client)) != expected and time.monotonic() < deadline:
        time.sleep(0.1)
    return value


@needs_engine
def test_progress_then_one_end_event_with_the_verdict(server, example_case):
    with server.client() as client:
        # long enough (seconds) that a 0.5 s poll sees it running on a quiet machine too
        job = submit(client, example_case, options={"starts": 8, "max_iterations": 2000, "seed": 11})
        assert job.status_code == 202, job.text
        job_id = job.json()["id"]
        frames, _ = _frames(client, job_id)
        final = client.get(f"/v1/registrations/{job_id}").json()
    kinds = [f["event"] for f in frames]
    assert kinds[-1] == "end" and kinds.count("end") == 1 and set(kinds[:-1]) == {"progress"}, kinds
    progress = [f["data"] for f in frames[:-1]]
    assert all(p["id"] == job_id and p["status"] in ("queued", "running") for p in progress)
    fractions = [p["progress"]["fraction"] for p in progress if p["progress"]]
    assert fractions == sorted(fractions), fractions
    assert any(p["status"] == "running" and (p["progress"] or {}).get("stage") not in (None, "queued", "start")
               for p in progress), progress
    end = frames[-1]["data"]
    assert end["id"] == job_id and end["status"] == final["status"] == "succeeded"
    assert end["verdict"] == final["verdict"] and end["verdict"] in ("ok", "check", "failed")
    assert [int(f["id"]) for f in frames] == list(range(1, len(frames) + 1))
    with RegistrationClient(server.url) as typed:  # the Python client reads the same stream
        again = list(typed.events(job_id))
    assert [e["event"] for e in again] == ["end"] and again[0]["data"]["verdict"] == end["verdict"]


def test_keys_ownership_cancel_and_disconnect(tmp_path, example_case):
    alpha, beta = "alpha-key-0123456789", "beta-key-9876543210"
    srv = Server(tmp_path / "data", workers=0, env={"DSAREG_API_KEYS": f"{alpha},{beta}"}).start()
    try:
        with srv.client(headers={"Authorization": f"Bearer {alpha}"}) as a, \
                srv.client(headers={"Authorization": f"Bearer {beta}"}) as b, srv.client() as anonymous:
            job = submit(a, example_case)
            assert job.status_code == 202, job.text
            job_id = job.json()["id"]
            events_url = f"/v1/registrations/{job_id}/events"
            assert anonymous.get(events_url).status_code == 401
            forbidden = b.get(events_url)
            assert forbidden.status_code == 404 and forbidden.headers["content-type"].startswith("application/problem+json")
            assert a.get("/v1/registrations/nosuchjob/events").status_code == 404
            # a client that goes away: the server's stream ends (no task left behind)
            with a.stream("GET", events_url) as response:
                frames = parse_event_stream(response.iter_lines())  # kept: dropping it closes the connection
                first = next(frames)
                assert first["event"] == "progress" and first["data"]["status"] == "queued"
                assert _open_streams(a) == 1
            assert _wait_open_streams(a, 0) == 0
            # cancel while a stream is open: it ends with the summary, and the server closes it
            with RegistrationClient(srv.url, api_key=alpha) as typed:
                stream = typed.events(job_id)
                assert next(stream)["data"]["status"] == "queued"
                assert a.post(f"/v1/registrations/{job_id}/cancel").json()["status"] == "canceled"
                started = time.monotonic()
                rest = list(stream)
                assert time.monotonic() - started < allowed(5.0)
            assert [e["event"] for e in rest] == ["end"] and rest[0]["data"]["status"] == "canceled"
            with RegistrationClient(srv.url, api_key=beta) as other:
                try:
                    list(other.events(job_id))
                    raise AssertionError("another key read the job's events")
                except ServiceError as error:
                    assert error.status == 404
            assert _wait_open_streams(a, 0) == 0
            # a job deleted while its stream is open ends with 'gone'
            second = submit(a, example_case).json()["id"]
            with a.stream("GET", f"/v1/registrations/{second}/events") as response:
                frames = parse_event_stream(response.iter_lines())
                assert next(frames)["event"] == "progress"
                assert a.delete(f"/v1/registrations/{second}").status_code == 204
                assert [f["event"] for f in frames] == ["gone"]
    finally:
        srv.stop()


def test_events_in_the_openapi_document(server):
    with server.client() as client:
        document = client.get("/openapi.json").json()
    operation = document["paths"]["/v1/registrations/{job_id}/events"]["get"]
    content = operation["responses"]["200"]["content"]
    assert list(content) == ["text/event-stream"]
    schemas = document["components"]["schemas"]
    for ref in content["text/event-stream"]["x-event-data"].values():
        assert ref["$ref"].rsplit("/", 1)[-1] in schemas
    assert {"401", "404"} <= set(operation["responses"])
    assert schemas["JobProgressEvent"]["properties"]["progress"]["anyOf"][0]["$ref"] == "#/components/schemas/Progress"

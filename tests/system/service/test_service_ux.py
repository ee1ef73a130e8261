"""What integrators touch, against a real server: progress, links and list summaries over real
jobs; real responses validated against the published OpenAPI document; a client generated
from it; /docs and /redoc rendered offline in a real headless Chromium."""

from __future__ import annotations

import datetime
import importlib
import json
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path

import httpx
import pytest
from tests.support.service_testkit import make_example_case, needs_engine, submit, wait_for

PROGRESS_OPTIONS = {"starts": 2, "max_iterations": 300, "animation": True, "seed": 3}
QUICK = {"starts": 1, "max_iterations": 20, "seed": 4}


@pytest.fixture(scope="module")
def ux_server(server):
    """The shared API server (tests/system/service/conftest.py: progress written at every iteration)."""
    return server


@pytest.fixture(scope="module")
def finished_jobs(ux_server, example_case, tmp_path_factory):
    """One job with animation whose progress was polled as it ran (256 px: two pyramid levels and the
    refinement), and one quick job without."""
    larger = make_example_case(tmp_path_factory.mktemp("case256"), size=256)
    with ux_server.client() as c:
        response = submit(c, larger, options=PROGRESS_OPTIONS)
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        seen: list[dict] = []
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            body = c.get(f"/v1/registrations/{job_id}").json()
            seen.append(body)
            if body["status"] in ("succeeded", "failed", "canceled"):
                break
            time.sleep(0.02)
        quick = submit(c, example_case, options=QUICK).json()
        quick_final = wait_for(c, quick["id"], timeout=180)
    return {"animated": seen, "quick": quick_final, "first_response": response}


@needs_engine
def test_progress_is_monotone_over_a_real_job(finished_jobs):
    polls = finished_jobs["animated"]
    final = polls[-1]
    assert final["status"] == "succeeded", final
    fractions = [p["progress"]["fraction"] for p in polls if p.get("progress")]
    assert fractions == sorted(fractions), fractions  # never goes back
    running = [p["progress"] for p in polls if p["status"] == "running" and p.get("progress")]
    stages = [p["stage"] for p in running]
    optimization = {s for s in stages if ":" in s}
    assert len(optimization) >= 2, stages  # more than one pyramid level / the refinement was seen
    distinct = sorted({round(f, 3) for f in fractions if 0 < f < 1})
    assert len(distinct) >= 6, distinct  # moves in small steps, not 4 % → 84 %
    gaps = [b - a for a, b in zip(distinct, distinct[1:])]
    assert max(gaps) < 0.45, distinct
    # the finished job reports its last optimization stage at 1.0
    last_stage = list(final["result"]["metrics"]["iterations"])[-1]
    assert final["progress"]["stage"] == last_stage and final["progress"]["fraction"] == 1.0
    assert final["progress"]["iteration"] == final["result"]["metrics"]["iterations"][last_stage]
    # writing the outputs moves the bar on (stages outputs / animation / dicom / saving), not sitting at 92 %
    after = [p for p in running if p["stage"] in ("outputs", "animation", "dicom", "saving")]
    assert {p["stage"] for p in after} >= {"outputs"}, stages
    assert max(p["fraction"] for p in after) > 0.95, after
    assert len({round(p["fraction"], 3) for p in after}) >= 3, after


@needs_engine
def test_links_lead_only_to_what_exists(ux_server, finished_jobs):
    animated, quick = finished_jobs["animated"][-1], finished_jobs["quick"]
    queued = finished_jobs["first_response"].json()
    assert set(queued["links"]) == {"self", "cancel"}, queued["links"]
    assert "cancel" not in animated["links"]
    assert "animation" in animated["links"] and "animation" not in quick["links"]
    with ux_server.client() as c:
        for job in (animated, quick):
            assert {"result", "overlay_ap", "overlay_lat", "mask_ap", "mask_lat", "loss_plot", "dicom_reg",
                    "dicom_overlay_ap", "dicom_overlay_lat", "track"} <= set(job["links"]), job["links"]
            assert job["links"]["track"] == f"/v1/registrations/{job['id']}/track"
            for name, link in job["links"].items():
                assert link is not None
                if name == "track":  # a POST (tests/system/service/test_service_track.py)
                    continue
                r = c.get(link)
                assert r.status_code == 200, (name, link, r.text[:200])
        gif = c.get(animated["links"]["animation"]).content
    import io

    from PIL import Image

    image = Image.open(io.BytesIO(gif))
    assert image.n_frames >= 20


@needs_engine
def test_list_returns_summaries(ux_server, finished_jobs):
    quick = finished_jobs["quick"]
    with ux_server.client() as c:
        items = c.get("/v1/registrations", params={"limit": 100}).json()["items"]
    summary = next(item for item in items if item["id"] == quick["id"])
    assert "result" not in summary and "warnings" not in summary
    assert summary["status"] == "succeeded" and summary["finished_at"] and summary["seconds"] > 0
    assert isinstance(summary["converged"], bool) and summary["verdict"]
    assert set(summary["dice"]) == {"ap", "lat"}
    assert summary["links"] == {"self": quick["links"]["self"], "result": quick["links"]["result"]}
    assert len(json.dumps(summary)) < len(json.dumps(quick)) / 3


# ---- the published schema ------------------------------------------------------------------


def _validator(ux_server):
    schemathesis = pytest.importorskip("schemathesis")
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        response_headers_conformance,
        response_schema_conformance,
        status_code_conformance,
    )

    with ux_server.client() as c:
        document = c.get("/openapi.json").json()
    schema = schemathesis.openapi.from_dict(document)
    checks = [response_schema_conformance, status_code_conformance, content_type_conformance,
              response_headers_conformance]

    def validate(method: str, path: str, response: httpx.Response, **path_parameters) -> None:
        operation = schema[path][method]
        case = operation.Case(path_parameters=path_parameters or None)
        response.request.read()  # multipart requests stream; schemathesis reads the request body
        case.validate_response(response, checks=checks)

    return document, validate


def test_published_schema_documents_the_payloads(ux_server):
    document, _ = _validator(ux_server)
    schemas = document["components"]["schemas"]
    for name in ("RegistrationOptions", "GeometryFile", "ViewSpec", "RegistrationResult", "ResultMetrics",
                 "ViewResult", "JobStatus", "JobSummary", "ProblemDetails", "Progress", "JobLinks"):
        assert name in schemas, name
    options = schemas["RegistrationOptions"]["properties"]
    assert options["configuration"]["enum"] == ["ap", "lat", "simultaneous", "ap_then_lat", "lat_then_ap"]
    assert options["starts"]["description"] and options["starts"]["maximum"] == 64
    assert "mm" in schemas["ViewSpec"]["properties"]["sid_mm"]["description"]
    assert schemas["RegistrationResult"].get("additionalProperties") is False  # closed: every field declared
    body = document["paths"]["/v1/registrations"]["post"]["requestBody"]["content"]["multipart/form-data"]
    parts = body["schema"]["properties"]
    assert parts["options"]["contentSchema"] == {"$ref": "#/components/schemas/RegistrationOptions"}
    assert {"$ref": "#/components/schemas/GeometryFile"} in [s.get("contentSchema") for s in parts["geometry"]["anyOf"]]
    result = document["paths"]["/v1/registrations/{job_id}/result"]["get"]["responses"]["200"]
    assert result["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/RegistrationResult"}
    operation_ids = {op["operationId"] for methods in document["paths"].values() for op in methods.values()}
    assert {"submit", "get_job", "list_jobs", "get_result", "cancel_job", "delete_job"} <= operation_ids


def test_the_documented_geometry_and_options_models_match_the_engine():
    from dsareg_engine.geometry.file import RigSpec
    from service.api.schemas import payloads as schemas

    assert issubclass(schemas.GeometryFile, RigSpec)  # the engine's model, documented: its fields written once
    assert not {"ViewSpec", "LatFromAp"} & set(vars(schemas))  # no second copy in the service
    assert set(schemas.GeometryFile.model_fields) == set(RigSpec.model_fields)
    example = Path(__file__).resolve().parents[3] / "examples" / "phantom" / "geometry.json"
    schemas.GeometryFile.model_validate_json(example.read_text())


@needs_engine
def test_real_responses_match_the_published_schema(ux_server, example_case, finished_jobs):
    _, validate = _validator(ux_server)
    with ux_server.client() as c:
        accepted = submit(c, example_case, options={**QUICK, "seed": 8})
        validate("POST", "/v1/registrations", accepted)
        job_id = accepted.json()["id"]
        validate("GET", "/v1/registrations/{job_id}", c.get(f"/v1/registrations/{job_id}"), job_id=job_id)
        wait_for(c, job_id, timeout=180)
        for job in (finished_jobs["animated"][-1], finished_jobs["quick"], {"id": job_id}):
            jid = job["id"]
            validate("GET", "/v1/registrations/{job_id}", c.get(f"/v1/registrations/{jid}"), job_id=jid)
            validate("GET", "/v1/registrations/{job_id}/result", c.get(f"/v1/registrations/{jid}/result"), job_id=jid)
        for running in finished_jobs["animated"][1:-1:max(1, len(finished_jobs["animated"]) // 5)]:
            # a running job's body as it was polled: validate it through the same schema
            response = httpx.Response(200, json=running, headers={"content-type": "application/json"},
                                      request=httpx.Request("GET", f"{ux_server.url}/v1/registrations/{running['id']}"))
            response.elapsed = datetime.timedelta(0)
            validate("GET", "/v1/registrations/{job_id}", response, job_id=running["id"])
        validate("GET", "/v1/registrations", c.get("/v1/registrations", params={"limit": 100}))
        # the validator has teeth: a result that breaks the documented types is caught
        broken = json.loads(json.dumps(finished_jobs["quick"]))
        broken["result"]["views"]["ap"]["dice"] = "high"
        response = httpx.Response(200, json=broken, headers={"content-type": "application/json"},
                                  request=httpx.Request("GET", f"{ux_server.url}/v1/registrations/{broken['id']}"))
        response.elapsed = datetime.timedelta(0)
        with pytest.raises(BaseException) as caught:
            validate("GET", "/v1/registrations/{job_id}", response, job_id=broken["id"])
        assert "violates schema" in "".join(traceback.format_exception(caught.value))
        validate("GET", "/v1/registrations/{job_id}", c.get("/v1/registrations/nope"), job_id="nope")
        bad = submit(c, example_case, options={"starts": 0})
        assert bad.status_code == 422
        validate("POST", "/v1/registrations", bad)
        validate("GET", "/healthz", c.get("/healthz"))
        validate("GET", "/readyz", c.get("/readyz"))


# ---- a client generated from the document ----------------------------------------------------


@needs_engine
def test_generated_client_talks_to_the_server(ux_server, finished_jobs, example_case, tmp_path):
    generator = shutil.which("openapi-python-client", path=str(Path(sys.executable).parent)) or shutil.which(
        "openapi-python-client")
    if generator is None:
        pytest.skip("openapi-python-client is not installed (pip install -e '.[test]')")
    with ux_server.client() as c:
        (tmp_path / "openapi.json").write_text(c.get("/openapi.json").text)
    env_path = f"{Path(sys.executable).parent}:{Path(generator).parent}"
    proc = subprocess.run([generator, "generate", "--path", str(tmp_path / "openapi.json"), "--meta", "none",
                           "--output-path", str(tmp_path / "dsareg_client")], capture_output=True, text=True,
                          timeout=180, check=False, cwd=tmp_path, env={"PATH": env_path, "HOME": str(tmp_path)})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    sys.path.insert(0, str(tmp_path))
    try:
        package = importlib.import_module("dsareg_client")
        get_job = importlib.import_module("dsareg_client.api.registrations.get_job")
        list_jobs = importlib.import_module("dsareg_client.api.registrations.list_jobs")
        get_result = importlib.import_module("dsareg_client.api.results.get_result")
        models = importlib.import_module("dsareg_client.models")
        client = package.Client(base_url=ux_server.url, raise_on_unexpected_status=True)
        quick = finished_jobs["quick"]
        status = get_job.sync(client=client, job_id=quick["id"])
        assert isinstance(status, models.JobStatus) and status.status.value == "succeeded"
        assert isinstance(status.result, models.RegistrationResult)
        assert status.result.metrics.converged in (True, False)
        assert len(status.result.mesh_to_world) == 4
        result = get_result.sync(client=client, job_id=quick["id"])
        assert isinstance(result, models.RegistrationResult)
        assert set(result.views.additional_properties) == {"ap", "lat"}
        assert 0.0 <= result.views["ap"].dice <= 1.0
        page = list_jobs.sync(client=client, limit=100)
        assert isinstance(page, models.JobList) and quick["id"] in [item.id for item in page.items]
        missing = get_job.sync_detailed(client=client, job_id="nope")
        assert missing.status_code == 404 and isinstance(missing.parsed, models.ProblemDetails)
        # the verdict through typed fields: a job with AP and LAT swapped runs (succeeded) but is not to be trusted
        assert status.result.verdict in list(models.Verdict) and status.verdict == status.result.verdict
        assert isinstance(status.result.metrics.confidence, models.Confidence)
        with ux_server.client() as c:
            # failed on its Dice (< 0.1) whether or not the mirror is fitted (2.3 CPU-s at 128 px): not fitted
            swapped = submit(c, example_case, options={**QUICK, "mirror_check": False},
                             names=("m.obj", "lat.png", "ap.png"),
                             files_override={"ap": example_case.lat_png, "lat": example_case.ap_png}).json()
        wait_for_typed = time.monotonic() + 180
        while (job := get_job.sync(client=client, job_id=swapped["id"])).status.value in ("queued", "running"):
            assert time.monotonic() < wait_for_typed, "the swapped job did not finish"
            time.sleep(0.3)
        assert job.status == models.JobStatusStatus.SUCCEEDED  # it ran ...
        assert job.verdict == models.Verdict.FAILED and job.result.verdict == models.Verdict.FAILED  # ... wrongly
        confidence = job.result.metrics.confidence
        assert confidence.verdict == models.Verdict.FAILED
        assert confidence.reasons and all(isinstance(reason, str) for reason in confidence.reasons)
        assert max(confidence.signals.dice.additional_properties.values()) < 0.5
        summary = next(i for i in list_jobs.sync(client=client, limit=100).items if i.id == swapped["id"])
        assert summary.verdict == models.Verdict.FAILED and summary.reasons == confidence.reasons
    finally:
        sys.path.remove(str(tmp_path))
        for name in [m for m in sys.modules if m == "dsareg_client" or m.startswith("dsareg_client.")]:
            del sys.modules[name]


# ---- offline docs in a real browser --------------------------------------------------------

CDN_HOSTS = ("cdn.jsdelivr.net", "unpkg.com", "fonts.googleapis.com", "fonts.gstatic.com", "cdn.redoc.ly",
             "validator.swagger.io", "fastapi.tiangolo.com")


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("headless Chromium not installed (Debian: apt-get install chromium; .ci/run installs it): "
                "the offline /docs test needs a real browser")


def _page_requests(net_log: Path, origin: str) -> tuple[list[str], list[str]]:
    """URLs the page asked for (initiator = the server's origin, or the navigation), and every URL."""
    data = json.loads(net_log.read_text())
    names = {value: key for key, value in data["constants"]["logEventTypes"].items()}
    page, every = [], []
    for event in data["events"]:
        params = event.get("params") or {}
        if names.get(event["type"]) != "URL_REQUEST_START_JOB" or "url" not in params:
            continue
        every.append(params["url"])
        if params.get("initiator") == origin or params["url"].startswith(origin):
            page.append(params["url"])
    return page, every


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_render_offline_in_chromium(ux_server, tmp_path, page):
    browser = _chromium()
    shot, net_log = tmp_path / "page.png", tmp_path / "net.json"
    common = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
              "--disable-background-networking", "--disable-component-update", "--disable-default-apps",
              f"--user-data-dir={tmp_path / 'profile'}",
              # every non-loopback request goes to a dead proxy: nothing can leave the machine
              "--proxy-server=http://127.0.0.1:9", "--window-size=1280,1400", "--virtual-time-budget=20000"]
    url = ux_server.url + page
    proc = subprocess.run([*common, f"--log-net-log={net_log}", f"--screenshot={shot}", url],
                          capture_output=True, text=True, timeout=120, check=False)
    assert shot.is_file(), proc.stderr[-2000:]
    dom = subprocess.run([*common, "--dump-dom", url], capture_output=True, text=True, timeout=120, check=False).stdout
    for text in ("Submit a registration job", "List jobs", "Job status", "Registration result"):
        assert text in dom, f"{page}: '{text}' not rendered"
    if page == "/docs":
        assert dom.count('class="opblock ') >= 10 or dom.count("opblock-summary") >= 10
    page_urls, every_url = _page_requests(net_log, ux_server.url)
    assert any(u.endswith("/openapi.json") for u in page_urls), page_urls
    outside = [u for u in page_urls if not u.startswith(ux_server.url)]
    assert not outside, f"the page asked for {outside}"
    assert not [u for u in every_url if any(host in u for host in CDN_HOSTS)], every_url
    # the screenshot is a rendered page, not a blank one
    from PIL import Image

    image = Image.open(shot).convert("L")
    colours = image.getcolors(maxcolors=1 << 16)
    assert colours is None or len(colours) > 50, "the screenshot is (nearly) blank"
    keep = Path("/tmp") / f"dsareg-docs{page.replace('/', '-')}.png"
    try:
        shutil.copyfile(shot, keep)
    except OSError:
        pass

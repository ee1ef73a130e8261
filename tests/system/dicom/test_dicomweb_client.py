"""The DICOMweb client and request model without a PACS (httpx.MockTransport)."""

from __future__ import annotations

import gzip
import json

import httpx
import pytest
from pydantic import ValidationError

from service.pacs.dicomweb import DicomwebClient, DicomwebRegistrationRequest, PacsError, PacsServer, configured_servers
from tests.support.time_bounds import allowed


def client(handler, **kwargs) -> DicomwebClient:
    return DicomwebClient(PacsServer("http://pacs/dicom-web"), transport=httpx.MockTransport(handler), backoff=0.0,
                          **kwargs)


def test_bounded_retries_then_success_or_failure():
    calls = []

    def flaky(request):
        calls.append(request.url.path)
        return httpx.Response(503 if len(calls) < 3 else 200, json=[])

    assert client(flaky, retries=2).search_instances("1.2", "1.3") == [] and len(calls) == 3
    calls.clear()
    with pytest.raises(PacsError) as info:
        client(flaky, retries=1).search_instances("1.2", "1.3")
    assert (info.value.status, info.value.attempts, info.value.step) == (503, 2, "search instances (QIDO-RS)")
    assert "http://pacs/dicom-web" in str(info.value)

    def not_found(request):
        calls.append(1)
        return httpx.Response(404, text="no such series")

    calls.clear()
    with pytest.raises(PacsError) as info:
        client(not_found, retries=5).retrieve_series("1.2", "1.3")
    assert info.value.status == 404 and info.value.attempts == 1 and len(calls) == 1  # 4xx: not retried
    assert "no such series" in info.value.detail


def test_multipart_gzip_and_byte_cap():
    def handler(request):
        if request.url.path.endswith("/instances/1.4"):
            body = (b"--XyZ\r\nContent-Type: application/dicom\r\n\r\nfirst\r\n"
                    b"--XyZ\r\nContent-Type: application/dicom\r\n\r\nsec\r\n--ond\r\n--XyZ--\r\n")
            return httpx.Response(200, content=gzip.compress(body), headers={
                "Content-Type": 'multipart/related; type="application/dicom"; boundary=XyZ', "Content-Encoding": "gzip"})
        return httpx.Response(200, content=b"\x00" * 4096, headers={"Content-Type": "application/dicom"})

    with pytest.raises(PacsError, match="expected one instance, got 2"):
        client(handler).retrieve_instance("1.2", "1.3", "1.4")
    assert client(handler).retrieve_series("1.2", "1.5") == [b"\x00" * 4096]
    with pytest.raises(PacsError, match="exceeds 1000 bytes"):
        client(handler, max_bytes=1000).retrieve_series("1.2", "1.5")


def test_stow_reports_refused_instances():
    def handler(request):
        assert request.headers["content-type"].startswith('multipart/related; type="application/dicom"; boundary=')
        return httpx.Response(202, json={"00081198": {"vr": "SQ", "Value": [{"00081197": {"vr": "US", "Value": [272]}}]},
                                         "00081199": {"vr": "SQ", "Value": [
                                             {"00081155": {"vr": "UI", "Value": ["1.2.3"]}}]}})

    with pytest.raises(PacsError, match=r"1 instance\(s\) refused \(failure reasons \['272'\]\)"):
        client(handler).store("1.2", [b"a", b"b"])


def test_request_model_checks_uids_frames_and_refuses_credentials():
    base = {"url": "http://pacs/dicom-web", "study_uid": "1.2.840.1", "ap": {"series_uid": "1.2.3"},
            "lat": {"series_uid": "1.2.4", "frame": 3}, "volume": {"series_uid": "1.2.5"}}
    request = DicomwebRegistrationRequest.model_validate({"source": {"dicomweb": base}})
    assert request.store_results and request.source.dicomweb.frames == (None, 3)
    per_view = {**base, "ap": {"series_uid": "1.2", "frame": 1}, "lat": {"series_uid": "1.2.4", "frame": "minip"}}
    assert DicomwebRegistrationRequest.model_validate(
        {"source": {"dicomweb": per_view}}).source.dicomweb.frames == (1, "minip")  # each view its own frame
    for bad in ({"study_uid": "1.2/../x"}, {"study_uid": "1.02.3"}, {"ap": {"series_uid": "1.2", "frame": -1}},
                {"password": "x"}, {"volume": {"series_uid": "1." + "1" * 70}}):
        with pytest.raises(ValidationError):
            DicomwebRegistrationRequest.model_validate({"source": {"dicomweb": {**base, **bad}}})


def test_configured_servers_from_settings():
    from service.settings import ServiceSettings

    settings = ServiceSettings(dicomweb_servers=json.dumps(
        [{"url": "http://a/dicom-web/", "username": "u", "password": "p"}, "http://b/wado"]))
    servers = configured_servers(settings)
    assert set(servers) == {"http://a/dicom-web", "http://b/wado"}
    assert servers["http://a/dicom-web"].auth is not None and servers["http://b/wado"].auth is None


def test_a_trickling_pacs_holds_the_client_no_longer_than_the_jobs_budget():
    """A real server that answers one byte every 0.3 s (each read well within the 1 s timeout; before the budget,
    each attempt lasted 10 timeouts and was retried): the job's 2.5 s PACS budget ends the fetch, clearly."""
    import time

    from service.pacs.dicomweb import PacsBudget
    from tests.support.faults_kit import TricklingHttpServer

    server = TricklingHttpServer(interval_s=0.3)
    budget = PacsBudget(2.5)
    started = time.monotonic()
    try:
        with DicomwebClient(PacsServer(server.url), timeout=1.0, retries=2, backoff=0.1, budget=budget) as pacs:
            with pytest.raises(PacsError) as failed:
                pacs.search_instances("1.2.3", "1.2.4")
        took = time.monotonic() - started
    finally:
        server.close()
    assert took <= 2.5 + allowed(1.0), took  # the budget, and at most one read timeout past it
    assert "DSAREG_PACS_DEADLINE_SECONDS" in str(failed.value) and failed.value.step.startswith("search instances")
    assert budget.remaining() <= 0.0  # spent: a later request of the same job fails at once
    with DicomwebClient(PacsServer(server.url), timeout=1.0, budget=budget) as pacs, pytest.raises(PacsError):
        pacs.search_instances("1.2.3", "1.2.4")

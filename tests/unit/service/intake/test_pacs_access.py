"""A PACS-access policy per API key (issue 43 item 5): with keys on, a key may have fetched by reference only the
peers and studies its DSAREG_PACS_ACCESS entry grants; a key without one may fetch none (403)."""

from __future__ import annotations

import asyncio
import json

import pytest

from service.api.handlers import refusal_problem
from service.intake.context import IntakeContext, close_intake
from service.intake.pacs_access import AccessDenied, parse_pacs_access
from service.intake.reference import parse_reference, submit_reference
from service.jobs.executor import NoExecutor
from service.settings import ServiceSettings, hash_api_key

PACS, OTHER = "http://pacs.example:8042/dicom-web", "http://other.example/dicom-web"
RADIOLOGY, RESEARCH = "k-radiology-desk", "k-research-bench"
ROOT = "1.2.826.0.1.3680043.8.498."


def _request(url: str = PACS, study_uid: str = ROOT + "7") -> str:
    source = {"url": url, "study_uid": study_uid, "ap": {"series_uid": "1.2.3.1"}, "lat": {"series_uid": "1.2.3.2"},
              "volume": {"series_uid": "1.2.3.3"}}
    return json.dumps({"source": {"dicomweb": source}, "options": {}})


def _who(key: str) -> str:
    return "key:" + hash_api_key(key)[:16]


@pytest.fixture()
def intake(tmp_path):
    policy = {hash_api_key(RADIOLOGY): {"peers": [PACS + "/"], "studies": [ROOT]}}
    settings = ServiceSettings(data_dir=tmp_path, dicomweb_servers=[PACS, OTHER], min_free_bytes=0,
                               api_keys=f"{RADIOLOGY},{RESEARCH}", pacs_access=json.dumps(policy))
    ctx = IntakeContext.open(settings, lambda s, store: NoExecutor(), validate=False)
    yield ctx
    close_intake(ctx)


def _submit(ctx, who: str, text: str):
    return asyncio.run(submit_reference(ctx, parse_reference(text), who, None))


def test_a_key_pulls_only_what_its_policy_grants(intake):
    assert _submit(intake, _who(RADIOLOGY), _request()).created
    for text, field in ((_request(study_uid="1.2.3.4"), "source.dicomweb.study_uid"),
                        (_request(url=OTHER), "source.dicomweb.url")):
        with pytest.raises(AccessDenied) as caught:
            _submit(intake, _who(RADIOLOGY), text)
        assert caught.value.field == field
    with pytest.raises(AccessDenied) as caught:  # no entry, no "*": default deny
        _submit(intake, _who(RESEARCH), _request())
    assert "DSAREG_PACS_ACCESS" in caught.value.detail and refusal_problem(caught.value).status == 403


def test_every_key_entry_and_no_policy_without_keys(tmp_path):
    open_everything = ServiceSettings(data_dir=tmp_path / "a", dicomweb_servers=[PACS], min_free_bytes=0,
                                      api_keys=RESEARCH, pacs_access='{"*": {"peers": ["*"]}}')
    no_keys = ServiceSettings(data_dir=tmp_path / "b", dicomweb_servers=[PACS], min_free_bytes=0)
    for settings, who in ((open_everything, _who(RESEARCH)), (no_keys, "anonymous")):
        ctx = IntakeContext.open(settings, lambda s, store: NoExecutor(), validate=False)
        try:
            assert _submit(ctx, who, _request(study_uid="1.2.3.4")).created
        finally:
            close_intake(ctx)


@pytest.mark.parametrize("value, says", [
    ("{not json", "not valid JSON"), ('{"abc": {"peers": ["*"]}}', "SHA-256 hex digest"),
    ('{"*": {"studies": []}}', "'peers'"), ('{"*": {"peers": "PACS"}}', "peers must be a list"),
])
def test_a_malformed_policy_is_refused_naming_the_entry(value, says):
    with pytest.raises(ValueError, match=says):
        parse_pacs_access(value)


def test_a_dimse_reference_is_held_to_the_same_policy(tmp_path):
    """The DIMSE pull (``source.dimse``: C-MOVE / C-GET from a configured peer) goes through the same check as a
    DICOMweb reference: the key's peers are AE titles, its studies UID roots."""
    peers = [{"ae_title": title, "host": "127.0.0.1", "port": 11112 + n} for n, title in enumerate(("ARCHIVE", "CATH"))]
    policy = {hash_api_key(RADIOLOGY): {"peers": ["ARCHIVE"], "studies": [ROOT]}}
    settings = ServiceSettings(data_dir=tmp_path, dicom_peers=peers, min_free_bytes=0,
                               api_keys=f"{RADIOLOGY},{RESEARCH}", pacs_access=json.dumps(policy))

    def dimse(peer: str = "ARCHIVE", study_uid: str = ROOT + "7") -> str:
        source = {"peer": peer, "study_uid": study_uid, "ap": {"series_uid": "1.2.3.1"},
                  "lat": {"series_uid": "1.2.3.2"}, "volume": {"series_uid": "1.2.3.3"}}
        return json.dumps({"source": {"dimse": source}, "options": {}})

    ctx = IntakeContext.open(settings, lambda s, store: NoExecutor(), validate=False)
    try:
        assert _submit(ctx, _who(RADIOLOGY), dimse()).created
        for text, who, field in ((dimse(peer="CATH"), _who(RADIOLOGY), "source.dimse.peer"),
                                 (dimse(study_uid="1.2.3.4"), _who(RADIOLOGY), "source.dimse.study_uid"),
                                 (dimse(), _who(RESEARCH), "source.dimse.peer")):  # no entry: default deny
            with pytest.raises(AccessDenied) as caught:
                _submit(ctx, who, text)
            assert caught.value.field == field and refusal_problem(caught.value).status == 403
    finally:
        close_intake(ctx)

"""A submission by PACS reference (service/intake/reference.py): the JSON request checked, the PACS known.

Each refusal names the field at fault; a known DICOMweb server becomes the job's one input and the request
under the same key is the same job."""

from __future__ import annotations

import asyncio
import json

import pytest

from service.intake.context import IntakeContext, close_intake
from service.intake.reference import parse_reference, stored_reference, submit_reference
from service.intake.refusals import InvalidInput
from service.jobs.executor import NoExecutor
from service.settings import ServiceSettings

PACS = "http://pacs.example:8042/dicom-web"


def _request(url: str = PACS, study_uid: str = "1.2.3", **more) -> dict:
    source = {"url": url, "study_uid": study_uid, "ap": {"series_uid": "1.2.3.1"}, "lat": {"series_uid": "1.2.3.2"},
              "volume": {"series_uid": "1.2.3.3"}}
    return {"source": {"dicomweb": source}, "options": {}, **more}


@pytest.fixture()
def intake(tmp_path):
    settings = ServiceSettings(data_dir=tmp_path, dicomweb_servers=[PACS], min_free_bytes=0)
    ctx = IntakeContext.open(settings, lambda s, store: NoExecutor(), validate=False)
    yield ctx
    close_intake(ctx)


@pytest.mark.parametrize("text, field", [
    ("{broken", "body"),
    ('{"options": {}}', "source"),
    (json.dumps(_request(study_uid="1.2.3/../../x")), "source.dicomweb.study_uid"),
    (json.dumps({"source": {"dimse": {"peer": "PACS"}}}), "source.dimse"),
])
def test_a_malformed_request_is_refused_naming_the_field(text, field):
    with pytest.raises(InvalidInput) as caught:
        parse_reference(text)
    assert (caught.value.field or "").startswith(field), caught.value.field


def test_a_server_not_configured_here_is_refused(intake):
    reference = parse_reference(json.dumps(_request(url="http://elsewhere.example/dicom-web")))
    with pytest.raises(InvalidInput) as caught:
        stored_reference(intake, reference)
    assert caught.value.field == "source.dicomweb.url" and "DSAREG_DICOMWEB_SERVERS" in caught.value.detail


def test_a_known_server_becomes_the_jobs_one_input_and_a_replay_is_the_same_job(intake):
    reference = parse_reference(json.dumps(_request(url=PACS + "/")))
    first = asyncio.run(submit_reference(intake, reference, "anonymous", "k"))
    again = asyncio.run(submit_reference(intake, reference, "anonymous", "k"))
    assert first.created and (again.job.id, again.created) == (first.job.id, False)
    [item] = first.job.inputs
    stored = json.loads(intake.blobs.read(item.sha256))
    assert item.role == "dicomweb" and stored["source"]["dicomweb"]["url"] == PACS

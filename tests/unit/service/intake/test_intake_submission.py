"""Submission as a service layer (service/intake/submission.py): typed files in, a job or a refusal out.

A real intake on a temporary SQLite store and blob folder, without validator processes (the inputs are
not parsed: the refusals here come before that) and an executor that records what it was handed."""

from __future__ import annotations

import asyncio
import io

import pytest

from service.intake.context import IntakeContext, close_intake
from service.intake.refusals import IdempotencyConflict, InvalidInput, Overloaded, QuotaExceeded
from service.intake.submission import FileRequest, Upload, check_queue, checked_roles, parse_options_json, submit_files
from service.jobs.executor import NoExecutor
from service.settings import ServiceSettings

MESH = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


class _Recording(NoExecutor):
    def __init__(self):
        self.submitted: list[str] = []

    def submit(self, job_id: str) -> None:
        self.submitted.append(job_id)


@pytest.fixture()
def intake(tmp_path):
    settings = ServiceSettings(data_dir=tmp_path, queue_limit=3, queue_limit_per_key=2, min_free_bytes=0)
    ctx = IntakeContext.open(settings, lambda s, store: _Recording(), validate=False)
    yield ctx
    close_intake(ctx)


def _files(image: bytes = b"ap-image", **extra: list[Upload]) -> dict[str, list[Upload]]:
    files = {"mesh": [Upload("vessels.obj", io.BytesIO(MESH), len(MESH))],
             "ap": [Upload("ap.png", io.BytesIO(image), len(image))],
             "lat": [Upload("lat.png", io.BytesIO(b"lat-image"), 9)]}
    return {**files, **extra}


def _submit(ctx: IntakeContext, files, who: str = "anonymous", key: str | None = None, options=None):
    request = FileRequest(checked_roles(files), None, options or parse_options_json(None))
    return asyncio.run(submit_files(ctx, request, who, key))


def test_files_become_a_queued_job_handed_to_the_executor(intake):
    submitted = _submit(intake, _files())
    job = intake.store.get(submitted.job.id)
    assert submitted.created and job.status == "queued" and intake.executor.submitted == [job.id]
    assert [item.role for item in job.inputs] == ["mesh", "ap", "lat"]
    assert intake.blobs.read(job.inputs[0].sha256) == MESH and job.input_bytes == len(MESH) + 8 + 9
    assert [item.suffix for item in job.inputs] == [".obj", ".png", ".png"]


def test_the_same_request_under_the_same_key_is_the_same_job_and_another_is_a_conflict(intake):
    first = _submit(intake, _files(), key="k1")
    again = _submit(intake, _files(), key="k1")
    assert (again.job.id, again.created) == (first.job.id, False) and intake.executor.submitted == [first.job.id]
    with pytest.raises(IdempotencyConflict) as caught:
        _submit(intake, _files(image=b"another image"), key="k1")
    assert caught.value.job_id == first.job.id and caught.value.field == "Idempotency-Key"


def test_a_full_queue_is_overloaded_and_an_owner_over_its_share_is_over_quota(intake):
    for k in range(2):
        _submit(intake, _files(image=b"image %d" % k), who="key:alpha")
    with pytest.raises(QuotaExceeded) as quota:
        _submit(intake, _files(image=b"image 2"), who="key:alpha")
    assert quota.value.retry_after_s == 30 and quota.value.kind == "too-many-requests"
    _submit(intake, _files(image=b"image 3"), who="key:beta")
    with pytest.raises(Overloaded) as full:
        asyncio.run(check_queue(intake, "key:gamma"))
    assert not isinstance(full.value, QuotaExceeded) and full.value.kind == "queue-full"
    assert "3 queued" in full.value.detail and len(intake.executor.submitted) == 3


@pytest.mark.parametrize("change, field, needle", [
    ({"lat": []}, "lat", "required"),
    ({"volume": [Upload("v.nii", io.BytesIO(b"x"), 1)]}, "mesh", "not both"),
    ({"mesh": []}, "mesh", "3D model is required"),
    ({"ap": [Upload(f"ap{k}.png", io.BytesIO(b"x"), 1) for k in range(3)]}, "ap", "one image file"),
])
def test_roles_are_checked_by_name(change, field, needle):
    files = {role: uploads for role, uploads in _files(**change).items() if uploads}
    with pytest.raises(InvalidInput) as caught:
        checked_roles(files)
    assert caught.value.field == field and needle in caught.value.detail


def test_an_empty_file_is_refused_naming_its_role_and_nothing_is_queued(intake):
    with pytest.raises(InvalidInput) as caught:
        _submit(intake, _files(image=b""))
    assert (caught.value.field, caught.value.detail) == ("ap", "the file is empty")
    assert intake.store.queued_count() == 0 and intake.executor.submitted == []

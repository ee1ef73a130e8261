"""``/v1/registrations``: submit, list, status, cancel, delete."""

from __future__ import annotations

import logging
from urllib.parse import quote

from fastapi import Query, Request
from fastapi.responses import JSONResponse, Response

from ...pacs.dimse.export import dimse_source
from ...problems import Problem, problem_responses
from ...storage.interfaces import Jobs
from ...storage.store import REVIEW_FILTERS, STATUSES, decode_cursor
from ..deps import Ctx, JobsStore, OwnedJob, Principal
from ..submit.accept import RETRY_AFTER_QUEUED, submit_by_reference, submit_form
from ..submit.forms import read_form
from ..submit.parts import MAX_VOLUME_FILES, idempotency_key
from ..openapi import resource_router
from ..schemas.jobs import JobList, JobStatus, previous_link_header, status_body, summary_body

log = logging.getLogger("dsareg.service")

router = resource_router("registrations")

SUBMIT_DOC = {
    "status_code": 202,
    "response_model": JobStatus,
    "summary": "Submit a registration job",
    "description": (
        "multipart/form-data with `mesh` (or `volume`), `ap`, `lat`, optional `geometry`, `options` and "
        "`callback_url`; or application/json with the inputs by DICOMweb reference (`DicomwebRegistrationRequest`). "
        "Inputs are fully parsed before the job is accepted. Answers 202 with `Location` of the job. "
        "A job that `succeeded` ran to the end; whether to trust its pose is `verdict` (ok / check / failed). "
        "With an `Idempotency-Key` header, repeating the same request returns the original job (200), "
        "while reusing the key with a different request is a 409."
    ),
    "openapi_extra": {
        # the body's schema is written once, in service/api/schemas/payloads.py (multipart_schema, document)
        "requestBody": {"required": True},
        "parameters": [{"name": "Idempotency-Key", "in": "header", "required": False,
                        "schema": {"type": "string", "minLength": 1, "maxLength": 255, "pattern": r"\S"},
                        "description": "Makes retries of the same submission safe. 1 to 255 characters, at "
                                       "least one of them not white space; otherwise 400 (field "
                                       "`Idempotency-Key`)."}],
    },
    "responses": {
        200: {"description": "Idempotent replay: the job created earlier with this key.", "model": JobStatus},
        202: {"description": "Accepted; poll the Location.", "headers": {
            "Location": {"description": "The job's URL.", "schema": {"type": "string"}},
            "Retry-After": {"description": "Seconds before the first poll.", "schema": {"type": "integer"}}}},
        **problem_responses(400, 401, 403, 408, 409, 413, 415, 422, 429, 503, 507),
    },
}


@router.post("/v1/registrations", **SUBMIT_DOC)
async def submit(request: Request, ctx: Ctx, who: Principal) -> Response:
    key = idempotency_key(request)
    content_type = request.headers.get("content-type", "")
    if content_type.lower().startswith("application/json"):  # inputs by DICOMweb reference
        return await submit_by_reference(ctx, request, who, key)
    if not content_type.lower().startswith("multipart/form-data"):
        raise Problem(415, "send multipart/form-data with the files mesh (or volume), ap and lat",
                      accepted="multipart/form-data")
    form = await read_form(request, max_files=MAX_VOLUME_FILES + 8, max_fields=20)
    try:
        return await submit_form(ctx, form, who, key)
    finally:
        await form.close()


def list_page(jobs: Jobs, who: str, status: str | None, limit: int, cursor: str | None,
              review: str | None = None, q: str | None = None) -> dict:
    if status is not None and status not in STATUSES:
        raise Problem(422, f"unknown status '{status[:20]}'", field="status", accepted=", ".join(STATUSES))
    if review is not None and review not in REVIEW_FILTERS:
        raise Problem(422, f"unknown review state '{review[:20]}'", field="review", accepted=", ".join(REVIEW_FILTERS))
    if cursor:
        try:
            decode_cursor(cursor)
        except Exception:  # noqa: BLE001
            raise Problem(400, "the cursor is not valid; use next_cursor from a previous page", field="cursor") from None
    q = q.strip() if q else None
    records, next_cursor = jobs.list(owner=who, status=status, limit=limit, cursor=cursor, review=review,
                                     q=q or None)
    next_link = None
    if next_cursor:
        next_link = (f"/v1/registrations?limit={limit}&cursor={next_cursor}" + (f"&status={status}" if status else "")
                     + (f"&review={review}" if review else "") + (f"&q={quote(q, safe='')}" if q else ""))
    return {"items": [summary_body(r) for r in records], "next_cursor": next_cursor, "links": {"next": next_link}}


@router.get("/v1/registrations", response_model=JobList, summary="List jobs (newest first)",
            responses=problem_responses(400, 401, 422))
def list_jobs(
    jobs: JobsStore,
    status: str | None = Query(None, description="Only jobs in this state.",
                               json_schema_extra={"enum": list(STATUSES)}),
    limit: int = Query(20, ge=1, le=100, description="Page size."),
    cursor: str | None = Query(
        None, max_length=200,
        description="Opaque paging token: exactly the `next_cursor` of the previous page (URL-safe base64 "
                    "without padding, at most 200 characters). Any other value → 400 with field `cursor`."),
    review: str | None = Query(None, description="Only jobs never reviewed (none) or whose latest review is "
                                                 "approved / rejected.", json_schema_extra={"enum": list(REVIEW_FILTERS)}),
    q: str | None = Query(None, max_length=64,
                          description="Only jobs whose case matches: part of the patient ID or name, study date "
                                      "(YYYY-MM-DD), study description or accession number (case-insensitive). "
                                      "Never logged."),
    *,
    who: Principal,
) -> Response:
    return JSONResponse(list_page(jobs, who, status, limit, cursor, review, q))


@router.get("/v1/registrations/{job_id}", response_model=JobStatus, summary="Job status",
            responses=problem_responses(401, 404))
def get_job(ctx: Ctx, job: OwnedJob) -> Response:
    headers = {"Retry-After": RETRY_AFTER_QUEUED} if job.status in ("queued", "running") else {}
    body = status_body(job)
    if (source := dimse_source(job, ctx.blobs.read)) is not None:
        body["source"] = source
    return JSONResponse(body, headers={**headers, **previous_link_header(job)})


@router.post("/v1/registrations/{job_id}/cancel", response_model=JobStatus, summary="Cancel a job",
             description="A queued job is canceled at once (200); a running job stops at its next progress check "
                         "(202, poll until status is canceled). A finished job gives 409.",
             responses={202: {"description": "Cancellation requested; the worker stops shortly.", "model": JobStatus},
                        **problem_responses(401, 404, 409)})
def cancel_job(ctx: Ctx, jobs: JobsStore, job: OwnedJob) -> Response:
    if job.status in ("succeeded", "failed"):
        raise Problem(409, f"the job already finished ({job.status}); nothing to cancel", kind="job-finished",
                      extra={"job_status": job.status})
    updated = jobs.request_cancel(job.id) or job
    ctx.executor.cancel(job.id)
    code = 202 if updated.status == "running" else 200
    return JSONResponse(status_body(updated), status_code=code, headers=previous_link_header(updated))


@router.delete("/v1/registrations/{job_id}", status_code=204, summary="Delete a job and its files",
               response_class=Response, responses={204: {"description": "Deleted."}, **problem_responses(401, 404)})
def delete_job(ctx: Ctx, jobs: JobsStore, job: OwnedJob) -> Response:
    if job.status == "running":
        jobs.request_cancel(job.id)
        ctx.executor.cancel(job.id)
    orphans = jobs.delete(job.id)
    ctx.blobs.delete(orphans, min_age_seconds=0.0)
    ctx.blobs.remove_job_work(job.id)
    log.info("job %s: deleted", job.id)
    return Response(status_code=204)

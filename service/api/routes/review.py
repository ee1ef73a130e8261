"""``POST /v1/registrations/{job_id}/review``: a person approves or rejects a finished job;
``GET /v1/registrations/{job_id}/audit``: the job's audit log.

The latest review is on the job (``review``); every review is a ``reviewed`` event in the job's
audit log (``job_events``), so a later review replaces the shown one without losing the earlier.
"""

from __future__ import annotations

import logging

from fastapi.responses import JSONResponse, Response

from ...problems import Problem, problem_responses
from ..deps import OwnedJob, Principal, ReviewStore
from ..openapi import resource_router
from ..schemas.jobs import JobStatus, status_body
from ..schemas.review import AuditLog, ReviewRequest, audit_event, reviewer_label

log = logging.getLogger("dsareg.service")

router = resource_router("registrations")


@router.post(
    "/v1/registrations/{job_id}/review", response_model=JobStatus, summary="Approve or reject a finished job",
    description="Records a person's decision (`approved` / `rejected`) and comment on a finished job "
                "(succeeded, failed or canceled) and answers the job with its `review`. A later review replaces "
                "the earlier one on the job; each stays in the job's audit log. A queued or running job gives 409.",
    responses=problem_responses(400, 401, 404, 408, 409, 422),
)
def review_job(body: ReviewRequest, reviews: ReviewStore, job: OwnedJob, who: Principal) -> Response:
    if job.status in ("queued", "running"):
        raise Problem(409, f"the job has not finished ({job.status}); review it once it has", kind="job-not-finished",
                      extra={"job_status": job.status})
    reviewed = reviews.review(job.id, body.decision, body.comment, reviewer_label(who))
    if reviewed is None:  # deleted meanwhile (a finished job never becomes unfinished)
        raise Problem(404, f"no registration job with id '{job.id}'", kind="job-not-found")
    log.info("job %s: reviewed (%s)", job.id, body.decision)
    return JSONResponse(status_body(reviewed))


@router.get(
    "/v1/registrations/{job_id}/audit", response_model=AuditLog, summary="The job's audit log",
    description="Every recorded event of the job, oldest first: submission, claims, the end state, reviews and the "
                "PACS export held for review, each with who did it (an API key's label, never the key) and details.",
    responses=problem_responses(401, 404),
)
def get_audit(reviews: ReviewStore, job: OwnedJob) -> Response:
    items = [audit_event(row, job.owner) for row in reviews.events(job.id)]
    return JSONResponse(AuditLog(job_id=job.id, items=items).model_dump(mode="json"))

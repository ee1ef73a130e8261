"""A submission request → the intake → its HTTP answer: 202 with the new job, 200 for an idempotent replay.

The intake's refusals become problem+json in :mod:`service.api.handlers`.
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse

from ...intake.reference import parse_reference, submit_reference
from ...intake.submission import FileRequest, Submitted, checked_roles, submit_files
from ..deps import ServiceContext
from ..schemas.jobs import previous_link_header, status_body
from .forms import read_body
from .parts import form_callback_url, form_files, form_geometry_and_options

RETRY_AFTER_QUEUED = "2"
MAX_REFERENCE_BYTES = 64 * 1024


def answer(submitted: Submitted) -> JSONResponse:
    """202 with the job as every submission answers it (only the links that lead somewhere now), or 200 with
    the job an equal request made earlier under the same Idempotency-Key."""
    job = submitted.job
    location = {"Location": f"/v1/registrations/{job.id}"}
    if not submitted.created:
        return JSONResponse(status_body(job), status_code=200, headers={**location, **previous_link_header(job)})
    return JSONResponse(status_body(job), status_code=202,
                        headers={**location, "Retry-After": RETRY_AFTER_QUEUED, **previous_link_header(job)})


async def accept_files(ctx: ServiceContext, request: FileRequest, who: str, key: str | None) -> JSONResponse:
    """Files → the intake → the answer; the stored bytes of a new job counted (``dsareg_upload_bytes``)."""
    submitted = await submit_files(ctx, request, who, key)
    if submitted.created:
        ctx.uploads.inc(submitted.job.input_bytes)
    return answer(submitted)


async def submit_form(ctx: ServiceContext, form: Any, who: str, key: str | None) -> JSONResponse:
    """A parsed multipart form → 202 with the new job (or 200/409 for an Idempotency-Key replay)."""
    files = checked_roles(form_files(form))
    geometry, options = await asyncio.to_thread(form_geometry_and_options, form)  # JSON parsing off the event loop
    request = FileRequest(files, geometry, options, callback_url=form_callback_url(ctx, form))
    return await accept_files(ctx, request, who, key)


async def submit_by_reference(ctx: ServiceContext, request: Request, who: str, key: str | None) -> JSONResponse:
    """A JSON body naming the inputs on a PACS (DICOMweb or DIMSE) → 202 with the new job (or a replay)."""
    body = await read_body(request, MAX_REFERENCE_BYTES)  # streamed: never buffered past the limit
    reference = parse_reference(body.decode("utf-8", errors="replace"))
    return answer(await submit_reference(ctx, reference, who, key))

"""``GET /v1/registrations/{id}/events``: the job's progress as Server-Sent Events (text/event-stream).

The stream polls the job store (workers write progress there, in both topologies) every
``POLL_SECONDS``: a ``progress`` event each time the status or progress changes (the first one at
once), a comment every ``KEEP_ALIVE_SECONDS`` so proxies keep the connection, and one ``end`` event
with the job summary when the job is succeeded, failed or canceled (or ``gone`` when it was deleted);
then the server closes the stream. A client that disconnects ends the stream within one poll.
"""

from __future__ import annotations

import json
import time
from collections.abc import AsyncIterator
from typing import Any

import anyio
from fastapi import Request
from fastapi.responses import StreamingResponse

from ...problems import problem_responses
from ...storage.store import JobRecord
from ..deps import Ctx, OwnedJob, ServiceContext
from ..openapi import resource_router
from ..schemas.jobs import progress_event, summary_body

router = resource_router("registrations")

POLL_SECONDS = 0.5
KEEP_ALIVE_SECONDS = 15.0
RETRY_MILLISECONDS = 2000
FINAL = ("succeeded", "failed", "canceled")
OPEN_STREAMS = "event_streams_open"
"""Key in ``ServiceContext.extra``: streams open now (``dsareg_event_streams_open`` in /metrics)."""

EVENTS_DOC: dict[str, Any] = {
    "summary": "Follow a job's progress (Server-Sent Events)",
    "description": (
        "`text/event-stream`. Events: `progress` (data: `JobProgressEvent`, JSON) at once and whenever the status "
        "or progress changes; `end` (data: `JobSummary`, with `status` and `verdict`) once the job is succeeded, "
        "failed or canceled, after which the server closes the stream; `gone` (data: `{\"id\"}`) if the job is "
        f"deleted meanwhile. Comment lines (`: keep-alive`) every {KEEP_ALIVE_SECONDS:g} s. The store is polled "
        f"every {POLL_SECONDS:g} s. Same API key and ownership rules as `GET /v1/registrations/{{id}}`."),
    "response_class": StreamingResponse,
    "responses": {
        200: {"description": "The event stream.", "content": {"text/event-stream": {
            "schema": {"type": "string", "description": "SSE frames: `event: progress|end|gone`, `id: <n>`, `data: <JSON>`."},
            "x-event-data": {"progress": {"$ref": "#/components/schemas/JobProgressEvent"},
                             "end": {"$ref": "#/components/schemas/JobSummary"}},
            "example": 'retry: 2000\n\nid: 1\nevent: progress\ndata: {"id": "…", "status": "running", '
                       '"progress": {"stage": "ap+lat:1/4", "iteration": 3, "loss": 0.08, "fraction": 0.05}}\n\n'
                       'id: 7\nevent: end\ndata: {"id": "…", "status": "succeeded", "verdict": "ok", …}\n\n'}}},
        **problem_responses(401, 404),
    },
}


def frame(event: str, data: dict[str, Any], number: int) -> bytes:
    """One SSE frame: ``id``, ``event`` and the JSON ``data`` on one line."""
    return f"id: {number}\nevent: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


async def _read(ctx: ServiceContext, job_id: str) -> JobRecord | None:
    return await anyio.to_thread.run_sync(ctx.jobs.get, job_id)


async def job_events(request: Request, ctx: ServiceContext, job: JobRecord) -> AsyncIterator[bytes]:
    """The frames of one stream (see the module's text); stops on the job's end or the client's disconnect."""
    ctx.extra[OPEN_STREAMS] = ctx.extra.get(OPEN_STREAMS, 0) + 1
    try:
        yield f"retry: {RETRY_MILLISECONDS}\n\n".encode()
        number, last, quiet_since = 0, None, time.monotonic()
        current: JobRecord | None = job
        while current is not None and current.status not in FINAL:
            state = progress_event(current)
            if state != last:
                number, last, quiet_since = number + 1, state, time.monotonic()
                yield frame("progress", state, number)
            elif time.monotonic() - quiet_since >= KEEP_ALIVE_SECONDS:
                quiet_since = time.monotonic()
                yield b": keep-alive\n\n"
            await anyio.sleep(POLL_SECONDS)
            if await request.is_disconnected():
                return
            current = await _read(ctx, job.id)
        if current is None:
            yield frame("gone", {"id": job.id}, number + 1)
        else:
            yield frame("end", summary_body(current), number + 1)
    finally:
        ctx.extra[OPEN_STREAMS] -= 1


@router.get("/v1/registrations/{job_id}/events", **EVENTS_DOC)
def job_event_stream(request: Request, ctx: Ctx, job: OwnedJob) -> StreamingResponse:
    headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
    return StreamingResponse(job_events(request, ctx, job), media_type="text/event-stream", headers=headers)

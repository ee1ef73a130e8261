"""API side of the DICOM integration: submission by DICOMweb reference and the DICOM results.

* ``POST /v1/registrations`` with ``Content-Type: application/json`` and a body
  ``{"source": {"dicomweb": {...}}, "options": {...}, "store_results": true}``
  (see :class:`service.dicomweb.DicomwebRegistrationRequest`). The reference is checked
  (UID syntax, the URL is one of ``settings.dicomweb_servers``, options) and stored as the
  job's only input; the worker fetches the images (``service/dicom_jobs.py``).
* ``GET /v1/registrations/{id}/dicom/{reg,overlay_ap,overlay_lat,loss}.dcm``.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import time
from typing import Literal

from fastapi import Depends, FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import ValidationError

from .dicomweb import DicomwebRegistrationRequest, resolve_server
from .limits import check_options, parse_json_part
from .models import job_status
from .problems import Problem, problem_responses
from .store import ConflictError, InputFile, JobRecord, new_job_id

log = logging.getLogger("dsareg.service")

MAX_REFERENCE_BYTES = 64 * 1024
DICOM_FILES = ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm")


def _field(loc) -> str:
    return ".".join(str(part) for part in loc)


async def submit_by_reference(ctx, request: Request, who: str, key: str | None) -> Response:
    body = await request.body()
    if len(body) > MAX_REFERENCE_BYTES:
        raise Problem(413, f"a reference request is at most {MAX_REFERENCE_BYTES} bytes")
    data = parse_json_part(body.decode("utf-8", errors="replace"), "body")
    if "source" not in data:
        raise Problem(415, "send multipart/form-data with the files mesh (or volume), ap and lat, or application/json "
                           "with a DICOMweb reference {\"source\": {\"dicomweb\": ...}}",
                      accepted="multipart/form-data, application/json (source.dicomweb)")
    try:
        reference = DicomwebRegistrationRequest.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise Problem(422, f"{first.get('msg', 'invalid')}", field=_field(first.get("loc", ())) or None,
                      accepted='{"source": {"dicomweb": {"url", "study_uid", "ap": {"series_uid"}, '
                               '"lat": {"series_uid"}, "volume": {"series_uid"}}}, "options": {}, "store_results": true}'
                      ) from None
    source = reference.source.dicomweb
    server = resolve_server(ctx.settings, source.url)
    if server is None:
        raise Problem(422, "this DICOMweb server is not configured on this registration server "
                           "(the administrator lists allowed servers in DSAREG_DICOMWEB_SERVERS)",
                      field="source.dicomweb.url")
    from dsareg_engine.errors import DsaregInputError
    from dsareg_engine.registration.options import parse_options

    try:
        options = parse_options(json.dumps(reference.options) if reference.options else None)
    except DsaregInputError as exc:
        raise Problem(422, exc.message, field=exc.field, accepted=exc.accepted) from None
    check_options(options)
    options_json = options.model_dump(mode="json")
    stored_reference = reference.model_copy(update={"options": {}})
    stored_reference.source.dicomweb.url = server.url  # normalized
    text = stored_reference.model_dump_json().encode()
    digest, size = await asyncio.to_thread(ctx.blobs.put_bytes, text)
    inputs = [InputFile(role="dicomweb", sha256=digest, size=size, suffix=".json")]
    fingerprint = hashlib.sha256(json.dumps({"inputs": [vars(f) for f in inputs], "geometry": None,
                                             "options": options_json}, sort_keys=True).encode()).hexdigest()
    if key is not None:
        existing = await asyncio.to_thread(ctx.store.find_idempotent, who, key)
        if existing is not None:
            return _replay(existing, fingerprint)
    if await asyncio.to_thread(ctx.store.queued_count) >= ctx.settings.queue_limit:
        raise Problem(503, f"the job queue is full ({ctx.settings.queue_limit} queued); retry later",
                      kind="queue-full", headers={"Retry-After": "30"})
    if who != "anonymous" and await asyncio.to_thread(ctx.store.queued_count, who) >= ctx.settings.queue_limit_per_key:
        raise Problem(429, f"this API key already has {ctx.settings.queue_limit_per_key} queued jobs; retry later",
                      headers={"Retry-After": "30"})
    now = time.time()
    job = JobRecord(id=new_job_id(), owner=who, status="queued", created_at=now, updated_at=now,
                    max_attempts=ctx.settings.max_attempts, options=options_json, geometry=None, inputs=inputs,
                    warnings=[], idempotency_key=key, request_hash=fingerprint, input_bytes=size)
    try:
        stored, created = await asyncio.to_thread(ctx.store.create, job)
    except ConflictError as exc:
        return _replay(exc.existing, fingerprint)
    if not created:
        return _replay(stored, fingerprint)
    if not ctx.blobs.exists(digest):
        await asyncio.to_thread(ctx.blobs.put_bytes, text)
    await asyncio.to_thread(ctx.executor.submit, stored.id)
    log.info("job %s: queued by DICOMweb reference", stored.id)
    return JSONResponse(job_status(stored).model_dump(mode="json"), status_code=202,
                        headers={"Location": f"/v1/registrations/{stored.id}", "Retry-After": "2"})


def _replay(existing: JobRecord, fingerprint: str) -> Response:
    if existing.request_hash != fingerprint:
        raise Problem(409, "this Idempotency-Key was already used with a different request; use a new key",
                      kind="idempotency-conflict", field="Idempotency-Key", extra={"job_id": existing.id})
    return JSONResponse(job_status(existing).model_dump(mode="json"), status_code=200,
                        headers={"Location": f"/v1/registrations/{existing.id}"})


def _inline_schema(model) -> dict:
    """``model``'s JSON schema with its ``$defs`` inlined (it goes inside an operation, not components)."""
    schema = model.model_json_schema()
    defs = schema.pop("$defs", {})

    def resolve(node):
        if isinstance(node, dict):
            ref = node.get("$ref", "")
            if ref.startswith("#/$defs/"):
                return resolve({**defs[ref.rsplit("/", 1)[1]], **{k: v for k, v in node.items() if k != "$ref"}})
            return {k: resolve(v) for k, v in node.items()}
        if isinstance(node, list):
            return [resolve(v) for v in node]
        return node

    return resolve(schema)


def document_json_submission(app: FastAPI) -> None:
    """Add the ``application/json`` (DICOMweb reference) body to the submit operation's OpenAPI."""
    for route in app.routes:
        if getattr(route, "path", None) == "/v1/registrations" and "POST" in getattr(route, "methods", ()):
            extra = route.openapi_extra if route.openapi_extra is not None else {}
            content = extra.setdefault("requestBody", {"required": True}).setdefault("content", {})
            content["application/json"] = {"schema": _inline_schema(DicomwebRegistrationRequest)}
            route.openapi_extra = extra


def install_dicom_routes(app: FastAPI, get_ctx, principal, owned_job) -> None:
    document_json_submission(app)

    @app.get("/v1/registrations/{job_id}/dicom/{name}", tags=["results"],
             summary="DICOM results: Spatial Registration (reg.dcm) and Secondary Capture overlays",
             response_class=Response,
             responses={200: {"content": {"application/dicom": {"schema": {"type": "string", "format": "binary"}}},
                              "description": "A DICOM Part 10 file."},
                        **problem_responses(401, 403, 404, 422)})
    def get_dicom(request: Request, job_id: str,
                  name: Literal["reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm"],
                  who: str = Depends(principal)) -> Response:
        ctx = get_ctx(request)
        job = owned_job(ctx, job_id, who)
        digest = job.artifacts.get(name)
        if job.status != "succeeded" or not digest:
            why = f"the job is {job.status}" if job.status != "succeeded" else "the job did not produce it"
            raise Problem(404, f"{name} is not available: {why}", kind="artifact-not-available",
                          extra={"job_status": job.status})
        path = ctx.blobs.local_path(digest)
        if path is None:
            raise Problem(404, f"{name} is no longer stored", kind="artifact-not-available")
        return FileResponse(path, media_type="application/dicom", filename=name,
                            headers={"Cache-Control": "private, max-age=86400"})

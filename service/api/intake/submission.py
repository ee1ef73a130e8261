"""A multipart submission → a queued job: parse the form, store the uploads, validate, enqueue.

The steps (idempotency, back-pressure, create, replay) are shared with the DICOMweb reference
submission (:mod:`service.api.intake.dicom_reference`) and motion tracking (:mod:`service.api.routes.tracking`).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import time
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse, Response
from starlette.datastructures import UploadFile

from ...budgets import check_job_cost, parse_json_part
from ...engine_adapter import check_options, engine, image_reading_json, job_case, submitted_geometry, volume_reading
from ...jobs.callbacks import url_problem
from ...pacs.instance_check import InstanceLimits, refusal_of_file
from ...intake.refusals import IdempotencyConflict, InvalidInput, Overloaded, QuotaExceeded
from ...problems import Problem
from ...storage.blobs import safe_suffix
from ...storage.diskspace import ensure_room
from ...storage.store import ConflictError, InputFile, JobRecord, new_job_id
from ..deps import ANONYMOUS, ServiceContext
from ..schemas.jobs import previous_link_header, status_body
from .forms import MAX_TEXT_PART_BYTES

log = logging.getLogger("dsareg.service")

MAX_GEOMETRY_BYTES = MAX_TEXT_PART_BYTES
MAX_OPTIONS_BYTES = MAX_TEXT_PART_BYTES
MAX_VOLUME_FILES = 4000
RETRY_AFTER_QUEUED = "2"
QUEUE_RETRY_AFTER_S = 30
ENGINE_RETRY_AFTER_S = 60
FORM_FIELDS = ("mesh", "volume", "ap", "lat", "geometry", "options", "callback_url")
FILE_ROLES = ("mesh", "volume", "ap", "lat")


# ---- request parts ---------------------------------------------------------------------------


def idempotency_key(request: Request) -> str | None:
    key = request.headers.get("idempotency-key")
    if key is not None and (not key.strip() or len(key) > 255):
        raise Problem(400, "Idempotency-Key must be 1 to 255 characters", field="Idempotency-Key")
    return key


def read_text_field(value: Any, name: str, limit: int) -> str:
    if isinstance(value, UploadFile):
        data = value.file.read(limit + 1)
    elif isinstance(value, str):
        data = value.encode("utf-8")
    else:
        raise Problem(400, f"'{name}' must be text or a file", field=name)
    if len(data) > limit:
        raise Problem(413, f"'{name}' is larger than {limit} bytes", field=name)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise InvalidInput("is not UTF-8 text", field=name, accepted="UTF-8 JSON text") from None


def parse_options_json(data: Any) -> dict[str, Any]:
    """Options (a dict, JSON text or None) → the validated, complete options (``engine.DsaregInputError``
    naming the option if invalid: 422, :mod:`service.api.handlers`)."""
    options = engine.parse_options(data)
    check_options(options)
    return options


def form_files(form: Any) -> dict[str, list[UploadFile]]:
    """The file parts by role, checked for presence and count."""
    unknown = sorted(set(form.keys()) - set(FORM_FIELDS))
    if unknown:
        raise InvalidInput(f"unknown form field(s) {unknown[:5]}", field=str(unknown[0])[:64],
                      accepted=", ".join(FORM_FIELDS))
    files: dict[str, list[UploadFile]] = {}
    for name in FILE_ROLES:
        values = form.getlist(name)
        for value in values:
            if not isinstance(value, UploadFile):
                raise InvalidInput("must be a file part (with a filename)", field=name)
        if values:
            files[name] = values  # type: ignore[assignment]
    if len(files.get("mesh", [])) > 1:
        raise InvalidInput("give exactly one mesh file", field="mesh")
    for name in ("ap", "lat"):
        if len(files.get(name, [])) > 2:
            raise InvalidInput("give one image file (or a .rad + .raw pair)", field=name)
    if "mesh" in files and "volume" in files:
        raise InvalidInput("give either a mesh or a volume, not both", field="mesh", accepted="mesh or volume")
    if "mesh" not in files and "volume" not in files:
        raise InvalidInput("a 3D model is required", field="mesh", accepted="a mesh file or volume file(s)")
    for name in ("ap", "lat"):
        if name not in files:
            raise InvalidInput("this image is required", field=name, accepted="a DSA image or mask file")
    return files


def form_geometry_and_options(form: Any) -> tuple[str | None, Any]:
    """The geometry of a form, parsed once into its canonical JSON, and the parsed options."""
    geometry_values = form.getlist("geometry")
    options_values = form.getlist("options")
    if len(geometry_values) > 1 or len(options_values) > 1:
        raise InvalidInput("give geometry and options at most once",
                      field="geometry" if len(geometry_values) > 1 else "options")
    geometry = submitted_geometry(
        read_text_field(geometry_values[0], "geometry", MAX_GEOMETRY_BYTES) if geometry_values else None)
    options_text = read_text_field(options_values[0], "options", MAX_OPTIONS_BYTES) if options_values else None
    options_data = parse_json_part(options_text, "options") if options_text and options_text.strip() else None
    return geometry, parse_options_json(options_data)


async def refuse_hostile_dicom(ctx: ServiceContext, role: str, digest: str) -> None:
    """A DICOM upload's sizes as the DICOM node checks them (inflated, pixels, truncation): 422 naming the field."""
    path = ctx.blobs.local_path(digest)
    if path is None:
        return
    reason = await asyncio.to_thread(refusal_of_file, path, InstanceLimits.of(ctx.settings))
    if reason is not None:
        raise InvalidInput(f"DICOM file refused: {reason}", field=role,
                      accepted="DICOM within DSAREG_MAX_DICOM_INSTANCE_BYTES (as stored and inflated) and "
                               "DSAREG_MAX_DICOM_PIXEL_BYTES, complete")


async def store_uploads(ctx: ServiceContext, files: dict[str, list[UploadFile]]
                        ) -> tuple[list[InputFile], list[UploadFile]]:
    """Store the uploads (content-addressed); the input records and their sources, in role order."""
    inputs: list[InputFile] = []
    sources: list[UploadFile] = []
    for role in FILE_ROLES:
        for upload in files.get(role, []):
            await upload.seek(0)
            digest, size = await asyncio.to_thread(ctx.blobs.put_stream, upload.file)
            if size == 0:
                raise InvalidInput("the file is empty", field=role)
            await refuse_hostile_dicom(ctx, role, digest)
            inputs.append(InputFile(role=role, sha256=digest, size=size, suffix=safe_suffix(upload.filename)))
            sources.append(upload)
    return inputs, sources


def fingerprint(inputs: list[InputFile], geometry: str | None, options_json: dict[str, Any],
                callback_url: str | None = None) -> str:
    request = {"inputs": [vars(f) for f in inputs], "geometry": geometry, "options": options_json}
    if callback_url:  # only when given: requests without one hash as before
        request["callback_url"] = callback_url
    return hashlib.sha256(json.dumps(request, sort_keys=True).encode()).hexdigest()


def checked_callback_url(ctx: ServiceContext, value: Any, field: str = "callback_url") -> str | None:
    """The callback URL of a request (None when not given); 422 naming ``field`` unless it is allowed."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if not isinstance(value, str):
        raise InvalidInput("must be text (a URL)", field=field)
    url = value.strip()
    why = url_problem(url, ctx.settings.callbacks.callback_allowed)
    if why is not None:
        raise InvalidInput(f"callback_url {why}", field=field,
                      accepted="an http(s) URL under a prefix the administrator allowed (DSAREG_CALLBACK_ALLOWED)")
    return url


def form_callback_url(ctx: ServiceContext, form: Any) -> str | None:
    values = form.getlist("callback_url")
    if len(values) > 1:
        raise InvalidInput("give callback_url at most once", field="callback_url")
    if values and isinstance(values[0], UploadFile):
        raise InvalidInput("must be a text field, not a file", field="callback_url")
    return checked_callback_url(ctx, values[0] if values else None)


# ---- the job ---------------------------------------------------------------------------------


async def check_queue(ctx: ServiceContext, who: str) -> None:
    """Back-pressure: :class:`Overloaded` when the queue is full, :class:`QuotaExceeded` when this owner has too
    many queued jobs."""
    limits = ctx.settings.limits
    if await asyncio.to_thread(ctx.store.queued_count) >= limits.queue_limit:
        raise Overloaded(f"the job queue is full ({limits.queue_limit} queued); retry later", kind="queue-full",
                         retry_after_s=QUEUE_RETRY_AFTER_S)
    if who != ANONYMOUS and await asyncio.to_thread(ctx.store.queued_count, who) >= limits.queue_limit_per_key:
        raise QuotaExceeded(f"this API key already has {limits.queue_limit_per_key} queued jobs; retry later",
                            retry_after_s=QUEUE_RETRY_AFTER_S)


async def validate_inputs(ctx: ServiceContext, inputs: list[InputFile], geometry: str | None,
                          options: Any) -> tuple[list[str], dict[str, Any] | None]:
    """Parse the inputs in a validator process (422 with the field if they are unusable); the warnings and
    the case identity the headers gave (source ``upload``, no file names: :func:`job_case` sets them)."""
    if ctx.validator is None:
        return [], None
    outcome = await ctx.validator.validate({
        "inputs": [vars(f) for f in inputs], "geometry": geometry, "segmentation": options.segmentation,
        "reading": image_reading_json(options),
        "volume_reading": volume_reading(options),
        "mesh_units": options.mesh_units,
        "hemodynamics": options.hemodynamics,
        "blob_root": str(ctx.blobs.root), "limits": ctx.settings.limits.input_limits,
        "require_cuda": options.device == "cuda" and ctx.settings.jobs.executor == "embedded",
    })
    if outcome.unavailable:
        raise Overloaded("the registration engine is not available on this server", kind="engine-unavailable",
                         retry_after_s=ENGINE_RETRY_AFTER_S)
    if outcome.busy:
        raise Overloaded(outcome.message or "input validation is temporarily unavailable",
                         kind="validator-unavailable", retry_after_s=ctx.validator.RETRY_AFTER_SECONDS)
    if not outcome.ok:
        raise InvalidInput(outcome.message or "invalid input", field=outcome.field, accepted=outcome.accepted)
    views = (outcome.summary or {}).get("views") or {}
    check_job_cost(options, [tuple(size) for size in views.values()], ctx.settings.limits.max_job_cost)
    return list((outcome.summary or {}).get("warnings", [])), (outcome.summary or {}).get("case")


def new_job(ctx: ServiceContext, who: str, key: str | None, *, options_json: dict[str, Any], geometry: str | None,
            inputs: list[InputFile], warnings: list[str], request_hash: str, input_bytes: int,
            callback_url: str | None = None, previous_id: str | None = None,
            case: tuple[dict[str, Any], str | None] | None = None) -> JobRecord:
    """``case``: the case identity and its search text (:func:`service.engine_adapter.job_case`)."""
    now = time.time()
    return JobRecord(
        id=new_job_id(), owner=who, status="queued", created_at=now, updated_at=now,
        max_attempts=ctx.settings.jobs.max_attempts, options=options_json, geometry=geometry, inputs=inputs,
        warnings=warnings, idempotency_key=key, request_hash=request_hash, input_bytes=input_bytes,
        callback_url=callback_url, previous_id=previous_id, case=case[0] if case else None,
        case_search=case[1] if case else None,
    )


def replay(existing: JobRecord, request_hash: str) -> Response:
    """The job created earlier with this Idempotency-Key (200), or :class:`IdempotencyConflict` if the request
    differs."""
    if existing.request_hash != request_hash:
        raise IdempotencyConflict("this Idempotency-Key was already used with a different request; use a new key",
                                  field="Idempotency-Key", job_id=existing.id)
    return JSONResponse(status_body(existing), status_code=200,
                        headers={"Location": f"/v1/registrations/{existing.id}", **previous_link_header(existing)})


async def find_replay(ctx: ServiceContext, who: str, key: str | None, request_hash: str) -> Response | None:
    if key is None:
        return None
    existing = await asyncio.to_thread(ctx.store.find_idempotent, who, key)
    return None if existing is None else replay(existing, request_hash)


async def create_job(ctx: ServiceContext, job: JobRecord) -> tuple[JobRecord | None, Response | None]:
    """Insert the job; ``(stored, None)`` when created, ``(None, replay)`` when an equal request won."""
    try:
        stored, created = await asyncio.to_thread(ctx.store.create, job)
    except ConflictError as exc:
        return None, replay(exc.existing, job.request_hash)
    if not created:
        return None, replay(stored, job.request_hash)
    return stored, None


def accepted(stored: JobRecord) -> JSONResponse:
    """202 with the job as every submission answers it (only the links that lead somewhere now)."""
    return JSONResponse(status_body(stored), status_code=202,
                        headers={"Location": f"/v1/registrations/{stored.id}", "Retry-After": RETRY_AFTER_QUEUED,
                                 **previous_link_header(stored)})


async def submit_form(ctx: ServiceContext, form: Any, who: str, key: str | None) -> Response:
    """A parsed multipart form → 202 with the new job (or 200/409 for an Idempotency-Key replay)."""
    files = form_files(form)
    geometry, options = await asyncio.to_thread(form_geometry_and_options, form)  # JSON parsing off the event loop
    return await submit_files(ctx, files, geometry, options, who, key, callback_url=form_callback_url(ctx, form))


async def submit_files(ctx: ServiceContext, files: dict[str, list[UploadFile]], geometry: str | None, options: Any,
                       who: str, key: str | None, *, callback_url: str | None = None,
                       previous_id: str | None = None) -> Response:
    """Checked file parts, canonical geometry JSON and parsed options → 202 with the new job (or a replay)."""
    options_json = options.model_dump(mode="json")
    upload_bytes = sum(upload.size or 0 for uploads in files.values() for upload in uploads)
    await asyncio.to_thread(ensure_room, ctx.blobs.root, ctx.settings.storage.min_free_bytes, upload_bytes)  # 507 before writing
    inputs, sources = await store_uploads(ctx, files)
    request_hash = fingerprint(inputs, geometry, options_json, callback_url)
    total = sum(f.size for f in inputs)
    if (previous := await find_replay(ctx, who, key, request_hash)) is not None:
        return previous
    await check_queue(ctx, who)  # back-pressure before the expensive parse
    warnings, identity = await validate_inputs(ctx, inputs, geometry, options)
    names = {role: [u.filename or "" for u in uploads] for role, uploads in files.items()}
    job = new_job(ctx, who, key, options_json=options_json, geometry=geometry, inputs=inputs, warnings=warnings,
                  request_hash=request_hash, input_bytes=total, callback_url=callback_url, previous_id=previous_id,
                  case=job_case(identity, "upload", names))
    stored, answer = await create_job(ctx, job)
    if stored is None:
        return answer  # type: ignore[return-value]
    # a concurrent DELETE of another job with the same content may have removed a shared blob
    # between our upload and our insert; now that we reference it, put it back if so
    for item, upload in zip(inputs, sources):
        if not ctx.blobs.exists(item.sha256):
            await upload.seek(0)
            await asyncio.to_thread(ctx.blobs.put_stream, upload.file)
    ctx.uploads.inc(total)
    await asyncio.to_thread(ctx.executor.submit, stored.id)
    log.info("job %s: queued (%d files, %d bytes)", stored.id, len(inputs), total)
    return accepted(stored)

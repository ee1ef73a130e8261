"""Inputs → a queued job: store the uploads, check them, back-pressure, validate, record, enqueue.

The steps (idempotency, back-pressure, create, replay) are shared by every way a job arrives: files
(:func:`submit_files`: ``POST /v1/registrations`` and motion tracking), a DICOMweb or DIMSE reference
(:mod:`.reference`) and a study received over DIMSE (:mod:`service.pacs.dimse.submit`). Each step raises
a :mod:`.refusals` error; the answer is a :class:`Submitted`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import json
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, BinaryIO

from ..budgets import check_job_cost
from ..engine_adapter import (check_options, engine, image_reading_json, job_case, model_cache, model_store,
                              volume_model_key, volume_reading)
from ..jobs.callbacks import url_problem
from ..pacs.instance_check import InstanceLimits, refusal_of_file
from ..storage.blobs import safe_suffix
from ..storage.diskspace import ensure_room
from ..storage.shared_models import shared_models_for
from ..storage.store import ConflictError, InputFile, JobRecord, new_job_id
from .context import ANONYMOUS, IntakeContext
from .refusals import IdempotencyConflict, InvalidInput, Overloaded, QuotaExceeded

log = logging.getLogger("dsareg.service")

FILE_ROLES = ("mesh", "volume", "ap", "lat")
QUEUE_RETRY_AFTER_S = 30
ENGINE_RETRY_AFTER_S = 60


@dataclass(frozen=True)
class Upload:
    """One submitted file: its name as sent (only its suffix is kept), its bytes (seekable) and size if known."""

    filename: str | None
    file: BinaryIO
    size: int | None = None


@dataclass(frozen=True)
class Submitted:
    """The job of a submission: ``created`` it now, or found (``created`` false) the one an equal request
    with the same idempotency key made before."""

    job: JobRecord
    created: bool


# ---- the inputs ------------------------------------------------------------------------------


def parse_options_json(data: Any) -> Any:
    """Options (a dict, JSON text or None) → the validated, complete options (``engine.DsaregInputError``
    naming the option if invalid)."""
    options = engine.parse_options(data)
    check_options(options)
    return options


def checked_roles(files: dict[str, list[Upload]]) -> dict[str, list[Upload]]:
    """The files by role, checked for presence and count (a model, mesh or volume, and both images)."""
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


def checked_callback_url(ctx: IntakeContext, value: Any, field: str = "callback_url") -> str | None:
    """The callback URL of a request (None when not given); refused naming ``field`` unless it is allowed."""
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


async def refuse_hostile_dicom(ctx: IntakeContext, role: str, digest: str) -> None:
    """A DICOM upload's sizes as the DICOM node checks them (inflated, pixels, truncation), refused naming the role."""
    path = ctx.blobs.local_path(digest)
    if path is None:
        return
    reason = await asyncio.to_thread(refusal_of_file, path, InstanceLimits.of(ctx.settings))
    if reason is not None:
        raise InvalidInput(f"DICOM file refused: {reason}", field=role,
                           accepted="DICOM within DSAREG_MAX_DICOM_INSTANCE_BYTES (as stored and inflated) and "
                                    "DSAREG_MAX_DICOM_PIXEL_BYTES, complete")


def _put(ctx: IntakeContext, upload: Upload) -> tuple[str, int]:
    upload.file.seek(0)
    return ctx.blobs.put_stream(upload.file)


async def store_uploads(ctx: IntakeContext, files: dict[str, list[Upload]]) -> list[InputFile]:
    """Store the uploads (content-addressed); their input records, in role order (as :func:`_ordered`)."""
    inputs: list[InputFile] = []
    for role, upload in _ordered(files):
        digest, size = await asyncio.to_thread(_put, ctx, upload)
        if size == 0:
            raise InvalidInput("the file is empty", field=role)
        await refuse_hostile_dicom(ctx, role, digest)
        inputs.append(InputFile(role=role, sha256=digest, size=size, suffix=safe_suffix(upload.filename)))
    return inputs


def _ordered(files: dict[str, list[Upload]]) -> list[tuple[str, Upload]]:
    return [(role, upload) for role in FILE_ROLES for upload in files.get(role, [])]


def fingerprint(inputs: list[InputFile], geometry: str | None, options_json: dict[str, Any],
                callback_url: str | None = None) -> str:
    request = {"inputs": [vars(f) for f in inputs], "geometry": geometry, "options": options_json}
    if callback_url:  # only when given: requests without one hash as before
        request["callback_url"] = callback_url
    return hashlib.sha256(json.dumps(request, sort_keys=True).encode()).hexdigest()


# ---- the job ---------------------------------------------------------------------------------


async def check_queue(ctx: IntakeContext, who: str) -> None:
    """Back-pressure: :class:`Overloaded` when the queue is full, :class:`QuotaExceeded` when this owner has too
    many queued jobs."""
    limits = ctx.settings.limits
    if await asyncio.to_thread(ctx.jobs.queued_count) >= limits.queue_limit:
        raise Overloaded(f"the job queue is full ({limits.queue_limit} queued); retry later", kind="queue-full",
                         retry_after_s=QUEUE_RETRY_AFTER_S)
    if who != ANONYMOUS and await asyncio.to_thread(ctx.jobs.queued_count, who) >= limits.queue_limit_per_key:
        raise QuotaExceeded(f"this API key already has {limits.queue_limit_per_key} queued jobs; retry later",
                            retry_after_s=QUEUE_RETRY_AFTER_S)


async def validate_inputs(ctx: IntakeContext, inputs: list[InputFile], geometry: str | None,
                          options: Any) -> tuple[list[str], dict[str, Any] | None]:
    """Parse the inputs in a validator process (:class:`InvalidInput` with the field if they are unusable); the
    warnings and the case identity the headers gave (source ``upload``, no file names: :func:`job_case` sets them)."""
    if ctx.validator is None:
        return [], None
    shared = shared_models_for(ctx.settings, ctx.blobs, model_store(model_cache(ctx.settings.storage)))  # scale-out: a model another node kept serves this check
    key = volume_model_key(inputs, options, ctx.settings.limits.input_limits) if shared is not None else None
    if key is not None:
        await asyncio.to_thread(shared.pull, key)
    outcome = await ctx.validator.validate({
        "inputs": [vars(f) for f in inputs], "geometry": geometry, "segmentation": options.segmentation,
        "reading": image_reading_json(options),
        "volume_reading": volume_reading(options),
        "mesh_units": options.mesh_units,
        "hemodynamics": options.hemodynamics,
        "blob_root": str(ctx.blobs.root), "limits": ctx.settings.limits.input_limits,
        "models": model_cache(ctx.settings.storage),
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
    if key is not None:  # the model this check kept, for the workers of other nodes
        await asyncio.to_thread(shared.push, key)
    views = (outcome.summary or {}).get("views") or {}
    check_job_cost(options, [tuple(size) for size in views.values()], ctx.settings.limits.max_job_cost)
    return list((outcome.summary or {}).get("warnings", [])), (outcome.summary or {}).get("case")


def new_job(ctx: IntakeContext, who: str, key: str | None, *, options_json: dict[str, Any], geometry: str | None,
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


def replay(existing: JobRecord, request_hash: str) -> Submitted:
    """The job created earlier with this idempotency key, or :class:`IdempotencyConflict` if the request differs."""
    if existing.request_hash != request_hash:
        raise IdempotencyConflict("this Idempotency-Key was already used with a different request; use a new key",
                                  field="Idempotency-Key", job_id=existing.id)
    return Submitted(existing, created=False)


async def find_replay(ctx: IntakeContext, who: str, key: str | None, request_hash: str) -> Submitted | None:
    if key is None:
        return None
    existing = await asyncio.to_thread(ctx.jobs.find_idempotent, who, key)
    return None if existing is None else replay(existing, request_hash)


async def create_job(ctx: IntakeContext, job: JobRecord) -> Submitted:
    """Insert the job: created, or the replay of an equal request that won the race."""
    try:
        stored, created = await asyncio.to_thread(ctx.jobs.create, job)
    except ConflictError as exc:
        return replay(exc.existing, job.request_hash)
    return Submitted(stored, created=True) if created else replay(stored, job.request_hash)


@dataclass(frozen=True)
class FileRequest:
    """A submission by files: checked roles (:func:`checked_roles`), canonical geometry JSON, parsed options."""

    files: dict[str, list[Upload]]
    geometry: str | None
    options: Any
    callback_url: str | None = None
    previous_id: str | None = None  # the job a tracking job follows
    carried: Mapping[str, str] = dataclasses.field(default_factory=dict)  # plane not sent again → job it came with


async def submit_files(ctx: IntakeContext, request: FileRequest, who: str, key: str | None) -> Submitted:
    """Files → the new job, queued (or the replay of an equal request with the same key)."""
    options_json = request.options.model_dump(mode="json")
    upload_bytes = sum(upload.size or 0 for _, upload in _ordered(request.files))
    await asyncio.to_thread(ensure_room, ctx.blobs.root, ctx.settings.storage.min_free_bytes, upload_bytes)
    inputs = await store_uploads(ctx, request.files)
    request_hash = fingerprint(inputs, request.geometry, options_json, request.callback_url)
    if (previous := await find_replay(ctx, who, key, request_hash)) is not None:
        return previous
    await check_queue(ctx, who)  # back-pressure before the expensive parse
    warnings, identity = await validate_inputs(ctx, inputs, request.geometry, request.options)
    names = {role: [u.filename or "" for u in uploads] for role, uploads in request.files.items()}
    job = new_job(ctx, who, key, options_json=options_json, geometry=request.geometry, inputs=inputs,
                  warnings=warnings, request_hash=request_hash, input_bytes=sum(f.size for f in inputs),
                  callback_url=request.callback_url, previous_id=request.previous_id,
                  case=job_case(identity, "upload", names, carried=request.carried))
    submitted = await create_job(ctx, job)
    if submitted.created:
        await _restore_blobs(ctx, inputs, [upload for _, upload in _ordered(request.files)])
        await asyncio.to_thread(ctx.executor.submit, submitted.job.id)
        log.info("job %s: queued (%d files, %d bytes)", submitted.job.id, len(inputs), job.input_bytes)
    return submitted


async def _restore_blobs(ctx: IntakeContext, inputs: list[InputFile], sources: list[Upload]) -> None:
    """A concurrent DELETE of another job with the same content may have removed a shared blob between our
    upload and our insert; now that the job references it, put it back if so."""
    for item, upload in zip(inputs, sources, strict=True):
        if not ctx.blobs.exists(item.sha256):
            await asyncio.to_thread(_put, ctx, upload)

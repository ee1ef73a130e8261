"""API side of the DICOM integration: submission by DICOMweb reference.

* ``POST /v1/registrations`` with ``Content-Type: application/json`` and a body
  ``{"source": {"dicomweb": {...}}, "options": {...}, "store_results": true}``
  (see :class:`service.pacs.dicomweb.DicomwebRegistrationRequest`). The reference is checked
  (UID syntax, the URL is one of ``settings.dicomweb.dicomweb_servers``, options) and stored as the
  job's only input; the worker fetches the images (``service/pacs/dicom_jobs.py``).
  The DICOM results are served by :mod:`service.api.routes.artifacts`.
"""

from __future__ import annotations

import asyncio
import json
import logging

from fastapi import Request
from fastapi.responses import Response
from pydantic import ValidationError

from ...budgets import parse_json_part
from ...pacs.dicomweb import DicomwebRegistrationRequest, resolve_server
from ...pacs.dimse.pull import ROLE as PULL_ROLE
from ...pacs.dimse.pull import DimseRegistrationRequest
from ...pacs.dimse.scp import configured_peers
from ...intake.refusals import InvalidInput
from ...storage.store import InputFile
from ..deps import ServiceContext
from .forms import read_body
from .submission import (
    accepted,
    check_queue,
    checked_callback_url,
    create_job,
    find_replay,
    fingerprint,
    new_job,
    parse_options_json,
)

log = logging.getLogger("dsareg.service")

MAX_REFERENCE_BYTES = 64 * 1024


def _field(loc) -> str:
    return ".".join(str(part) for part in loc)


async def parse_reference(request: Request) -> DicomwebRegistrationRequest | DimseRegistrationRequest:
    body = await read_body(request, MAX_REFERENCE_BYTES)  # streamed: never buffered past the limit
    data = parse_json_part(body.decode("utf-8", errors="replace"), "body")
    if not isinstance(data, dict) or "source" not in data:
        raise InvalidInput("a JSON body gives the inputs by reference: {\"source\": {\"dicomweb\": ...}} (or "
                           "{\"source\": {\"dimse\": ...}}) is required (or send multipart/form-data with the files "
                           "mesh (or volume), ap and lat)", field="source",
                      accepted="application/json with source.dicomweb or source.dimse, or multipart/form-data")
    if isinstance(data.get("source"), dict) and "dimse" in data["source"]:
        try:
            return DimseRegistrationRequest.model_validate(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            raise InvalidInput(f"{first.get('msg', 'invalid')}", field=_field(first.get("loc", ())) or None,
                          accepted='{"source": {"dimse": {"peer", "study_uid", "ap": {"series_uid"}, '
                                   '"lat": {"series_uid"}, "volume": {"series_uid"}, "retrieve": "move" | "get"}}, '
                                   '"options": {}, "store_results": true}') from None
    try:
        return DicomwebRegistrationRequest.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise InvalidInput(f"{first.get('msg', 'invalid')}", field=_field(first.get("loc", ())) or None,
                      accepted='{"source": {"dicomweb": {"url", "study_uid", "ap": {"series_uid"}, '
                               '"lat": {"series_uid"}, "volume": {"series_uid"}}}, "options": {}, "store_results": true}'
                      ) from None


def _stored_reference(ctx: ServiceContext, reference) -> tuple[str, bytes]:
    """The input role and stored JSON of a checked reference (422 naming the field when its PACS is unknown).
    The callback URL is the job's, not an input: it is not stored with the reference."""
    stored_reference = reference.model_copy(update={"options": {}})
    if isinstance(reference, DimseRegistrationRequest):
        if reference.source.dimse.peer not in configured_peers(ctx.settings):
            raise InvalidInput("this DICOM peer is not configured on this registration server (the administrator "
                               "lists allowed peers in DSAREG_DICOM_PEERS)", field="source.dimse.peer")
        return PULL_ROLE, stored_reference.model_dump_json(exclude={"callback_url"}).encode()
    server = resolve_server(ctx.settings, reference.source.dicomweb.url)
    if server is None:
        raise InvalidInput("this DICOMweb server is not configured on this registration server "
                           "(the administrator lists allowed servers in DSAREG_DICOMWEB_SERVERS)",
                      field="source.dicomweb.url")
    stored_reference.source.dicomweb.url = server.url  # normalized
    return "dicomweb", stored_reference.model_dump_json(exclude={"callback_url"}).encode()


async def submit_by_reference(ctx: ServiceContext, request: Request, who: str, key: str | None) -> Response:
    reference = await parse_reference(request)
    callback_url = checked_callback_url(ctx, getattr(reference, "callback_url", None))
    role, text = _stored_reference(ctx, reference)
    options = parse_options_json(json.dumps(reference.options) if reference.options else None)
    options_json = options.model_dump(mode="json")
    digest, size = await asyncio.to_thread(ctx.blobs.put_bytes, text)
    inputs = [InputFile(role=role, sha256=digest, size=size, suffix=".json")]
    request_hash = fingerprint(inputs, None, options_json, callback_url)
    if (previous := await find_replay(ctx, who, key, request_hash)) is not None:
        return previous
    await check_queue(ctx, who)
    job = new_job(ctx, who, key, options_json=options_json, geometry=None, inputs=inputs, warnings=[],
                  request_hash=request_hash, input_bytes=size, callback_url=callback_url)
    stored, answer = await create_job(ctx, job)
    if stored is None:
        return answer  # type: ignore[return-value]
    if not ctx.blobs.exists(digest):
        await asyncio.to_thread(ctx.blobs.put_bytes, text)
    await asyncio.to_thread(ctx.executor.submit, stored.id)
    log.info("job %s: queued by %s reference", stored.id, "DIMSE" if role == PULL_ROLE else "DICOMweb")
    return accepted(stored)

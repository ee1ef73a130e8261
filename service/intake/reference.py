"""A submission by reference: the inputs are on a PACS, named by DICOMweb URL or DIMSE peer and UIDs.

The request (``{"source": {"dicomweb": {...}}, "options": {...}, "store_results": true}`` or
``{"source": {"dimse": {...}}, ...}``: :class:`service.pacs.dicomweb.DicomwebRegistrationRequest`,
:class:`service.pacs.dimse.pull.DimseRegistrationRequest`) is checked (UID syntax, the URL or peer is
one this server is configured for, options) and stored as the job's only input; the worker fetches the
images (``service/pacs/dicom_jobs.py``).
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from pydantic import ValidationError

from ..budgets import parse_json_part
from ..pacs.dicomweb import DicomwebRegistrationRequest, resolve_server
from ..pacs.dimse.pull import ROLE as PULL_ROLE
from ..pacs.dimse.pull import DimseRegistrationRequest
from ..pacs.dimse.scp import configured_peers
from ..storage.store import InputFile
from .context import IntakeContext
from .pacs_access import check_access
from .refusals import InvalidInput
from .submission import (
    Submitted,
    check_queue,
    checked_callback_url,
    create_job,
    find_replay,
    fingerprint,
    new_job,
    parse_options_json,
)

log = logging.getLogger("dsareg.service")

Reference = DicomwebRegistrationRequest | DimseRegistrationRequest
ACCEPTED_DIMSE = ('{"source": {"dimse": {"peer", "study_uid", "ap": {"series_uid"}, "lat": {"series_uid"}, '
                  '"volume": {"series_uid"}, "retrieve": "move" | "get"}}, "options": {}, "store_results": true}')
ACCEPTED_DICOMWEB = ('{"source": {"dicomweb": {"url", "study_uid", "ap": {"series_uid"}, "lat": {"series_uid"}, '
                     '"volume": {"series_uid"}}}, "options": {}, "store_results": true}')


def _field(loc) -> str:
    return ".".join(str(part) for part in loc)


def parse_reference(text: str) -> Reference:
    """A request by reference (JSON text) → its checked model; :class:`InvalidInput` naming the field otherwise."""
    data = parse_json_part(text, "body")
    if not isinstance(data, dict) or "source" not in data:
        raise InvalidInput("a JSON body gives the inputs by reference: {\"source\": {\"dicomweb\": ...}} (or "
                           "{\"source\": {\"dimse\": ...}}) is required (or send multipart/form-data with the files "
                           "mesh (or volume), ap and lat)", field="source",
                           accepted="application/json with source.dicomweb or source.dimse, or multipart/form-data")
    dimse = isinstance(data.get("source"), dict) and "dimse" in data["source"]
    model, accepted = (DimseRegistrationRequest, ACCEPTED_DIMSE) if dimse else (DicomwebRegistrationRequest,
                                                                                 ACCEPTED_DICOMWEB)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise InvalidInput(f"{first.get('msg', 'invalid')}", field=_field(first.get("loc", ())) or None,
                           accepted=accepted) from None


def stored_reference(ctx: IntakeContext, reference: Reference) -> tuple[str, bytes]:
    """The input role and stored JSON of a checked reference (:class:`InvalidInput` naming the field when its PACS
    is unknown). The callback URL is the job's, not an input: it is not stored with the reference."""
    stored = reference.model_copy(update={"options": {}})
    if isinstance(reference, DimseRegistrationRequest):
        if reference.source.dimse.peer not in configured_peers(ctx.settings):
            raise InvalidInput("this DICOM peer is not configured on this registration server (the administrator "
                               "lists allowed peers in DSAREG_DICOM_PEERS)", field="source.dimse.peer")
        return PULL_ROLE, stored.model_dump_json(exclude={"callback_url"}).encode()
    server = resolve_server(ctx.settings, reference.source.dicomweb.url)
    if server is None:
        raise InvalidInput("this DICOMweb server is not configured on this registration server "
                           "(the administrator lists allowed servers in DSAREG_DICOMWEB_SERVERS)",
                           field="source.dicomweb.url")
    stored.source.dicomweb.url = server.url  # normalized
    return "dicomweb", stored.model_dump_json(exclude={"callback_url"}).encode()


def checked_access(ctx: IntakeContext, reference: Reference, who: str) -> None:
    """:class:`~.pacs_access.AccessDenied` unless ``who`` may have this study fetched (keys on only)."""
    if not ctx.settings.auth.auth_enabled:
        return
    dimse = isinstance(reference, DimseRegistrationRequest)
    source, name = (reference.source.dimse, "dimse") if dimse else (reference.source.dicomweb, "dicomweb")
    peer, peer_field = (source.peer, "source.dimse.peer") if dimse else (source.url, "source.dicomweb.url")
    check_access(ctx.settings.auth.pacs_access, who, peer=peer, peer_field=peer_field, study_uid=source.study_uid,
                 study_field=f"source.{name}.study_uid")


async def submit_reference(ctx: IntakeContext, reference: Reference, who: str, key: str | None) -> Submitted:
    """A checked reference → the new job, queued (or the replay of an equal request with the same key)."""
    callback_url = checked_callback_url(ctx, getattr(reference, "callback_url", None))
    role, text = stored_reference(ctx, reference)
    checked_access(ctx, reference, who)  # with API keys: the key's DSAREG_PACS_ACCESS grants this study (403)
    options = parse_options_json(json.dumps(reference.options) if reference.options else None)
    options_json: dict[str, Any] = options.model_dump(mode="json")
    digest, size = await asyncio.to_thread(ctx.blobs.put_bytes, text)
    inputs = [InputFile(role=role, sha256=digest, size=size, suffix=".json")]
    request_hash = fingerprint(inputs, None, options_json, callback_url)
    if (previous := await find_replay(ctx, who, key, request_hash)) is not None:
        return previous
    await check_queue(ctx, who)
    job = new_job(ctx, who, key, options_json=options_json, geometry=None, inputs=inputs, warnings=[],
                  request_hash=request_hash, input_bytes=size, callback_url=callback_url)
    submitted = await create_job(ctx, job)
    if submitted.created:
        if not ctx.blobs.exists(digest):
            await asyncio.to_thread(ctx.blobs.put_bytes, text)
        await asyncio.to_thread(ctx.executor.submit, submitted.job.id)
        log.info("job %s: queued by %s reference", submitted.job.id, "DIMSE" if role == PULL_ROLE else "DICOMweb")
    return submitted

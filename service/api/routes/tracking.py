"""``POST /v1/registrations/{job_id}/track``: re-register a finished job's model to a later run of either plane, or both.

During an intervention the patient moves; the client sends only the new images: ``ap``, ``lat`` or both. The new
job re-uses the previous job's stored model files (mesh or volume) and geometry, starts from its result's
``mesh_to_world`` with ``options.mode = "track"`` (one start, a short schedule) and carries the procedure's first
pose along (``options.reference_mesh_to_world``: the previous job's reference when it was a tracking job, else its
result pose). One plane sent: ``options.configuration`` is that plane, and the other plane's image is the previous
job's (shown in that view's overlay and Dice, not fitted), named as carried from an earlier run wherever the new job
describes its images: ``case.inputs[].carried_from`` and ``result.views[plane].image_from_job`` hold the id of the
job that plane's image was sent with (followed back through earlier one-plane tracks), and the review page says so.
The result carries ``metrics.motion`` (since the previous pose) and ``metrics.tracking`` (since the first pose, the
planes fitted, and for one plane the beam direction whose motion cannot be measured: never ``ok``).
It runs as an ordinary job through the same queue and workers (the API process never loads the
engine), so status, result, overlays, cancel and delete work as for any job.
"""

from __future__ import annotations

import asyncio
import io
from typing import Any

from fastapi import Request
from fastapi.responses import Response

from ...budgets import parse_json_part
from ...engine_adapter import canonical_geometry
from ...intake.refusals import InvalidInput
from ...problems import Problem, problem_responses
from ...storage.store import JobRecord
from ..deps import Ctx, OwnedJob, Principal, ServiceContext
from ...intake.submission import FileRequest, Upload, checked_roles, parse_options_json
from ..submit.accept import accept_files
from ..submit.forms import read_form
from ..submit.parts import MAX_OPTIONS_BYTES, file_parts, form_callback_url, idempotency_key, read_text_field
from ..openapi import resource_router
from ..schemas.jobs import JobStatus

router = resource_router("registrations")

TRACK_SCHEMA = {
    "type": "object",
    "description": "Give `ap`, `lat` or both (at least one): a later run of either plane, or of both.",
    "properties": {
        "ap": {"type": "string", "format": "binary", "description": "New AP image or vessel mask (same rig as the job); "
                                                                    "left out: a LAT-only track."},
        "lat": {"type": "string", "format": "binary", "description": "New LAT image or vessel mask; left out: an "
                                                                     "AP-only track."},
        "options": {"type": "string", "description": "RegistrationOptions overriding the job's (JSON); mode is 'track', "
                                                     "the initial pose is the job's result, the reference its reference "
                                                     "(or its pose), the configuration the plane sent (one plane) or "
                                                     "'simultaneous' unless given (both).",
                    "example": "{\"max_iterations\": 60}"},
        "callback_url": {"type": "string", "maxLength": 2048,
                         "description": "POSTed the new job's summary once it ends (as for POST /v1/registrations)."},
    },
}
INHERITED_OUT = ("ground_truth_mesh_to_world", "initial_mesh_to_world", "mode", "starts", "reference_mesh_to_world",
                 "configuration")
"""Options of the previous job that do not carry over: its truth, its start, its mode, its reference (set from its
result), its planes (set from the files sent)."""
PLANES = ("ap", "lat")

TRACK_DOC = {
    "status_code": 202,
    "response_model": JobStatus,
    "summary": "Re-register the job's model to a later run of either plane or both (motion tracking)",
    "description": (
        "multipart/form-data with `ap`, `lat` or both, and optional `options`. The job must have succeeded; its model "
        "and geometry are re-used and its result pose is the starting pose. One plane sent: only that plane is fitted "
        "(the other view shows the previous job's image, named as carried from an earlier run: "
        "`case.inputs[].carried_from` and `result.views[plane].image_from_job` give the job it was sent with). "
        "Answers 202 with the new job's `Location`; its result has "
        "the new `mesh_to_world`, `metrics.motion` since the previous pose and `metrics.tracking` since the "
        "procedure's first pose (`since_reference`), with the planes fitted and, for one plane, "
        "`along_beam_measured: false` and the beam's direction (the verdict is then at most `check`)."
    ),
    "openapi_extra": {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": TRACK_SCHEMA}}},
                   "parameters": [{"name": "Idempotency-Key", "in": "header", "required": False,
                                   "schema": {"type": "string", "maxLength": 255}}]},
    "responses": {202: {"description": "Accepted; poll the Location.", "headers": {
        "Location": {"description": "The new job's URL.", "schema": {"type": "string"}}}},
        **problem_responses(400, 401, 404, 408, 409, 413, 415, 422, 429, 503, 507)},
}


def _reference(previous: JobRecord) -> Any:
    """The procedure's first pose: the previous job's reference when it tracked, else its result pose."""
    tracking = (previous.result.get("metrics") or {}).get("tracking") or {}
    return tracking.get("reference_mesh_to_world") or previous.result["mesh_to_world"]


def _options(previous: JobRecord, form: Any, planes: tuple[str, ...]) -> Any:
    """The new job's options: the previous job's (less INHERITED_OUT), the form's, mode track, its pose, the
    procedure's reference, and for one plane sent (``planes``) that plane's configuration.

    Blocking (a file part is read, JSON parsed): called in a thread. The part is capped like on
    ``POST /v1/registrations`` (:func:`service.api.submit.parts.read_text_field`, 1 MiB, UTF-8)."""
    options = {k: v for k, v in previous.options.items() if k not in INHERITED_OUT}
    options_values = form.getlist("options")
    if len(options_values) > 1:
        raise InvalidInput("give options at most once", field="options")
    if options_values:
        text = read_text_field(options_values[0], "options", MAX_OPTIONS_BYTES)
        if text.strip():
            options.update(parse_json_part(text, "options"))
    if len(planes) == 1:
        if options.get("configuration", planes[0]) != planes[0]:
            raise InvalidInput(f"only {planes[0]} was sent: the configuration is {planes[0]}",
                               field="options.configuration", accepted=planes[0])
        options["configuration"] = planes[0]
    options["mode"] = "track"
    options["initial_mesh_to_world"] = previous.result["mesh_to_world"]
    options["reference_mesh_to_world"] = _reference(previous)
    return parse_options_json(options)


def carried_origins(previous: JobRecord, planes: tuple[str, ...]) -> dict[str, str]:
    """Plane not sent again → the job whose run its image is: the job it was first sent with (the previous job's
    own ``carried_from`` when it had carried that plane too, else the previous job)."""
    rows = {row.get("role"): row for row in ((previous.case or {}).get("inputs") or [])}
    return {plane: (rows.get(plane) or {}).get("carried_from") or previous.id for plane in planes}


def _stored_files(ctx: ServiceContext, previous: JobRecord, roles: tuple[str, ...]) -> dict[str, list[Upload]]:
    """The previous job's stored files of ``roles`` (its model, mesh or volume; a plane not sent) as uploads by role."""
    files: dict[str, list[Upload]] = {}
    for item in previous.inputs:
        if item.role in roles:
            data = ctx.blobs.read(item.sha256)
            files.setdefault(item.role, []).append(Upload(f"{item.role}{item.suffix}", io.BytesIO(data), len(data)))
    return files


@router.post("/v1/registrations/{job_id}/track", **TRACK_DOC)
async def track(request: Request, ctx: Ctx, previous: OwnedJob, who: Principal) -> Response:
    if previous.status != "succeeded" or not previous.result or "mesh_to_world" not in previous.result:
        raise Problem(409, f"only a succeeded job can be tracked from: this one is {previous.status}",
                      kind="job-not-succeeded", extra={"job_status": previous.status})
    key = idempotency_key(request)
    if not request.headers.get("content-type", "").lower().startswith("multipart/form-data"):
        raise Problem(415, "send multipart/form-data with the files ap and/or lat", accepted="multipart/form-data")
    form = await read_form(request, max_files=6, max_fields=5)
    try:
        unknown = sorted(set(form.keys()) - {"ap", "lat", "options", "callback_url"})
        if unknown:
            raise InvalidInput(f"unknown form field(s) {unknown[:5]}; the model and geometry are the job's",
                               field=str(unknown[0])[:64], accepted="ap, lat, options, callback_url")
        sent = file_parts(form, PLANES)
        if not sent:
            raise InvalidInput("send the new run of a plane: ap, lat or both", field="ap", accepted="ap and/or lat")
        callback_url = form_callback_url(ctx, form)
        options = await asyncio.to_thread(_options, previous, form, tuple(sent))
        carried = carried_origins(previous, tuple(plane for plane in PLANES if plane not in sent))
        files = checked_roles({**_stored_files(ctx, previous, ("mesh", "volume", *carried)), **sent})
        geometry = canonical_geometry(previous.geometry)  # the job's, as stored (parsed once at its submission)
        # the new job records its previous one: its status, result and 202 carry Link: rel="previous"
        return await accept_files(ctx, FileRequest(files, geometry, options, callback_url=callback_url,
                                                   previous_id=previous.id, carried=carried), who, key)
    finally:
        await form.close()

"""``POST /v1/registrations/{job_id}/track``: re-register a finished job's model to a new AP/LAT pair.

During an intervention the patient moves; the client sends only the new images. The new job
re-uses the previous job's stored model files (mesh or volume) and geometry, starts from its
result's ``mesh_to_world`` with ``options.mode = "track"`` (one start, a short schedule), and its
result carries ``metrics.motion`` (rotation in degrees, translation in mm since the previous pose).
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
    "required": ["ap", "lat"],
    "properties": {
        "ap": {"type": "string", "format": "binary", "description": "New AP image or vessel mask (same rig as the job)."},
        "lat": {"type": "string", "format": "binary", "description": "New LAT image or vessel mask."},
        "options": {"type": "string", "description": "RegistrationOptions overriding the job's (JSON); mode is 'track', "
                                                     "the initial pose is the job's result.",
                    "example": "{\"max_iterations\": 60}"},
        "callback_url": {"type": "string", "maxLength": 2048,
                         "description": "POSTed the new job's summary once it ends (as for POST /v1/registrations)."},
    },
}
INHERITED_OUT = ("ground_truth_mesh_to_world", "initial_mesh_to_world", "mode", "starts")
"""Options of the previous job that do not carry over: its truth, its start, its mode."""

TRACK_DOC = {
    "status_code": 202,
    "response_model": JobStatus,
    "summary": "Re-register the job's model to a new AP/LAT pair (motion tracking)",
    "description": (
        "multipart/form-data with `ap`, `lat` and optional `options`. The job must have succeeded; its model and "
        "geometry are re-used and its result pose is the starting pose. Answers 202 with the new job's "
        "`Location`; its result has the new `mesh_to_world` and `metrics.motion` (`rotation_deg`, "
        "`translation_mm`, `mean_displacement_mm`) since the previous pose."
    ),
    "openapi_extra": {"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": TRACK_SCHEMA}}},
                   "parameters": [{"name": "Idempotency-Key", "in": "header", "required": False,
                                   "schema": {"type": "string", "maxLength": 255}}]},
    "responses": {202: {"description": "Accepted; poll the Location.", "headers": {
        "Location": {"description": "The new job's URL.", "schema": {"type": "string"}}}},
        **problem_responses(400, 401, 404, 408, 409, 413, 415, 422, 429, 503, 507)},
}


def _options(previous: JobRecord, form: Any) -> Any:
    """The new job's options: the previous job's (less INHERITED_OUT), the form's, mode track, its pose.

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
    options["mode"] = "track"
    options["initial_mesh_to_world"] = previous.result["mesh_to_world"]
    return parse_options_json(options)


def _model_files(ctx: ServiceContext, previous: JobRecord) -> dict[str, list[Upload]]:
    """The previous job's stored model files (mesh or volume) as uploads by role."""
    files: dict[str, list[Upload]] = {}
    for item in previous.inputs:
        if item.role in ("mesh", "volume"):
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
        raise Problem(415, "send multipart/form-data with the files ap and lat", accepted="multipart/form-data")
    form = await read_form(request, max_files=6, max_fields=5)
    try:
        unknown = sorted(set(form.keys()) - {"ap", "lat", "options", "callback_url"})
        if unknown:
            raise InvalidInput(f"unknown form field(s) {unknown[:5]}; the model and geometry are the job's",
                               field=str(unknown[0])[:64], accepted="ap, lat, options, callback_url")
        callback_url = form_callback_url(ctx, form)
        options = await asyncio.to_thread(_options, previous, form)
        files = checked_roles({**_model_files(ctx, previous), **file_parts(form, ("ap", "lat"))})
        geometry = canonical_geometry(previous.geometry)  # the job's, as stored (parsed once at its submission)
        # the new job records its previous one: its status, result and 202 carry Link: rel="previous"
        return await accept_files(ctx, FileRequest(files, geometry, options, callback_url=callback_url,
                                                   previous_id=previous.id), who, key)
    finally:
        await form.close()

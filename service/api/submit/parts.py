"""The parts of a submission request → the intake's typed inputs (:mod:`service.intake.submission`).

What only HTTP has is checked here: the ``Idempotency-Key`` header, which form fields exist and are files,
text parts sent as files. What any submission could get wrong (roles, options, callback URL) is the
intake's to refuse.
"""

from __future__ import annotations

from typing import Any

from fastapi import Request
from starlette.datastructures import UploadFile

from ...budgets import parse_json_part
from ...engine_adapter import submitted_geometry
from ...intake.context import IntakeContext
from ...intake.refusals import InvalidInput
from ...intake.submission import FILE_ROLES, Upload, checked_callback_url, parse_options_json
from ...problems import Problem
from .forms import MAX_TEXT_PART_BYTES

MAX_GEOMETRY_BYTES = MAX_TEXT_PART_BYTES
MAX_OPTIONS_BYTES = MAX_TEXT_PART_BYTES
MAX_VOLUME_FILES = 4000
FORM_FIELDS = ("mesh", "volume", "ap", "lat", "geometry", "options", "callback_url")


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


def file_parts(form: Any, roles: tuple[str, ...] = FILE_ROLES) -> dict[str, list[Upload]]:
    """The file parts of ``roles`` in a form, as the intake's uploads (a text field there is refused)."""
    files: dict[str, list[Upload]] = {}
    for name in roles:
        values = form.getlist(name)
        for value in values:
            if not isinstance(value, UploadFile):
                raise InvalidInput("must be a file part (with a filename)", field=name)
        if values:
            files[name] = [Upload(value.filename, value.file, value.size) for value in values]
    return files


def form_files(form: Any) -> dict[str, list[Upload]]:
    """The file parts of a submission form, only known fields."""
    unknown = sorted(set(form.keys()) - set(FORM_FIELDS))
    if unknown:
        raise InvalidInput(f"unknown form field(s) {unknown[:5]}", field=str(unknown[0])[:64],
                           accepted=", ".join(FORM_FIELDS))
    return file_parts(form)


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


def form_callback_url(ctx: IntakeContext, form: Any) -> str | None:
    values = form.getlist("callback_url")
    if len(values) > 1:
        raise InvalidInput("give callback_url at most once", field="callback_url")
    if values and isinstance(values[0], UploadFile):
        raise InvalidInput("must be a text field, not a file", field="callback_url")
    return checked_callback_url(ctx, values[0] if values else None)

"""Limits on what a submission may ask of the service, checked before it is accepted.

* JSON parts (``geometry``, ``options``): Python's ``json`` recurses once per nesting level
  (10,000 levels raise ``RecursionError``) and refuses integers over 4,300 digits with a
  bare ``ValueError``; both used to reach the generic 500 handler. :func:`parse_json_part`
  bounds depth, number length and non-finite constants first and refuses the part by name
  (:class:`service.intake.refusals.InvalidInput`, an HTTP 422).
* Jobs whose estimated cost is above ``max_job_cost`` are refused at submission
  (:func:`check_job_cost`) instead of failing later in a worker; options the worker would reject
  (a non-rigid or NaN ``initial_mesh_to_world``…) are refused by
  :func:`service.engine_adapter.check_options`, which asks the engine.
* Images: :func:`image_decoded_bytes` reads only the header and gives pixels × channels ×
  bytes per sample, so a small file that decodes to gigabytes is refused before decoding
  (see :func:`service.engine_adapter.check_image_budget`, called by :func:`service.engine_adapter.stored_case_files`).
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
from typing import Any

from .intake.refusals import InvalidInput

MAX_JSON_DEPTH = 32
MAX_NUMBER_CHARS = 40
_STRINGS = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
_BRACKETS = re.compile(r"[\[\]{}]")


def json_depth(text: str) -> int:
    """Deepest nesting of arrays/objects in JSON text (strings ignored); linear, no recursion."""
    depth = deepest = 0
    for match in _BRACKETS.finditer(_STRINGS.sub("", text)):
        depth += 1 if match.group() in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def _number(kind: type) -> Any:
    def parse(token: str) -> Any:
        if len(token) > MAX_NUMBER_CHARS:
            raise ValueError(f"a number has {len(token)} characters (at most {MAX_NUMBER_CHARS})")
        value = kind(token)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"the number {token} is out of range")
        return value
    return parse


def _constant(token: str) -> Any:
    raise ValueError(f"{token} is not allowed (strict JSON has no NaN or Infinity)")


def parse_json_part(text: str, field: str, *, want_object: bool = True) -> Any:
    """Parse a JSON form part with bounded depth and numbers; 422 naming ``field`` otherwise."""
    accepted = f"a JSON object, nested at most {MAX_JSON_DEPTH} levels, numbers of at most {MAX_NUMBER_CHARS} characters"
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise InvalidInput(f"is nested {depth} levels deep (at most {MAX_JSON_DEPTH})", field=field, accepted=accepted)
    try:
        data = json.loads(text, parse_int=_number(int), parse_float=_number(float), parse_constant=_constant)
    except json.JSONDecodeError as exc:
        raise InvalidInput(f"is not valid JSON ({exc.msg} at line {exc.lineno})", field=field, accepted=accepted) from None
    except (ValueError, RecursionError) as exc:
        raise InvalidInput(f"is not acceptable JSON: {str(exc)[:200]}", field=field, accepted=accepted) from None
    if want_object and not isinstance(data, dict):
        raise InvalidInput("must be a JSON object", field=field, accepted=accepted)
    return data


# ---- options ------------------------------------------------------------------------------------


def job_cost(options: Any, view_sizes: list[tuple[int, int]]) -> float:
    """Upper estimate of a job's work: starts × iterations × final-stage pixels of every view.

    ``view_sizes`` are the images' (width, height); ``working_size_px`` rescales the longest side.
    """
    pixels = 0.0
    for width, height in view_sizes:
        scale = options.working_size_px / max(width, height) if options.working_size_px else 1.0
        pixels += width * height * scale * scale
    return float(options.starts) * float(options.max_iterations) * pixels


def check_job_cost(options: Any, view_sizes: list[tuple[int, int]], limit: float) -> None:
    if not limit or not view_sizes:
        return
    cost = job_cost(options, view_sizes)
    if cost > limit:
        raise InvalidInput(
            f"this job would cost about {cost:.3g} pixel-iterations (starts × max_iterations × pixels of "
            f"the views at working_size_px), above this server's limit of {limit:.3g}",
            field="options", kind="job-too-expensive",
            accepted="fewer starts, fewer max_iterations or a smaller working_size_px")


# ---- images -------------------------------------------------------------------------------------

_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def _png_decoded_bytes(data: bytes) -> int | None:
    if len(data) < 26 or data[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", data[16:24])
    bits, color = data[24], data[25]
    channels = _PNG_CHANNELS.get(color, 4)
    return width * height * channels * max(1, math.ceil(bits / 8))


def _pillow_decoded_bytes(data: bytes) -> int | None:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:  # header only
            bands = len(image.getbands())
            per_band = 4 if image.mode in ("I", "F") else 2 if image.mode.startswith("I;16") else 1
            bits = image.tag_v2.get(258) if hasattr(image, "tag_v2") else None  # TIFF BitsPerSample
            if bits:
                per_band = max(per_band, math.ceil(max(bits if isinstance(bits, tuple) else (bits,)) / 8))
                bands = max(bands, len(bits) if isinstance(bits, tuple) else 1)
            return image.size[0] * image.size[1] * bands * per_band
    except Exception:  # noqa: BLE001 - not an image Pillow knows: the engine's reader decides
        return None


def _dicom_decoded_bytes(data: bytes) -> int | None:
    try:
        import pydicom

        ds = pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True, force=True)
        rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
        samples = int(ds.get("SamplesPerPixel", 1) or 1)
        bits = int(ds.get("BitsAllocated", 16) or 16)
        frames = int(str(ds.get("NumberOfFrames", 1) or 1))
        return rows * cols * samples * max(1, math.ceil(bits / 8)) * max(1, frames)
    except Exception:  # noqa: BLE001 - the engine's reader reports what is wrong with it
        return None


def image_decoded_bytes(data: bytes) -> int | None:
    """Bytes the pixels of an image need once decoded, from its header only (None: unknown)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return _png_decoded_bytes(data)
    if data[:2] in (b"\xff\xd8", b"II", b"MM"):
        return _pillow_decoded_bytes(data)
    if data[128:132] == b"DICM":
        return _dicom_decoded_bytes(data)
    return None

"""2D X-ray images: PNG / TIFF / JPEG, ``.rad`` + ``.raw`` float images, DICOM XA.

The pixel count is checked from the header before anything is decoded (a PNG of a
few hundred bytes can declare 50,000 × 50,000 pixels). Images come back as float32
``(H, W)``; colour is reduced to luminance; DICOM ``MONOCHROME1`` is inverted so that
higher values are brighter on every input. ``is_mask`` is true when the pixels take
at most two values (an exported segmentation).

Multi-frame DICOM XA: a native (unsubtracted) run is subtracted by its recipe in the log
domain, with the patient motion corrected (:mod:`.xa_run`). A subtracted run is read as
stored: ``frame`` picks a frame (0-based), ``None`` picks the frame of maximum vessel
opacification (the frame furthest below the per-pixel brightest value over the run, i.e.
most contrast in the vessels, which are dark), and ``"minip"`` takes the per-pixel minimum
over all frames.
"""

from __future__ import annotations

import io
import struct
import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import ViewGeometry
from . import rad as rad_format
from .dicom_identity import DicomIdentity, identity_or_none, parse_dicom
from .input_decisions import InputDecision
from .limits import DEFAULT_LIMITS, InputLimits
from .xa_run import RunReading

_ACCEPTED = "PNG, TIFF, JPEG, DICOM (XA), or a .rad header with its .raw"


@dataclass
class LoadedImage:
    """One 2D image as the engine uses it."""

    pixels: np.ndarray  # float32 (H, W)
    is_mask: bool
    geometry: ViewGeometry | None
    kind: str
    warnings: list[str] = field(default_factory=list)
    reading: dict = field(default_factory=dict)  # multi-frame XA: what was read and done (xa_run)
    dicom: DicomIdentity | None = None  # DICOM: what the DICOM outputs refer to (taken from the one parse)
    dicom_unreadable: bool = False  # DICOM whose identity attributes could not be converted
    decisions: list[InputDecision] = field(default_factory=list)  # what was decided about the input (input_decisions)
    # DICOM: True where the detector sees the patient (Shutter / Collimator modules, io/xa_shutter), or None
    field_of_view: np.ndarray | None = None
    annotation_mask: np.ndarray | None = None  # DICOM: graphics overlay planes drawn over the image, or None
    geometry_tags: dict = field(default_factory=dict)  # DICOM: the C-arm geometry tags found (dicom_xa.geometry_found)

    @property
    def image_size(self) -> tuple[int, int]:
        return (int(self.pixels.shape[1]), int(self.pixels.shape[0]))


def detect_image_format(data: bytes) -> str | None:
    head = data[:16]
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[128:132] == b"DICM":  # before TIFF: a dual-personality file (PS3.10) has a TIFF header in its preamble
        return "dicom"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if rad_format.looks_like_rad(data[:4096]):
        return "rad"
    return None


def _is_binary(pixels: np.ndarray) -> bool:
    values = np.unique(pixels[:: max(1, pixels.shape[0] // 512), :: max(1, pixels.shape[1] // 512)])
    if len(values) > 2:
        return False
    return len(np.unique(pixels)) <= 2


def _check_pixels(width: int, height: int, limits: InputLimits, field_name: str) -> None:
    if width < 1 or height < 1:
        raise DsaregInputError(f"declares an empty image ({width}x{height})", field=field_name)
    if width * height > limits.max_image_pixels:
        raise DsaregInputError(
            f"declares {width}x{height} pixels, above the limit of {limits.max_image_pixels / 1e6:.0f} megapixels",
            field=field_name,
        )


def read_image(
    data: bytes | list[bytes],
    name: str | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
    *,
    frame: int | str | None = None,
    field_name: str = "image",
    reading: RunReading | None = None,
) -> LoadedImage:
    """Read one 2D image; a list of two parts is a ``.rad`` header and its ``.raw``.

    ``reading`` (multi-frame DICOM XA): frame choice and subtraction of native runs
    (:class:`.xa_run.RunReading`; default: ``frame``, automatic subtraction).

    Raises:
        DsaregInputError: empty, truncated, unknown format, too many pixels, no pixel data.
    """
    if reading is not None:
        frame = reading.frame
    if isinstance(data, (list, tuple)):
        parts = [bytes(p) for p in data]
        if len(parts) == 1:
            return read_image(parts[0], name, limits, frame=frame, field_name=field_name, reading=reading)
        headers = [p for p in parts if rad_format.looks_like_rad(p[:4096])]
        if len(parts) != 2 or len(headers) != 1:
            raise DsaregInputError("give one image file, or a .rad header and its .raw", field=field_name)
        raw = parts[1] if parts[0] is headers[0] else parts[0]
        return read_rad_image(headers[0], raw, limits, field_name=field_name)
    if not data:
        raise DsaregInputError("the file is empty", field=field_name, accepted=_ACCEPTED)
    fmt = detect_image_format(data)
    if fmt is None and name and name.lower().endswith((".dcm", ".dicom", ".ima")):
        fmt = "dicom"
    elif fmt in ("png", "jpeg", "tiff") and name and name.lower().endswith((".dcm", ".dicom", ".ima")):
        shown = name.replace("\\", "/").rsplit("/", 1)[-1]  # a renamed picture: say so, not "no geometry" later
        raise DsaregInputError(f"{shown} is a {fmt.upper()} image, not DICOM", field=field_name,
                               accepted="the DICOM file itself, or the picture under its own extension with a geometry")
    if fmt in ("png", "jpeg", "tiff"):
        from .xa_pixels import caught_warnings

        caught: list[str] = []
        with caught_warnings(caught, field_name):  # Pillow's warnings (corrupt EXIF, ...) are the image's, not stderr
            loaded = _read_raster(data, fmt, name, limits, frame, field_name)
        loaded.warnings.extend(caught)
        return loaded
    if fmt == "dicom":
        return read_dicom_image(data, limits, frame=frame, field_name=field_name, reading=reading)
    if fmt == "rad":
        raise DsaregInputError("a .rad header needs its .raw file too (send both)", field=field_name)
    if name and name.lower().endswith(".raw"):
        raise DsaregInputError("a .raw file needs its .rad header too (send both)", field=field_name)
    raise DsaregInputError("content is not a recognised image format", field=field_name, accepted=_ACCEPTED)


def _png_size(data: bytes) -> tuple[int, int] | None:
    if len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    return None


def tiff_page_count(data: bytes, cap: int) -> int:
    """Pages of a TIFF (or BigTIFF) counted from its IFD chain without decoding anything; stops
    counting past ``cap`` (a 19 MB file can hold 80,000 pages, which Pillow's ``n_frames`` walks in
    about a minute). A chain that loops or leaves the file ends the count."""
    big = data[2:4] in (b"+\x00", b"\x00+")
    order = "<" if data[:2] == b"II" else ">"
    offset_format, count_format, entry_bytes = ("Q", "Q", 20) if big else ("I", "H", 12)
    offset_size, count_size = struct.calcsize(offset_format), struct.calcsize(count_format)
    start = 8 if big else 4
    if len(data) < start + offset_size:
        return 0
    offset = struct.unpack_from(order + offset_format, data, start)[0]
    seen: set[int] = set()
    while offset and offset not in seen and offset + count_size <= len(data) and len(seen) <= cap:
        seen.add(offset)
        entries = struct.unpack_from(order + count_format, data, offset)[0]
        next_at = offset + count_size + entries * entry_bytes
        if next_at + offset_size > len(data):
            break
        offset = struct.unpack_from(order + offset_format, data, next_at)[0]
    return len(seen)


def _check_pages(data: bytes, fmt: str, limits: InputLimits, field_name: str) -> int | None:
    """The page count of a multi-page format from its header (None: single-page formats), refused above the limit."""
    if fmt != "tiff":
        return None
    pages = tiff_page_count(data, limits.max_image_pages)
    if pages > limits.max_image_pages:
        raise DsaregInputError(f"has more than {limits.max_image_pages} pages", field=field_name,
                               accepted=f"a TIFF of at most {limits.max_image_pages} pages (the first is used)")
    return pages


def _read_raster(data, fmt, name, limits, frame, field_name) -> LoadedImage:
    from PIL import Image

    warnings: list[str] = []
    if name and "." in name:
        extension = name.rsplit(".", 1)[-1].lower()
        named = {"png": "png", "jpg": "jpeg", "jpeg": "jpeg", "tif": "tiff", "tiff": "tiff"}.get(extension)
        if named is not None and named != fmt:
            warnings.append(f"{field_name}: the file is named '.{extension}' but its content is {fmt.upper()}")
    if fmt == "png":
        size = _png_size(data)
        if size is None:
            raise DsaregInputError("PNG is truncated (no IHDR header)", field=field_name)
        _check_pixels(size[0], size[1], limits, field_name)
    pages = _check_pages(data, fmt, limits, field_name)
    try:
        with _warnings.catch_warnings():
            _warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data))
            _check_pixels(image.size[0], image.size[1], limits, field_name)  # header only, nothing decoded yet
            n_frames = pages or int(getattr(image, "n_frames", 1))  # TIFF: counted from the header above
            if isinstance(frame, int):
                if not 0 <= frame < n_frames:
                    raise DsaregInputError(f"frame {frame} does not exist ({n_frames} frames)", field=field_name)
                image.seek(frame)
            elif n_frames > 1:
                warnings.append(f"{field_name}: {n_frames} pages; the first is used")
            image.load()
    except DsaregInputError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise DsaregInputError("declares too many pixels (decompression bomb)", field=field_name) from None
    except Exception as exc:
        raise DsaregInputError(
            f"{fmt.upper()} data is unreadable or truncated ({str(exc)[:200]})", field=field_name
        ) from None
    if image.mode in ("I;16", "I;16B", "I;16L", "I", "F", "L", "1"):
        pixels = np.asarray(image, dtype=np.float32)
    elif image.mode in ("LA", "P", "PA"):
        pixels = np.asarray(image.convert("L"), dtype=np.float32)
    else:
        rgb = np.asarray(image.convert("RGB"), dtype=np.float32)
        pixels = rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    if pixels.ndim != 2:
        raise DsaregInputError(f"has an unsupported layout {pixels.shape}", field=field_name)
    pixels = np.ascontiguousarray(pixels, dtype=np.float32)
    if not np.all(np.isfinite(pixels)):
        raise DsaregInputError("contains NaN or infinite pixels", field=field_name)
    return LoadedImage(pixels, _is_binary(pixels) and fmt != "jpeg", None, fmt, warnings)


def read_rad_image(
    header_bytes: bytes, raw: bytes, limits: InputLimits = DEFAULT_LIMITS, *, field_name: str = "image"
) -> LoadedImage:
    header = rad_format.parse_rad_header(header_bytes, field_name=f"{field_name}.rad")
    if header.ndim != 2:
        raise DsaregInputError("the .rad header describes a volume, not an image", field=field_name)
    _check_pixels(header.size[0], header.size[1], limits, field_name)
    pixels = rad_format.read_raw(header, raw, max_bytes=limits.max_image_pixels * 8, field_name=f"{field_name}.raw")
    if not np.all(np.isfinite(pixels)):
        raise DsaregInputError("contains NaN or infinite pixels", field=f"{field_name}.raw")
    warnings = []
    geometry = None
    if header.tposition is not None and header.source_position is not None:
        geometry = rad_format.view_from_rad(header, field_name=f"{field_name}.rad")
    else:
        warnings.append(f"{field_name}: the .rad header has no TPosition/SourcePosition; no geometry")
    return LoadedImage(pixels, _is_binary(pixels), geometry, "rad", warnings)


def dicom_number(dataset, keyword: str, default, field_name: str, *, kind: type = int):
    """A numeric DICOM attribute (``default`` when absent or empty); a value that is not a finite number
    of ``kind`` (``NumberOfFrames "abc"``, ``RescaleSlope "abc"``) is an input error naming the image."""
    try:
        value = getattr(dataset, keyword, None)
    except Exception:  # noqa: BLE001 - pydicom converts lazily: a malformed value raises here
        value = "(unreadable)"
    if value is None or value == "":
        return default
    try:
        number = float(value)
        if not np.isfinite(number) or (kind is int and number != int(number)):
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise DsaregInputError(f"the DICOM attribute {keyword} is {str(value)[:40]!r}, not a number", field=field_name,
                               accepted=f"{keyword} as {'a whole number' if kind is int else 'a finite decimal number'}"
                               ) from None
    return kind(number)


def _dicom_stack(data: bytes, limits: InputLimits, field_name: str):
    """``(dataset, frames (N, H, W) after the rescale)``: header checked before anything is decoded, the modality
    checked (:func:`.xa_pixels.check_modality`), the pixels decoded in any transfer syntax (:mod:`.xa_pixels`)."""
    from .xa_pixels import check_modality, decode_pixels

    header, failure = parse_dicom(data, field_name)
    rows, cols = dicom_number(header, "Rows", 0, field_name), dicom_number(header, "Columns", 0, field_name)
    if rows < 1 or cols < 1:
        raise DsaregInputError("DICOM file has no image (Rows/Columns missing)", field=field_name)
    _check_pixels(cols, rows, limits, field_name)
    n_frames = dicom_number(header, "NumberOfFrames", 1, field_name)
    samples = dicom_number(header, "SamplesPerPixel", 1, field_name)
    if n_frames < 1 or samples < 1:
        raise DsaregInputError(f"declares {n_frames} frames of {samples} samples", field=field_name,
                               accepted="NumberOfFrames and SamplesPerPixel of at least 1")
    if n_frames * rows * cols * samples * 4 > limits.max_volume_bytes:
        raise DsaregInputError(f"declares {n_frames} frames of {cols}x{rows}, above the size limit", field=field_name)
    check_modality(header, field_name)
    if failure is not None:
        raise DsaregInputError(f"DICOM is unreadable or truncated ({failure})", field=field_name)
    dataset = header
    if "PixelData" not in dataset:
        raise DsaregInputError("DICOM file has no pixel data", field=field_name)
    stack = np.asarray(decode_pixels(dataset, field_name), dtype=np.float32)
    if samples > 1:
        stack = stack @ np.array([0.299, 0.587, 0.114], dtype=np.float32)[: stack.shape[-1]]
    if stack.ndim == 2:
        stack = stack[None]
    if stack.ndim != 3 or stack.shape[1:] != (rows, cols):
        raise DsaregInputError(f"DICOM pixel data has shape {list(stack.shape)}", field=field_name)
    slope = dicom_number(dataset, "RescaleSlope", 1.0, field_name, kind=float)
    intercept = dicom_number(dataset, "RescaleIntercept", 0.0, field_name, kind=float)
    return dataset, stack * slope + intercept


def _field_of_view(dataset, shape_rc, frame, field_name: str):
    """``(field of view, annotation mask, decisions, warnings)`` from the Shutter / Collimator modules and the
    overlay planes (:mod:`.xa_shutter`)."""
    from .xa_shutter import field_of_view_details, overlay_annotation_mask

    fov, applied, notes = field_of_view_details(dataset, shape_rc, frame)
    warnings = [f"{field_name}: {note}" for note in notes]
    decisions = []
    if fov is not None:
        share = float(fov.mean())
        decisions.append(InputDecision(field_name, "field of view", " and ".join(applied),
                                       f"the file's Shutter / Collimator modules; {share:.0%} of the image inside",
                                       source="tag"))
    annotation = overlay_annotation_mask(dataset, shape_rc)
    burned = str(getattr(dataset, "BurnedInAnnotation", "") or "").strip().upper()
    if burned == "YES":
        warnings.append(f"{field_name}: Burned In Annotation is YES: text or marks are drawn into the pixels")
    return fov, annotation, decisions, warnings


def read_dicom_image(
    data: bytes, limits: InputLimits = DEFAULT_LIMITS, *, frame: int | str | None = None, field_name: str = "image",
    reading: RunReading | None = None,
) -> LoadedImage:
    """A 2D image (and its C-arm geometry when the tags are there) from DICOM XA.

    A multi-frame run is read by :func:`.xa_run.read_run` (``reading``; default: ``frame`` with
    automatic subtraction of native runs); the geometry comes from the frame used. The warnings pydicom
    raises while reading become the image's warnings; the Shutter / Collimator modules give its field
    of view (:mod:`.xa_shutter`).
    """
    from .dicom_xa import geometry_found, view_from_xa
    from .xa_pixels import caught_warnings
    from .xa_run import read_run, subtracted_record

    library_warnings: list[str] = []
    with caught_warnings(library_warnings, field_name):
        dataset, stack = _dicom_stack(data, limits, field_name)
        reading = reading if reading is not None else RunReading(frame=frame)
        native, call = read_run(stack, dataset, reading, field_name)
        if native is not None:
            pixels, chosen, record, warnings = native.pixels, native.geometry_frame, native.record, native.warnings
            decisions = native.decisions
        else:
            pixels, chosen, warnings = _stored_frame(stack, dataset, reading.frame, field_name)
            record = subtracted_record(len(stack), chosen, reading.frame, call.why, call.kind)
            decisions = [call.decision] if call.decision is not None else []
        relationship = str(getattr(dataset, "PixelIntensityRelationship", "") or "").strip().upper()
        if relationship:
            record.setdefault("pixel_intensity_relationship", relationship)
        geometry, geometry_warnings = view_from_xa(dataset, chosen, field_name=field_name)
        found = geometry_found(dataset, chosen)
        fov, annotation, fov_decisions, fov_warnings = _field_of_view(dataset, stack.shape[1:], chosen, field_name)
        identity, unreadable = identity_or_none(dataset)
    warnings.extend(geometry_warnings + fov_warnings + library_warnings)
    pixels = np.ascontiguousarray(pixels, dtype=np.float32)
    return LoadedImage(
        pixels, _is_binary(pixels), geometry, "dicom-xa" if len(stack) == 1 else "dicom-xa-multiframe", warnings,
        reading=record, dicom=identity, dicom_unreadable=unreadable, decisions=decisions + fov_decisions,
        field_of_view=fov, annotation_mask=annotation, geometry_tags=found,
    )


def _stored_frame(stack: np.ndarray, dataset, frame, field_name: str) -> tuple[np.ndarray, int | None, list[str]]:
    """A subtracted run (or one frame) as stored: ``(pixels, frame used, warnings)``."""
    if str(getattr(dataset, "PhotometricInterpretation", "")).upper() == "MONOCHROME1":
        stack = stack.max() - stack
    warnings: list[str] = []
    if frame == "minip":
        return stack.min(axis=0), None, warnings
    if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
        if not 0 <= frame < len(stack):
            raise DsaregInputError(
                f"frame {frame} does not exist ({len(stack)} frames)",
                field=field_name,
                accepted=f"0..{len(stack) - 1}, or 'minip'",
            )
        return stack[int(frame)], int(frame), warnings
    if frame is None:
        chosen = max_opacification_frame(stack)
        if len(stack) > 1:
            warnings.append(f"{field_name}: frame {chosen} of {len(stack)} used (maximum vessel opacification)")
        return stack[chosen], chosen, warnings
    raise DsaregInputError(
        f"frame option {frame!r} is not understood",
        field=field_name,
        accepted="a frame number, 'minip', or nothing (maximum opacification)",
    )


def max_opacification_frame(stack: np.ndarray) -> int:
    """Frame with the most contrast below the run's per-pixel maximum (vessels are dark)."""
    if len(stack) == 1:
        return 0
    step = max(1, max(stack.shape[1:]) // 256)
    small = stack[:, ::step, ::step].astype(np.float32)
    background = small.max(axis=0)
    darkening = background[None] - small
    # the strongest 5 % of darkening per frame: vessels, not global brightness drift
    flat = darkening.reshape(len(small), -1)
    k = max(1, flat.shape[1] // 20)
    score = np.partition(flat, flat.shape[1] - k, axis=1)[:, -k:].mean(axis=1) - np.median(flat, axis=1)
    return int(np.argmax(score))

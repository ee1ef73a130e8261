"""Header validation of one received DICOM instance, before it is kept or answered Success.

Checked from the encoded data set, never decoding the pixels (:func:`check_instance`):

* its size as received, and for Deflated Explicit VR Little Endian as inflated (bounded while
  inflating, :mod:`service.pacs.inflating_reader`): more than ``max_instance_bytes`` → 0xA700;
* the header parses (up to Pixel Data) → otherwise 0xC000 (cannot understand);
* its SOP Class / SOP Instance UIDs are those of the request, and the class is one we accept → 0xA900
  (data set does not match SOP class) otherwise;
* Study / Series / SOP Instance UIDs are well-formed (digits and dots, ≤ 64 characters) → 0xA900;
* an image has Rows, Columns and Bits Allocated, and Rows × Columns × Frames × Samples × Bits / 8 is at
  most ``max_pixel_bytes`` → 0xA700 (out of resources) past it, 0xA900 without them;
* native Pixel Data holds what the header says, and no element runs past the end → 0xC000 (truncated).

Statuses per PS3.4 B.2.3 (C-STORE): A7xx refused out of resources, A9xx data set does not match SOP
class, Cxxx cannot understand. :class:`InstanceRefused` carries the status and a reason for the log.
"""

from __future__ import annotations

import io
import re
import struct
from dataclasses import dataclass
from typing import Any

from .inflating_reader import InflateBoundExceeded, InflateError, inflate_bounded

OUT_OF_RESOURCES, DOES_NOT_MATCH, CANNOT_UNDERSTAND = 0xA700, 0xA900, 0xC000
DEFLATED = "1.2.840.10008.1.2.1.99"
IMPLICIT_LITTLE = "1.2.840.10008.1.2"
BIG_ENDIAN = "1.2.840.10008.1.2.2"
NO_PIXEL_CLASSES = {"1.2.840.10008.5.1.4.1.1.66.1"}  # Spatial Registration
HEADER_KEEP_BYTES = 32 << 20  # of an inflated data set, what the header may take at most
PIXEL_TAGS = (0x7FE00008, 0x7FE00009, 0x7FE00010)
UID_PATTERN = re.compile(r"^[0-9]+(\.[0-9]+)*$")
UID_MAX_CHARS = 64
SEQUENCE_DELIMITER = b"\xfe\xff\xdd\xe0\x00\x00\x00\x00"


@dataclass(frozen=True)
class InstanceLimits:
    max_instance_bytes: int
    max_pixel_bytes: int

    @classmethod
    def of(cls, settings: Any) -> InstanceLimits:
        return cls(settings.limits.max_dicom_instance_bytes, settings.limits.max_dicom_pixel_bytes)


class InstanceRefused(ValueError):
    def __init__(self, status: int, reason: str):
        super().__init__(reason)
        self.status, self.reason = status, reason


@dataclass(frozen=True)
class CheckedInstance:
    header: Any  # pydicom Dataset, up to Pixel Data
    study_uid: str
    series_uid: str
    sop_instance_uid: str
    sop_class_uid: str


def check_instance(data_set: bytes | memoryview, transfer_syntax: str, sop_class_uid: str, sop_instance_uid: str,
                   accepted_classes: set[str] | dict, limits: InstanceLimits) -> CheckedInstance:
    """The checked header of one encoded data set (no file meta), or :class:`InstanceRefused`."""
    if len(data_set) > limits.max_instance_bytes:
        raise InstanceRefused(OUT_OF_RESOURCES, f"larger than {limits.max_instance_bytes} bytes")
    plain, size = _plain(data_set, transfer_syntax, limits)
    header, pixels_at = _header(plain, transfer_syntax)
    checked = _identity(header, sop_class_uid, sop_instance_uid, accepted_classes)
    if checked.sop_class_uid not in NO_PIXEL_CLASSES:
        expected = _pixel_bytes(header, limits)
        _pixel_element(plain, pixels_at, size, expected, transfer_syntax)
    return checked


def check_file(data: Any, limits: InstanceLimits) -> Any:
    """The sizes of a DICOM file uploaded or fetched (Part 10: preamble, file meta, data set) checked as a received
    instance's are — bytes as received and inflated, pixel dimensions, truncation — without its identity (an
    upload's UIDs are not ours to judge); its header, or :class:`InstanceRefused`. Not DICOM: ``None``."""
    from pydicom.filereader import read_dataset

    if len(data) < 132 or bytes(data[128:132]) != b"DICM":
        return None
    if len(data) > limits.max_instance_bytes:
        raise InstanceRefused(OUT_OF_RESOURCES, f"larger than {limits.max_instance_bytes} bytes")
    stream = io.BytesIO(bytes(data[132:HEADER_KEEP_BYTES]))
    try:  # the file meta: group 0002, explicit VR little endian
        meta = read_dataset(stream, False, True, stop_when=lambda tag, vr, length: tag.group != 2)
        syntax = str(meta.TransferSyntaxUID)
    except Exception as exc:  # noqa: BLE001 - any unreadable file meta
        raise InstanceRefused(CANNOT_UNDERSTAND, f"the file meta does not parse ({type(exc).__name__})") from None
    plain, size = _plain(memoryview(data)[132 + stream.tell():], syntax, limits)
    header, pixels_at = _header(plain, syntax)
    if "Rows" in header:  # an image: its pixels within the bound, and all there
        _pixel_element(plain, pixels_at, size, _pixel_bytes(header, limits), syntax)
    return header


def _plain(data_set: bytes | memoryview, transfer_syntax: str, limits: InstanceLimits) -> tuple[bytes | memoryview, int]:
    """The data set as encoded without deflate (its first HEADER_KEEP_BYTES when deflated) and its full size."""
    if transfer_syntax != DEFLATED:
        return data_set, len(data_set)
    try:
        inflated = inflate_bounded(data_set, limits.max_instance_bytes, HEADER_KEEP_BYTES)
    except InflateBoundExceeded:
        raise InstanceRefused(OUT_OF_RESOURCES, f"inflates to more than {limits.max_instance_bytes} bytes") from None
    except InflateError as exc:
        raise InstanceRefused(CANNOT_UNDERSTAND, f"deflated data set: {exc}") from None
    return inflated.prefix, inflated.size_bytes


def _header(plain: bytes | memoryview, transfer_syntax: str) -> tuple[Any, int]:
    """The data set up to Pixel Data, and where Pixel Data starts (-1: none)."""
    from pydicom.filereader import read_dataset

    with memoryview(plain) as whole, whole[:HEADER_KEEP_BYTES] as part:
        stream = _ViewStream(part)  # reads what the header takes (was a copy of its first 32 MiB, pages all touched)
        try:
            header = read_dataset(stream, transfer_syntax == IMPLICIT_LITTLE, transfer_syntax != BIG_ENDIAN,
                                  stop_when=lambda tag, vr, length: int(tag) in PIXEL_TAGS)
            for element in header:  # force every value's decoding (a truncated value raises here)
                _ = element.value
        except Exception as exc:  # noqa: BLE001 - any undecodable header
            raise InstanceRefused(CANNOT_UNDERSTAND, f"the header does not parse ({type(exc).__name__})") from None
        at = stream.tell()
    return header, (at if at < min(len(plain), HEADER_KEEP_BYTES) else -1)


class _ViewStream(io.RawIOBase):
    """A seekable, read-only file over a memory view, copying only what is read."""

    def __init__(self, view: memoryview):
        super().__init__()
        self.view, self.at = view, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        count = max(0, min(len(buffer), len(self.view) - self.at))
        with memoryview(buffer) as out, self.view[self.at:self.at + count] as source:
            out[:count] = source
        self.at += count
        return count

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.at, io.SEEK_END: len(self.view)}[whence]
        self.at = max(0, base + offset)
        return self.at

    def tell(self) -> int:
        return self.at


def _uid(header: Any, keyword: str) -> str:
    value = str(getattr(header, keyword, "") or "").strip("\0 ")
    if not UID_PATTERN.match(value) or len(value) > UID_MAX_CHARS:
        raise InstanceRefused(DOES_NOT_MATCH, f"{keyword} is not a well-formed UID (digits and dots, "
                                              f"≤ {UID_MAX_CHARS} characters)")
    return value


def _identity(header: Any, sop_class_uid: str, sop_instance_uid: str, accepted: set[str] | dict) -> CheckedInstance:
    uids = {keyword: _uid(header, keyword) for keyword in
            ("SOPClassUID", "SOPInstanceUID", "StudyInstanceUID", "SeriesInstanceUID")}
    if uids["SOPClassUID"] not in accepted:
        raise InstanceRefused(DOES_NOT_MATCH, "SOP Class UID is not one this node stores")
    if uids["SOPClassUID"] != sop_class_uid or uids["SOPInstanceUID"] != sop_instance_uid:
        raise InstanceRefused(DOES_NOT_MATCH, "SOP Class / Instance UID differ from the C-STORE request's")
    return CheckedInstance(header, uids["StudyInstanceUID"], uids["SeriesInstanceUID"], uids["SOPInstanceUID"],
                           uids["SOPClassUID"])


def _pixel_bytes(header: Any, limits: InstanceLimits) -> int:
    """Rows × Columns × Frames × Samples × Bits Allocated / 8, within ``max_pixel_bytes``."""
    try:
        rows, columns, bits = int(header.Rows), int(header.Columns), int(header.BitsAllocated)
        frames = int(getattr(header, "NumberOfFrames", 1) or 1)
        samples = int(getattr(header, "SamplesPerPixel", 1) or 1)
    except (AttributeError, TypeError, ValueError):
        raise InstanceRefused(DOES_NOT_MATCH, "an image without readable Rows, Columns, Bits Allocated") from None
    if min(rows, columns, bits, frames, samples) < 1:
        raise InstanceRefused(DOES_NOT_MATCH, "Rows, Columns, Bits Allocated, Frames and Samples must be ≥ 1")
    size = (rows * columns * frames * samples * bits + 7) // 8
    if size > limits.max_pixel_bytes:
        raise InstanceRefused(OUT_OF_RESOURCES, f"its header says {size} bytes of pixels, more than "
                                                f"{limits.max_pixel_bytes}")
    return size


def _pixel_element(plain: bytes | memoryview, at: int, size: int, expected: int, transfer_syntax: str) -> None:
    """Pixel Data is there, fits in the data set and (native) holds ``expected`` bytes."""
    if at < 0:
        raise InstanceRefused(CANNOT_UNDERSTAND, "an image without Pixel Data (truncated?)")
    head = bytes(plain[at:at + 12])
    if transfer_syntax == IMPLICIT_LITTLE:
        if len(head) < 8:
            raise InstanceRefused(CANNOT_UNDERSTAND, "truncated in the Pixel Data element")
        length, start = struct.unpack("<I", head[4:8])[0], at + 8
    else:
        if len(head) < 12:
            raise InstanceRefused(CANNOT_UNDERSTAND, "truncated in the Pixel Data element")
        order = ">" if transfer_syntax == BIG_ENDIAN else "<"
        length, start = struct.unpack(order + "I", head[8:12])[0], at + 12
    if length == 0xFFFFFFFF:  # encapsulated: the fragments end with a sequence delimiter
        if transfer_syntax != DEFLATED and SEQUENCE_DELIMITER not in bytes(plain[-1024:]):
            raise InstanceRefused(CANNOT_UNDERSTAND, "encapsulated Pixel Data without its end (truncated)")
        return
    if start + length > size:
        raise InstanceRefused(CANNOT_UNDERSTAND, f"Pixel Data says {length} bytes, {size - start} follow (truncated)")
    if length < expected:
        raise InstanceRefused(DOES_NOT_MATCH, f"Pixel Data holds {length} bytes, its header says {expected}")


def refusal_of_file(path: Any, limits: InstanceLimits) -> str | None:
    """Why the DICOM file at ``path`` is refused (:func:`check_file`, read through a map), or None."""
    import contextlib
    import mmap
    import os

    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size < 132:
            return None
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            check_file(mapped, limits)
            return None
        except InstanceRefused as exc:
            return exc.reason
        finally:
            with contextlib.suppress(BufferError):  # a view still held: closed when it goes
                mapped.close()

"""What the DICOM writers need of the DICOM inputs, taken from them when they are read (never parsed again).

:class:`DicomIdentity` is one input instance's identity: its SOP class and instance, study, series and
frame of reference, and the patient and study attributes the outputs copy (``io/dicom_out.py``).
:class:`DicomSources` holds them for a case: the AP and LAT images and the volume's instances (in the
order given). The image and volume readers make them from the dataset they parse anyway
(:func:`identity_of`); :func:`read_sources` parses bytes for callers that hold files but no case.
"""

from __future__ import annotations

import copy
import io
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from .file_parts import PART_LISTS

# Patient module (and the Patient Study / clinical trial bits that travel with it), copied when present.
PATIENT_KEYWORDS = (
    "PatientName", "PatientID", "IssuerOfPatientID", "PatientBirthDate", "PatientSex", "OtherPatientIDsSequence",
    "PatientIdentityRemoved", "DeidentificationMethod", "DeidentificationMethodCodeSequence",
    "PatientAge", "PatientSize", "PatientWeight",
)
STUDY_KEYWORDS = (
    "StudyInstanceUID", "StudyDate", "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber",
    "StudyDescription",
)
SERIES_KEYWORDS = ("Modality", "SeriesNumber", "SeriesDescription")
"""Series attributes kept for the reviewer's view of the case (:mod:`.case_identity`), never written out."""


class UnreadableIdentity(ValueError):
    """A DICOM input whose identity attributes cannot be converted (the outputs cannot join its study)."""


@dataclass(frozen=True)
class DicomIdentity:
    """One DICOM input instance, as the REG and Secondary Capture writers refer to it.

    Attributes:
        sop_class_uid, sop_instance_uid: the instance (both present, else the input has no identity).
        study_instance_uid, series_instance_uid, frame_of_reference_uid: top-level values, or ``None``.
        patient: ``(keyword, value)`` of the :data:`PATIENT_KEYWORDS` present and non-empty, in that order
            (values as pydicom converts them; copied, never shared with the parsed dataset).
        study: the same for :data:`STUDY_KEYWORDS`.
        series: the same for :data:`SERIES_KEYWORDS` (modality, series number and description).
        image_type: the Image Type values, upper case (``SINGLE PLANE``, ``BIPLANE A`` ...): which plane took a run.
        start: when the run started (Acquisition DateTime, else Acquisition or Content Date + Time; a time without
            its date on :data:`TIME_ONLY_DAY`), or ``None``:
            two runs minutes apart were not acquired together (:mod:`.view_roles`).
    """

    sop_class_uid: str
    sop_instance_uid: str
    study_instance_uid: str | None = None
    series_instance_uid: str | None = None
    frame_of_reference_uid: str | None = None
    patient: tuple[tuple[str, Any], ...] = ()
    study: tuple[tuple[str, Any], ...] = ()
    series: tuple[tuple[str, Any], ...] = ()
    image_type: tuple[str, ...] = ()
    start: datetime | None = None


@dataclass(frozen=True)
class DicomSources:
    """The identities of a case's DICOM inputs; empty when no input is DICOM.

    ``unreadable`` names the inputs that are DICOM but whose identity could not be converted: the
    outputs then start a new study (or fail, when DICOM outputs are required).
    """

    ap: DicomIdentity | None = None
    lat: DicomIdentity | None = None
    volume: tuple[DicomIdentity, ...] = ()
    unreadable: tuple[str, ...] = ()

    @property
    def xa(self) -> list[DicomIdentity]:
        return [x for x in (self.ap, self.lat) if x is not None]

    @property
    def first(self) -> DicomIdentity | None:
        """The input whose study the outputs join: the AP XA, else the LAT, else the volume."""
        for identity in (*self.xa, *self.volume):
            return identity
        return None

    @property
    def volume_frame_uid(self) -> str | None:
        for identity in self.volume:
            if identity.frame_of_reference_uid:
                return identity.frame_of_reference_uid
        return None

    @property
    def xa_frame_uid(self) -> str | None:
        uids = {x.frame_of_reference_uid for x in self.xa if x.frame_of_reference_uid}
        return uids.pop() if len(uids) == 1 else None


def _present(dataset, keywords: tuple[str, ...]) -> tuple[tuple[str, Any], ...]:
    found = []
    for keyword in keywords:
        if keyword in dataset:
            value = dataset.data_element(keyword).value
            if value is not None and value != "":
                found.append((keyword, copy.deepcopy(value)))
    return tuple(found)


def _top(dataset, keyword: str) -> str | None:
    """A UID attribute's one value (None when absent or empty); several values are malformed (a UID has VM 1):
    :class:`UnreadableIdentity`, never their list's repr written into an output."""
    if keyword in dataset:
        value = dataset.data_element(keyword).value
        if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
            raise UnreadableIdentity(f"{keyword} holds {len(value)} values; a UID has one")
        return str(value) if value else None
    return None


def identity_of(dataset) -> DicomIdentity | None:
    """The identity of a parsed DICOM dataset (header only is enough); ``None`` without SOP class and instance.

    Raises:
        UnreadableIdentity: an attribute's value cannot be converted (pydicom converts lazily).
    """
    if dataset is None or "SOPInstanceUID" not in dataset or "SOPClassUID" not in dataset:
        return None
    try:
        return DicomIdentity(
            sop_class_uid=_top(dataset, "SOPClassUID") or "", sop_instance_uid=_top(dataset, "SOPInstanceUID") or "",
            study_instance_uid=_top(dataset, "StudyInstanceUID"), series_instance_uid=_top(dataset, "SeriesInstanceUID"),
            frame_of_reference_uid=_top(dataset, "FrameOfReferenceUID"),
            patient=_present(dataset, PATIENT_KEYWORDS), study=_present(dataset, STUDY_KEYWORDS),
            series=_present(dataset, SERIES_KEYWORDS), **_acquired(dataset))
    except UnreadableIdentity:
        raise
    except Exception as exc:  # noqa: BLE001 - a malformed value: no identity, said so
        raise UnreadableIdentity(str(exc)[:200]) from None


TIME_ONLY_DAY = datetime(1900, 1, 1)
"""The day of a :attr:`DicomIdentity.start` read from a time whose date is missing (only its time of day counts)."""


def _acquired(dataset) -> dict:
    """``image_type`` and ``start`` of :class:`DicomIdentity`; a value that does not convert is left out."""
    from ..hemodynamics.timing import parse_time_s, run_start

    found: dict = {}
    try:
        found["image_type"] = tuple(str(v).strip().upper() for v in (dataset.get("ImageType") or []))
        found["start"] = run_start(dataset)
        seconds = parse_time_s(dataset.get("AcquisitionTime") or dataset.get("ContentTime") or "")
        if found["start"] is None and seconds is not None:  # a time without its date: TIME_ONLY_DAY
            found["start"] = TIME_ONLY_DAY + timedelta(seconds=seconds)
    except Exception:  # noqa: BLE001 - an odd time or image type is no evidence either way
        pass
    return found


DEFER_BYTES = 64 * 1024
"""Values larger than this (the pixel data) are read from the buffer when used, not copied by the parse."""


def parse_dicom(data: bytes, field_name: str):
    """One parse of a DICOM file: ``(dataset, None)``, or ``(header, why)`` when only the header parses.

    The full dataset is parsed once with large values deferred, so the readers check the header, decode
    the pixels and take the :class:`DicomIdentity` from the same parse. Only a file whose full parse fails
    is parsed again, header only, to tell "not DICOM" from "truncated pixel data".

    Raises:
        DsaregInputError: not readable as DICOM at all.
    """
    import pydicom

    from ..errors import DsaregInputError

    try:
        return pydicom.dcmread(io.BytesIO(data), force=True, defer_size=DEFER_BYTES), None
    except Exception as exc:  # noqa: BLE001 - told apart below
        failure = str(exc)[:200]
    try:
        return pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True, force=True), failure
    except Exception as exc:  # noqa: BLE001
        raise DsaregInputError(f"is not readable DICOM ({str(exc)[:200]})", field=field_name) from None


def parse_header(data: bytes, field_name: str):
    """A DICOM file's header (everything before the pixel data) that holds no reference to ``data``: a series' headers
    are all read before its pixels (:func:`.volume_io.read_dicom_series`), and a whole head's files are 0.23 GB.

    Raises:
        DsaregInputError: not readable as DICOM at all (as :func:`parse_dicom`).
    """
    import pydicom

    from ..errors import DsaregInputError

    stream = io.BytesIO(data)
    try:
        return pydicom.dcmread(stream, stop_before_pixels=True, force=True)
    except Exception as exc:  # noqa: BLE001
        raise DsaregInputError(f"is not readable DICOM ({str(exc)[:200]})", field=field_name) from None
    finally:
        stream.close()  # the dataset keeps the stream, which lets go of ``data`` once closed


HEADER_BYTES = 64 * 1024
"""How much of a series' file is read for its header (:func:`series_header`): a CT or MR slice's header is 1–20 KB."""
_PIXEL_TAGS = tuple(tag.to_bytes(2, order) + element.to_bytes(2, order)
                    for order in ("little", "big") for tag in (0x7FE0,) for element in (0x0008, 0x0009, 0x0010))


def series_header(parts, index: int, field_name: str):
    """:func:`parse_header` of ``parts[index]``, from its first :data:`HEADER_BYTES` when its header ends within them
    (a whole head's 440 headers without reading 0.23 GB of pixels). The same dataset either way: the shorter read is
    taken only when pydicom stopped at a pixel data element that lies whole within it; else the whole file is read.

    Raises:
        DsaregInputError: the file is empty or not readable as DICOM (as :func:`parse_header`).
    """
    from ..errors import DsaregInputError
    from .file_parts import file_head

    head = file_head(parts, index, HEADER_BYTES)
    if not head:
        raise DsaregInputError(f"file {index} of the series is empty", field=field_name)
    if len(head) < HEADER_BYTES:  # the whole file
        return parse_header(head, field_name)
    header = _header_within(head)
    return header if header is not None else parse_header(parts[index], field_name)


def series_headers(parts, field_name: str) -> list:
    """:func:`series_header` of every file of ``parts``, in order."""
    return [series_header(parts, index, field_name) for index in range(len(parts))]


def _header_within(head: bytes):
    """The header parsed from ``head``, a file's first bytes, or None where it may not end within them."""
    import pydicom

    stream = io.BytesIO(head)
    try:
        header = pydicom.dcmread(stream, stop_before_pixels=True, force=True)
        at = stream.tell()  # pydicom stops in front of the pixel data's tag
    except Exception:  # noqa: BLE001 - the whole file is read and its error reported
        return None
    finally:
        stream.close()
    return header if at + 4 <= len(head) and head[at:at + 4] in _PIXEL_TAGS else None


def identity_or_none(dataset) -> tuple[DicomIdentity | None, bool]:
    """``(identity, unreadable)``: :func:`identity_of`, with a malformed identity as ``(None, True)``."""
    try:
        return identity_of(dataset), False
    except UnreadableIdentity:
        return None, True


def _header(data) -> object | None:
    """A pydicom Dataset of ``data``'s header when it is DICOM (Part 10 or raw), else None."""
    import pydicom

    if data is None or isinstance(data, (list, tuple)):  # a .rad + .raw pair
        return None
    data = bytes(data)
    if len(data) < 132:
        return None
    try:
        return pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True, force=data[128:132] != b"DICM")
    except Exception:  # noqa: BLE001 - not DICOM: no DICOM context
        return None


def read_sources(ap=None, lat=None, volume=None) -> DicomSources:
    """The identities of DICOM files given as bytes (as to ``load_case``), for callers without a loaded case.

    A case read by :func:`dsareg_engine.io.case.load_case` carries them already (``case.sources``).
    """
    parts = volume if isinstance(volume, PART_LISTS) else ([volume] if volume is not None else [])
    identities = [identity_of(_header(p)) for p in parts]
    return DicomSources(ap=identity_of(_header(ap)), lat=identity_of(_header(lat)),
                        volume=tuple(i for i in identities if i is not None))

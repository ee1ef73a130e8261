"""What hemodynamics asks of the inputs, checked before any work (and by the service at submission): both views
are DICOM runs with frame timing. Light on purpose: pydicom and the timing reader only (the service's validator
processes run it under a memory limit)."""

from __future__ import annotations

import io

from ..errors import DsaregInputError
from ..io.image_io import dicom_number
from .timing import TIMING_ACCEPTED, read_timing, require_timing

VIEWS = ("ap", "lat")


def dicom_timing(data: bytes, field_name: str):
    """``(timing, frames)`` of a DICOM run from its header alone."""
    import pydicom

    header = pydicom.dcmread(io.BytesIO(data), force=True, stop_before_pixels=True)
    count = dicom_number(header, "NumberOfFrames", 1, field_name)
    return require_timing(read_timing(header, count, field_name), count, field_name), count


def check_timed_runs(files) -> None:
    """Refuse, before any work, views that are not timed DICOM runs (a still image, one frame, no frame timing)."""
    for name in VIEWS:
        data = getattr(files, name)
        if not isinstance(data, (bytes, bytearray)) or data[128:132] != b"DICM":
            raise DsaregInputError(f"hemodynamics needs a DICOM XA run, but the {name} view is not DICOM", field=name,
                                   accepted=TIMING_ACCEPTED)
        dicom_timing(bytes(data), name)

"""Pixel data of an XA / RF file in any transfer syntax an archive holds, and what kind of file it is.

**Decoding.** pydicom's handlers first (``Dataset.pixel_array``; pydicom tries every installed plugin in
turn): uncompressed and deflated (pydicom itself), RLE Lossless (pydicom), JPEG baseline, extended,
lossless and JPEG-LS (pylibjpeg-libjpeg, else GDCM), JPEG 2000 (pylibjpeg-openjpeg, else GDCM). When
they all fail on a JPEG syntax, GDCM's own codec decodes the frames directly: libjpeg refuses some
lossy JPEG that archives hold (error -1038: a frame precision of 16 bits in a JPEG extended stream, as
GDCM writes 12-bit data; sequential scans whose spectral bounds are not 0..63), and pydicom's GDCM
plugin declines 12-bit JPEG extended altogether. The warnings pydicom and Pillow raise while reading
(an invalid UID, a value of the wrong length) are kept as the reading's warnings, not printed.

**Modality.** A 2D X-ray run is what the reader takes: Modality XA or RF (X-Ray Angiographic,
X-Ray Radiofluoroscopic, their enhanced forms), a projection radiograph (DX, CR, MG) or a secondary
capture (OT, SC, or no Modality) as exported by a workstation. Cross-sectional modalities (CT, MR,
PET, NM, US and their SOP classes) are refused: their frames are slices or echoes, not an X-ray run
(a CT / MR series is given as the volume instead).
"""

from __future__ import annotations

import contextlib
import warnings as _warnings

import numpy as np

from ..errors import DsaregInputError

JPEG_SYNTAXES = {
    "1.2.840.10008.1.2.4.50", "1.2.840.10008.1.2.4.51", "1.2.840.10008.1.2.4.57", "1.2.840.10008.1.2.4.70",
    "1.2.840.10008.1.2.4.80", "1.2.840.10008.1.2.4.81", "1.2.840.10008.1.2.4.90", "1.2.840.10008.1.2.4.91",
}
PROJECTION_MODALITIES = ("XA", "RF", "DX", "CR", "MG", "OT", "SC")
CROSS_SECTIONAL = {"CT": "CT", "MR": "MR", "PT": "PET", "NM": "nuclear medicine", "US": "ultrasound",
                   "OCT": "OCT", "IVOCT": "OCT"}
CROSS_SECTIONAL_CLASSES = {  # SOP class UID prefixes (Image Storage, Enhanced, Legacy Converted)
    "1.2.840.10008.5.1.4.1.1.2": "CT", "1.2.840.10008.5.1.4.1.1.4": "MR", "1.2.840.10008.5.1.4.1.1.128": "PET",
    "1.2.840.10008.5.1.4.1.1.130": "PET", "1.2.840.10008.5.1.4.1.1.20": "NM", "1.2.840.10008.5.1.4.1.1.6": "US",
    "1.2.840.10008.5.1.4.1.1.3.1": "US",
}
ACCEPTED_MODALITIES = ("an X-ray projection run or image: Modality XA or RF (X-Ray Angiographic / Radiofluoroscopic "
                       "Image Storage, enhanced or not), DX, CR, MG, or a secondary capture (OT, SC); a CT or MR series "
                       "is given as the volume")


@contextlib.contextmanager
def caught_warnings(into: list[str], field_name: str):
    """Python warnings raised inside (pydicom, Pillow) appended to ``into`` as ``"<field>: <message>"`` (each once)."""
    with _warnings.catch_warnings(record=True) as caught:
        _warnings.simplefilter("always")
        try:
            yield into
        finally:
            for item in caught:
                message = str(item.message).split(" Please see <")[0].splitlines()[0] if str(item.message) else ""
                text = f"{field_name}: {message[:200]}"
                if text not in into:
                    into.append(text)


def _sop_kind(sop_class: str) -> str | None:
    for prefix, kind in CROSS_SECTIONAL_CLASSES.items():
        if sop_class == prefix or sop_class.startswith(prefix + "."):
            return kind
    return None


def check_modality(dataset, field_name: str) -> str:
    """The file's Modality (``""`` when absent); a cross-sectional modality or SOP class is an input error."""
    modality = str(getattr(dataset, "Modality", "") or "").strip().upper()
    sop_class = str(getattr(dataset, "SOPClassUID", "") or "").strip()
    kind = CROSS_SECTIONAL.get(modality) or _sop_kind(sop_class)
    if kind is not None:
        try:
            from pydicom.uid import UID

            class_name = UID(sop_class).name if sop_class else "no SOP class"
        except Exception:  # noqa: BLE001 - a malformed UID is still named as written
            class_name = sop_class
        article = "an" if kind in ("MR", "NM", "OCT", "ultrasound") else "a"
        raise DsaregInputError(
            f"is {article} {kind} file (Modality {modality or 'missing'}, {class_name}): its frames are cross-sectional "
            "slices, not an X-ray angiography run", field=field_name, accepted=ACCEPTED_MODALITIES)
    return modality


def _gdcm_frame(frame: bytes, dataset, syntax: str) -> np.ndarray:
    """One encapsulated JPEG-family frame decoded by GDCM's codec (no precision restriction)."""
    import gdcm

    rows, columns = int(dataset.Rows), int(dataset.Columns)
    samples = int(getattr(dataset, "SamplesPerPixel", 1) or 1)
    allocated, stored = int(dataset.BitsAllocated), int(getattr(dataset, "BitsStored", dataset.BitsAllocated))
    signed = int(getattr(dataset, "PixelRepresentation", 0) or 0)
    fragment = gdcm.Fragment()
    fragment.SetByteStringValue(frame)
    fragments = gdcm.SequenceOfFragments.New()
    fragments.AddFragment(fragment)
    element = gdcm.DataElement(gdcm.Tag(0x7FE0, 0x0010))
    element.SetValue(fragments.__ref__())
    image = gdcm.Image()
    image.SetNumberOfDimensions(2)
    image.SetDimensions((columns, rows, 1))
    image.SetDataElement(element)
    photometric = str(getattr(dataset, "PhotometricInterpretation", "MONOCHROME2"))
    image.SetPhotometricInterpretation(gdcm.PhotometricInterpretation(
        gdcm.PhotometricInterpretation.GetPIType(photometric)))
    image.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.GetTSType(syntax)))
    image.SetPixelFormat(gdcm.PixelFormat(samples, allocated, stored, stored - 1, signed))
    buffer = image.GetBuffer()
    if not buffer:
        raise ValueError("GDCM could not decode the frame")
    dtype = np.dtype(f"{'i' if signed else 'u'}{max(1, allocated // 8)}").newbyteorder("<")
    values = np.frombuffer(buffer.encode("utf-8", "surrogateescape"), dtype=dtype)
    shape = (rows, columns) if samples == 1 else (rows, columns, samples)
    return values[: int(np.prod(shape))].reshape(shape)


@contextlib.contextmanager
def _native_stderr_as_warning():
    """What C code writes to the process's stderr inside (GDCM's IJG codec: "Unsupported JPEG data precision 12",
    then it decodes) becomes one Python warning, kept with the reading's warnings."""
    import os
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = " ".join(sink.read(2000).decode("utf-8", "replace").split())
            if text:
                _warnings.warn(f"GDCM decoded the pixel data and said: {text}", UserWarning, stacklevel=3)


def _gdcm_stack(dataset, syntax: str) -> np.ndarray:
    from pydicom.encaps import generate_frames

    n_frames = int(getattr(dataset, "NumberOfFrames", 1) or 1)
    with _native_stderr_as_warning():
        frames = [_gdcm_frame(frame, dataset, syntax)
                  for frame in generate_frames(dataset.PixelData, number_of_frames=n_frames)]
    if len(frames) != n_frames:
        raise ValueError(f"{len(frames)} frames found, {n_frames} declared")
    return frames[0] if n_frames == 1 else np.stack(frames)


def decode_pixels(dataset, field_name: str) -> np.ndarray:
    """The file's frames as stored (``(H, W)``, ``(N, H, W)``, colour with a last axis of samples).

    Raises:
        DsaregInputError: no decoder reads them (naming the transfer syntax and every decoder's reason).
    """
    syntax = str(getattr(getattr(dataset, "file_meta", None), "TransferSyntaxUID", "") or "")
    try:
        return dataset.pixel_array
    except Exception as exc:  # noqa: BLE001 - every plugin failed: GDCM directly, then the error
        failure = str(exc)
    if syntax in JPEG_SYNTAXES:
        try:
            return _gdcm_stack(dataset, syntax)
        except Exception as exc:  # noqa: BLE001
            failure += f"; GDCM: {exc}"
    try:
        from pydicom.uid import UID

        name = f"{UID(syntax).name} ({syntax})" if syntax else "an unknown transfer syntax"
    except Exception:  # noqa: BLE001
        name = syntax
    raise DsaregInputError(f"DICOM pixel data is unreadable: {name}: {' '.join(failure.split())[:300]}",
                           field=field_name,
                           accepted="uncompressed, deflated, RLE, JPEG baseline / extended / lossless, JPEG-LS, "
                                    "JPEG 2000") from None
